//! Bounds on what comes from outside the process: frame and sensor sizes, durations, counts of
//! intervals. Every reader, flag and config key that takes such a value checks it here, before
//! anything is allocated or a loop is started on it, so a hostile file or a typo gets a clear
//! error instead of a panic, an abort for memory, or a run that never ends.

use std::time::Duration;

use crate::error::{Error, Result};

/// The largest frame or sensor side, pixels (8192: twice the widest event sensor published,
/// and beyond any webcam's 4K; a 8192 x 8192 pixel model takes about 2.3 GB).
pub const MAX_SIDE: u32 = 8192;

/// The longest duration or period taken in seconds (about 3.2 years).
pub const MAX_SECONDS: f64 = 1e8;

/// The most frame intervals one evaluation builds (160 MB of intervals).
pub const MAX_INTERVALS: u64 = 10_000_000;

/// The largest storage chunk a file may declare, bytes (256 MiB: the readers decode a chunk
/// whole; DSEC's and this project's `.h5` chunks are under 1 MiB).
pub const MAX_CHUNK_BYTES: u64 = 256 << 20;

/// The largest DDS sample (one ROS 2 message) that crosses from the DDS transport's process:
/// the largest image a ROS 2 source takes ([`MAX_SIDE`] squared, 4 bytes a pixel) and 1 MiB
/// more for its header; larger frames on the pipe end the transport.
pub const MAX_DDS_SAMPLE_BYTES: u64 = (MAX_SIDE as u64) * (MAX_SIDE as u64) * 4 + (1 << 20);

/// The data segment (heap, anonymous mappings, stacks) of the DDS transport's process: a
/// sample as the transport reassembles it, its copy on the way out, and 250 MiB for the
/// participant itself. The transport sizes a fragmented sample's buffer from what its sender
/// declares, before anyone can look at it: a claim past this cap ends that process, not the
/// daemon ([`crate::ros2::host`]).
pub const DDS_HOST_MEMORY: u64 = 2 * MAX_DDS_SAMPLE_BYTES + (250 << 20);

/// Most threads `V2CE_THREADS` may ask for (each is a helper thread with its own stack).
pub const MAX_THREADS: usize = 256;

/// Checks a frame or sensor size of `what`: both sides from 1 to [`MAX_SIDE`].
pub fn frame_size(what: &'static str, width: u32, height: u32) -> Result<()> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(Error::invalid(
            what,
            format!("{width} x {height}: each side must be 1 to {MAX_SIDE} pixels"),
        ));
    }
    Ok(())
}

/// A duration of `what` given in seconds: finite, from 0 (when `zero` is allowed; else
/// above 0) to [`MAX_SECONDS`].
pub fn seconds(what: &'static str, value: f64, zero: bool) -> Result<Duration> {
    let low_ok = if zero { value >= 0.0 } else { value > 0.0 };
    if !(value.is_finite() && low_ok && value <= MAX_SECONDS) {
        return Err(Error::invalid(
            what,
            format!(
                "{} s: must be {} to {MAX_SECONDS:e} s",
                number(value),
                if zero { "0" } else { "above 0" }
            ),
        ));
    }
    Ok(Duration::from_secs_f64(value))
}

/// Checks a frame rate of `what`: finite, above 0, at most 1,000,000 fps (frames would share a
/// microsecond), and a period of at most [`MAX_SECONDS`].
pub fn frame_rate(what: &'static str, fps: f64) -> Result<()> {
    if !(fps.is_finite() && fps > 0.0 && fps <= 1e6 && 1.0 / fps <= MAX_SECONDS) {
        return Err(Error::invalid(
            what,
            format!(
                "{} frames per second: must be above {:e} and at most 1,000,000",
                number(fps),
                1.0 / MAX_SECONDS
            ),
        ));
    }
    Ok(())
}

