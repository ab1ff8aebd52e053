//! Threads that must act on time: the UDP sender at event time and `v2ce listen`'s receiver.
//!
//! On a busy machine a thread at normal priority whose timer fires, or whose socket has data,
//! can wait milliseconds for a core while the other threads finish their slices. The
//! `SCHED_FIFO` realtime policy gives it a core at once. Taking it needs `CAP_SYS_NICE` or an
//! `RLIMIT_RTPRIO` of at least the priority (the systemd unit grants `LimitRTPRIO=10`); the
//! kernel still throttles realtime threads to 95% of a core (`sched_rt_runtime_us`), so a
//! runaway one cannot take a machine.

/// Lowers the calling thread's timer slack to 1 us (Linux), so its sleeps end when asked
/// rather than up to 50 us later.
pub fn precise_timers() {
    // SAFETY: PR_SET_TIMERSLACK takes one integer and only changes this thread's slack.
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0);
    }
}

/// Puts the calling thread under `SCHED_FIFO` at `priority` (1..=99; 0 does nothing and
/// succeeds). The error says why the kernel refused (usually: not permitted).
pub fn make_realtime(priority: u8) -> std::io::Result<()> {
    if priority == 0 {
        return Ok(());
    }
    let param = libc::sched_param {
        sched_priority: i32::from(priority.min(99)),
    };
    // SAFETY: pid 0 is the calling thread; the parameter is a plain struct we own.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// The calling thread's scheduling policy is `SCHED_FIFO`.
pub fn is_realtime() -> bool {
    // SAFETY: pid 0 is the calling thread; the call only reads.
    unsafe { libc::sched_getscheduler(0) == libc::SCHED_FIFO }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn realtime_is_taken_or_refused_with_a_reason_and_only_for_this_thread() {
        let outcome = std::thread::spawn(|| {
            let r = make_realtime(3);
            (r.as_ref().err().map(|e| e.kind()), r.is_ok(), is_realtime())
        })
        .join()
        .unwrap();
        match outcome {
            (None, true, realtime) => assert!(realtime, "taken but not in effect"),
            (Some(kind), false, realtime) => {
                assert!(!realtime);
                assert_eq!(kind, std::io::ErrorKind::PermissionDenied);
            }
            other => panic!("{other:?}"),
        }
        // The test thread itself was not touched.
        assert!(!is_realtime());
        assert!(make_realtime(0).is_ok());
    }
}