/// Memory the process may still take, bytes: the least of the system's available memory
/// (`MemAvailable`), what the address-space limit (`RLIMIT_AS`, as under `ulimit -v`) leaves,
/// and what the cgroup's `memory.max` leaves (systemd's `MemoryMax`, a container's limit).
/// `None` when none of them can be read.
pub fn memory_available() -> Option<u64> {
    let read = |p: &str| std::fs::read_to_string(p).ok();
    let mut least: Option<u64> = None;
    let mut take = |v: u64| least = Some(least.map_or(v, |l| l.min(v)));
    if let Some(info) = read("/proc/meminfo") {
        let kib = info
            .lines()
            .find_map(|l| l.strip_prefix("MemAvailable:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok());
        if let Some(kib) = kib {
            take(kib * 1024);
        }
    }
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct it is given.
    let ok = unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } == 0;
    if ok && limit.rlim_cur != libc::RLIM_INFINITY {
        let taken = crate::process::virtual_bytes().unwrap_or(0);
        take(limit.rlim_cur.saturating_sub(taken));
    }
    let max = read("/sys/fs/cgroup/memory.max").and_then(|s| s.trim().parse::<u64>().ok());
    if let Some(max) = max {
        let current = read("/sys/fs/cgroup/memory.current")
            .and_then(|s| s.trim().parse::<u64>().ok())
            .unwrap_or(0);
        take(max.saturating_sub(current));
    }
    least
}

/// Checks, before allocating, that `bytes` for `what` fit in [`memory_available`].
pub fn memory(what: &'static str, bytes: u64, purpose: &str) -> Result<()> {
    match memory_available() {
        Some(free) if bytes > free => Err(Error::invalid(
            what,
            format!(
                "{purpose} needs about {:.1} GB, and {:.1} GB is available (the least of free \
                 memory, the address-space limit and the cgroup's memory limit)",
                bytes as f64 / 1e9,
                free as f64 / 1e9
            ),
        )),
        _ => Ok(()),
    }
}

/// Growth below this many bytes is not checked against [`memory_available`] (reading it
/// costs a few microseconds; small growth cannot take what is left).
const CHECKED_GROWTH: u64 = 1 << 20;

/// A buffer grows by at most this share of the memory left: what it holds is then sorted,
/// copied and encoded by others, which need their own.
const GROWTH_SHARE: u64 = 4;

/// Whether `bytes` more fit in what is left (see [`GROWTH_SHARE`]).
fn growth_fits(bytes: u64) -> bool {
    bytes < CHECKED_GROWTH
        || memory_available().is_none_or(|free| bytes.saturating_mul(GROWTH_SHARE) <= free)
}

/// Makes room in `v` for one more element (doubling, as `push` does) where memory allows it
/// ([`memory_available`], and the allocator itself): `false`, with nothing allocated, where
/// it does not. For buffers whose length comes from outside (the events a frame produces),
/// so that too many give a clear error instead of an abort.
pub fn room_for_one<T>(v: &mut Vec<T>) -> bool {
    if v.len() < v.capacity() {
        return true;
    }
    let extra = v.capacity().max(256);
    let bytes = (extra as u64).saturating_mul(std::mem::size_of::<T>() as u64);
    growth_fits(bytes) && v.try_reserve(extra).is_ok()
}

/// Memory that buffers filled together (one frame's events, in bands stepped on several
/// threads) may still grow by, shared by them: a share (see [`GROWTH_SHARE`]) of what was
/// left when one first had to grow. Read and taken only when a buffer grows, so a frame whose
/// buffers have room pays nothing.
#[derive(Debug)]
pub struct Budget(std::sync::atomic::AtomicU64);

/// A [`Budget`] not read yet.
const UNREAD: u64 = u64::MAX;

impl Budget {
    /// A share of the memory left when first needed (unbounded where it cannot be read).
    pub fn of_memory_left() -> Self {
        Budget(std::sync::atomic::AtomicU64::new(UNREAD))
    }

    /// Makes room in `v` for one more element (doubling) out of this budget, where it and
    /// the allocator allow: `false`, nothing allocated, where they do not.
    pub fn room_for_one<T>(&self, v: &mut Vec<T>) -> bool {
        use std::sync::atomic::Ordering::Relaxed;
        if v.len() < v.capacity() {
            return true;
        }
        if self.0.load(Relaxed) == UNREAD {
            let left = memory_available().map_or(UNREAD - 1, |free| free / GROWTH_SHARE);
            let _ = self.0.compare_exchange(UNREAD, left, Relaxed, Relaxed);
        }
        let extra = v.capacity().max(256);
        let bytes = (extra as u64).saturating_mul(std::mem::size_of::<T>() as u64);
        let taken = self
            .0
            .fetch_update(Relaxed, Relaxed, |left| left.checked_sub(bytes));
        taken.is_ok() && v.try_reserve(extra).is_ok()
    }
}

/// Makes room in `v` for `n` more elements where memory allows it (see [`room_for_one`]).
pub fn room_for<T>(v: &mut Vec<T>, n: usize) -> bool {
    if v.capacity() - v.len() >= n {
        return true;
    }
    // What the allocator is asked for: the buffer doubles, or grows to the length asked.
    let grown = v
        .capacity()
        .saturating_mul(2)
        .max(v.len().saturating_add(n));
    let bytes = ((grown - v.capacity()) as u64).saturating_mul(std::mem::size_of::<T>() as u64);
    growth_fits(bytes) && v.try_reserve(n).is_ok()
}

/// The slowest and fastest replay of a recording, times real time.
pub const REPLAY_SPEEDS: (f64, f64) = (1e-3, 1e6);

/// Checks a replay speed of `what`: from [`REPLAY_SPEEDS`]'s 1/1000 (a second of recording
/// over 17 minutes) to 1,000,000 times real time.
pub fn replay_speed(what: &'static str, speed: f64) -> Result<()> {
    let (low, high) = REPLAY_SPEEDS;
    if !(speed.is_finite() && (low..=high).contains(&speed)) {
        return Err(Error::invalid(
            what,
            format!(
                "{}: must be {low} to {} times real time",
                number(speed),
                number(high)
            ),
        ));
    }
    Ok(())
}

/// `v` as a person reads it: plain, or in scientific notation when huge or tiny.
fn number(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// Checks a count of frame intervals about to be built for `what`.
pub fn intervals(what: &'static str, count: f64) -> Result<()> {
    if !(count.is_finite() && count <= MAX_INTERVALS as f64) {
        return Err(Error::invalid(
            what,
            format!(
                "{count:.0} frame intervals, more than the {MAX_INTERVALS} one run takes; use a \
                 lower rate or a shorter stretch"
            ),
        ));
    }
    Ok(())
}

/// Parses `WIDTHxHEIGHT` (each 1..=65535).
pub fn parse_size(text: &str) -> Result<(u16, u16)> {
    let parsed = text
        .split_once(['x', 'X'])
        .and_then(|(w, h)| Some((w.trim().parse::<u16>().ok()?, h.trim().parse::<u16>().ok()?)));
    match parsed {
        Some((w, h)) if w > 0 && h > 0 => {
            frame_size("size", w.into(), h.into())?;
            Ok((w, h))
        }
        _ => Err(Error::invalid(
            "size",
            format!("{text:?} (expected WIDTHxHEIGHT, e.g. 346x260)"),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_durations_and_counts_are_bounded() {
        assert!(frame_size("f", 346, 260).is_ok());
        assert!(frame_size("f", 8192, 8192).is_ok());
        for (w, h) in [(0, 1), (1, 0), (8193, 1), (16000, 16000), (65535, 65535)] {
            let e = frame_size("frame", w, h).unwrap_err().to_string();
            assert!(e.contains("8192"), "{e}");
        }
        assert_eq!(
            seconds("d", 1.5, false).unwrap(),
            Duration::from_millis(1500)
        );
        assert_eq!(seconds("d", 0.0, true).unwrap(), Duration::ZERO);
        for v in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e20, 1e308] {
            assert!(seconds("d", v, false).is_err(), "{v}");
        }
        assert!(seconds("d", -0.5, true).is_err());
        assert!(intervals("i", 1e6).is_ok());
        assert!(intervals("i", 3.6e9).is_err());
        assert!(intervals("i", f64::NAN).is_err());
    }
}
