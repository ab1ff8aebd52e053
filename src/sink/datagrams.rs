//! Datagrams queued back to back and handed to the kernel many per system call (`sendmmsg` on
//! Linux, one `send` each elsewhere), each counted on its own: sent, refused (no receiver on
//! the port) or dropped (full send buffer, network down). At a million events a second a
//! sender makes a few thousand datagrams a second; one call for all that fall due at one
//! wake costs a fraction of a call each.
//!
//! On Linux, where asked (`segment_offload`), runs of datagrams of one length (and a shorter
//! one closing the run) also leave as one message with generic segmentation offload
//! (`UDP_SEGMENT`, Linux 4.18): the kernel builds one packet for the run and cuts it into the
//! same datagrams, sparing most of the per-datagram work of its network stack. A kernel or
//! route without it (an old kernel, a device without checksum offload) refuses the first such
//! message; the run is then sent datagram by datagram, and so is every later one. It is not
//! the default: on a loaded machine a receiver on loopback got datagrams out of order with it
//! (twice in about four loaded runs of the `listen` tests, never in four without it).

use std::net::UdpSocket;

use super::SinkStats;

/// Most datagrams one call takes (the kernel's `UIO_MAXIOV`).
const MAX_PER_CALL: usize = 1024;

/// Most datagrams in one segmented message (the kernel's `UDP_MAX_SEGMENTS` before 5.x).
#[cfg(target_os = "linux")]
const MAX_SEGMENTS: usize = 64;

/// Most payload bytes in one segmented message (under the 64 KiB of an IP packet, with room
/// for the headers).
#[cfg(target_os = "linux")]
const MAX_SEGMENTED_BYTES: usize = 60_000;

/// Encoded datagrams waiting for one send call.
#[derive(Debug, Default)]
pub(crate) struct Datagrams {
    /// Every payload, back to back.
    bytes: Vec<u8>,
    /// Per datagram: where its payload ends in `bytes`, and how many events it holds.
    ends: Vec<(usize, usize)>,
    /// Segmentation offload: untried (`None`), taken, or refused by the kernel or not asked
    /// for (`Some(false)`).
    #[cfg(target_os = "linux")]
    offload: Option<bool>,
}

impl Datagrams {
    /// An empty queue; `offload`: send runs of one length with segmentation offload.
    pub(crate) fn new(offload: bool) -> Self {
        #[cfg(not(target_os = "linux"))]
        let _ = offload;
        Datagrams {
            #[cfg(target_os = "linux")]
            offload: (!offload).then_some(false),
            ..Datagrams::default()
        }
    }

    /// Queues a datagram of `events` events whose payload `encode` appends to the buffer it is
    /// given; the queue must be flushed first when [`Datagrams::full`] says so.
    pub(crate) fn push(&mut self, events: usize, encode: impl FnOnce(&mut Vec<u8>)) {
        encode(&mut self.bytes);
        self.ends.push((self.bytes.len(), events));
    }

    /// As many datagrams are queued as one call takes.
    pub(crate) fn full(&self) -> bool {
        self.ends.len() >= MAX_PER_CALL
    }

    /// Sends every queued datagram on the connected `socket`, counting each in `stats`, and
    /// empties the queue. Never waits: the socket is non-blocking.
    pub(crate) fn flush(&mut self, socket: &UdpSocket, stats: &mut SinkStats) {
        let mut done = 0;
        while done < self.ends.len() {
            match self.send_from(socket, done) {
                Ok(n) => {
                    for k in done..done + n {
                        let (len, events) = self.datagram(k);
                        stats.messages_sent += 1;
                        stats.events_sent += events as u64;
                        stats.bytes_sent += len as u64;
                    }
                    done += n;
                }
                // The first datagram (or run) of the rest was not taken: count it and go on
                // with the next (a receiver that is gone is reported once, on one datagram).
                Err((e, n)) => {
                    for k in done..done + n {
                        let (_, events) = self.datagram(k);
                        stats.messages_dropped += 1;
                        if e.kind() == std::io::ErrorKind::ConnectionRefused {
                            stats.events_refused += events as u64;
                        } else {
                            stats.events_dropped += events as u64;
                        }
                    }
                    done += n;
                }
            }
        }
        self.bytes.clear();
        self.ends.clear();
    }

    /// Datagram `k`'s payload length and event count.
    fn datagram(&self, k: usize) -> (usize, usize) {
        let start = if k == 0 { 0 } else { self.ends[k - 1].0 };
        (self.ends[k].0 - start, self.ends[k].1)
    }

    #[cfg_attr(target_os = "linux", allow(dead_code))]
    fn payload(&self, k: usize) -> &[u8] {
        let start = if k == 0 { 0 } else { self.ends[k - 1].0 };
        &self.bytes[start..self.ends[k].0]
    }

    /// The datagrams from `k` that can leave as one segmented message: a run of one length,
    /// closed by at most one shorter datagram.
    #[cfg(target_os = "linux")]
    fn run(&self, k: usize) -> usize {
        let (len, _) = self.datagram(k);
        let mut n = 1;
        let mut bytes = len;
        while k + n < self.ends.len() && n < MAX_SEGMENTS {
            let (next, _) = self.datagram(k + n);
            if next > len || bytes + next > MAX_SEGMENTED_BYTES {
                break;
            }
            n += 1;
            bytes += next;
            if next < len {
                break;
            }
        }
        n
    }

    /// Sends datagrams `from..`, as many as the kernel takes in one call: `Ok(n)` with `n >= 1`
    /// datagrams sent, or the error of the first message and how many datagrams it held.
    #[cfg(target_os = "linux")]
    fn send_from(
        &mut self,
        socket: &UdpSocket,
        from: usize,
    ) -> Result<usize, (std::io::Error, usize)> {
        use std::os::fd::AsRawFd;
        let segment = self.offload != Some(false);
        // The messages: each a run of datagrams (one datagram without offload).
        let mut runs = Vec::new();
        let mut k = from;
        while k < self.ends.len() && runs.len() < MAX_PER_CALL {
            let n = if segment { self.run(k) } else { 1 };
            runs.push((k, n));
            k += n;
        }
        let mut iov: Vec<libc::iovec> = runs
            .iter()
            .map(|&(k, n)| {
                let start = if k == 0 { 0 } else { self.ends[k - 1].0 };
                let p = &self.bytes[start..self.ends[k + n - 1].0];
                libc::iovec {
                    iov_base: p.as_ptr() as *mut libc::c_void,
                    iov_len: p.len(),
                }
            })
            .collect();
        // One control message per run of two or more: the segment size.
        // SAFETY: CMSG_SPACE is arithmetic on its argument.
        let space = unsafe { libc::CMSG_SPACE(std::mem::size_of::<u16>() as u32) } as usize;
        let mut control = vec![0u64; runs.len() * space.div_ceil(8)];
        let mut headers: Vec<libc::mmsghdr> = Vec::with_capacity(runs.len());
        for (m, (v, &(k, n))) in iov.iter_mut().zip(&runs).enumerate() {
            // SAFETY: an all-zero msghdr is a valid "no address, no control data" header.
            let mut h: libc::mmsghdr = unsafe { std::mem::zeroed() };
            h.msg_hdr.msg_iov = v;
            h.msg_hdr.msg_iovlen = 1;
            if n > 1 {
                let size = self.datagram(k).0 as u16;
                let buf = control[m * space.div_ceil(8)..].as_mut_ptr();
                h.msg_hdr.msg_control = buf.cast();
                h.msg_hdr.msg_controllen = space as _;
                // SAFETY: the header's control buffer is `space` bytes of `control`, 8-byte
                // aligned, room for one cmsghdr with a u16 (CMSG_SPACE of it); CMSG_FIRSTHDR
                // of a buffer that size is non-null.
                unsafe {
                    let c = libc::CMSG_FIRSTHDR(&h.msg_hdr);
                    (*c).cmsg_level = libc::SOL_UDP;
                    (*c).cmsg_type = libc::UDP_SEGMENT;
                    (*c).cmsg_len = libc::CMSG_LEN(std::mem::size_of::<u16>() as u32) as _;
                    std::ptr::write_unaligned(libc::CMSG_DATA(c).cast::<u16>(), size);
                }
            }
            headers.push(h);
        }
        // SAFETY: `headers` points at `runs.len()` headers, each at one iovec over a live
        // slice of `self.bytes` and at most one control buffer in `control`; none outlives
        // this call, and the kernel only reads them (and writes each header's `msg_len`).
        let sent = unsafe {
            libc::sendmmsg(
                socket.as_raw_fd(),
                headers.as_mut_ptr(),
                runs.len() as libc::c_uint,
                0,
            )
        };
        let first = runs.first().map_or(1, |&(_, n)| n);
        match sent {
            n if n > 0 => {
                if runs[..n as usize].iter().any(|&(_, n)| n > 1) {
                    self.offload = Some(true);
                }
                Ok(runs[..n as usize].iter().map(|&(_, n)| n).sum())
            }
            0 => Err((std::io::ErrorKind::WouldBlock.into(), first)),
            _ => {
                let e = std::io::Error::last_os_error();
                let unsupported = matches!(
                    e.raw_os_error(),
                    Some(libc::EIO | libc::EINVAL | libc::ENOPROTOOPT | libc::EOPNOTSUPP)
                );
                if first > 1 && unsupported && self.offload.is_none() {
                    // No offload here: this run and every later one datagram by datagram.
                    tracing::debug!(
                        "UDP segmentation offload refused ({e}): one datagram a message"
                    );
                    self.offload = Some(false);
                    return self.send_from(socket, from);
                }
                Err((e, first))
            }
        }
    }

    /// One `send` per datagram where `sendmmsg` does not exist.
    #[cfg(not(target_os = "linux"))]
    fn send_from(
        &mut self,
        socket: &UdpSocket,
        from: usize,
    ) -> Result<usize, (std::io::Error, usize)> {
        socket
            .send(self.payload(from))
            .map(|_| 1)
            .map_err(|e| (e, 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_datagram_arrives_whole_and_is_counted_once() {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        rx.set_read_timeout(Some(std::time::Duration::from_millis(500)))
            .unwrap();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        tx.set_nonblocking(true).unwrap();
        tx.connect(rx.local_addr().unwrap()).unwrap();
        let mut q = Datagrams::default();
        let mut stats = SinkStats::default();
        // Datagrams of different lengths, in as many calls as a receive buffer holds.
        let count = 150;
        for k in 0..count {
            q.push(k % 5 + 1, |buf| {
                buf.extend(std::iter::repeat_n((k % 251) as u8, k % 5 + 1))
            });
        }
        q.flush(&tx, &mut stats);
        assert!(q.ends.is_empty() && q.bytes.is_empty());
        let mut buf = [0u8; 64];
        for k in 0..count {
            let n = rx.recv(&mut buf).unwrap();
            assert_eq!(
                &buf[..n],
                vec![(k % 251) as u8; k % 5 + 1].as_slice(),
                "{k}"
            );
        }
        assert_eq!(stats.messages_sent, count as u64);
        let events: u64 = (0..count).map(|k| (k % 5 + 1) as u64).sum();
        assert_eq!(stats.events_sent, events);
        assert_eq!(stats.bytes_sent, events);
        // A full queue is one call's worth; more are sent in several calls, each counted once
        // (a receiver that reads nothing loses what its buffer cannot hold, not the sender).
        for _ in 0..MAX_PER_CALL {
            assert!(!q.full());
            q.push(1, |buf| buf.push(7));
        }
        assert!(q.full());
        q.push(1, |buf| buf.push(7));
        let mut stats = SinkStats::default();
        q.flush(&tx, &mut stats);
        assert_eq!(
            stats.messages_sent + stats.messages_dropped,
            MAX_PER_CALL as u64 + 1
        );
        assert!(stats.messages_sent > 0);
    }

    /// Runs of one length closed by a shorter datagram leave as segmented messages where the
    /// kernel takes them; the receiver still gets every datagram whole, in order, and each is
    /// counted once.
    #[test]
    fn runs_of_one_length_arrive_as_the_same_datagrams() {
        for offload in [true, false] {
            runs_arrive_whole(offload);
        }
    }

    fn runs_arrive_whole(offload: bool) {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        rx.set_read_timeout(Some(std::time::Duration::from_millis(500)))
            .unwrap();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        tx.set_nonblocking(true).unwrap();
        tx.connect(rx.local_addr().unwrap()).unwrap();
        let mut q = Datagrams::new(offload);
        let mut stats = SinkStats::default();
        // Runs of 1 to 70 datagrams of 40 bytes (past MAX_SEGMENTS too), each closed by a
        // 13-byte one, then a lone longer one: payloads numbered so order and length show.
        let mut sent = Vec::new();
        for run in [1usize, 2, 7, 64, 70] {
            sent.extend(std::iter::repeat_n(40, run));
            sent.push(13);
            sent.push(52);
        }
        for (k, &len) in sent.iter().enumerate() {
            q.push(1, |buf| {
                buf.extend(std::iter::repeat_n((k % 251) as u8, len))
            });
        }
        q.flush(&tx, &mut stats);
        assert_eq!(stats.messages_sent, sent.len() as u64);
        assert_eq!(stats.bytes_sent, sent.iter().sum::<usize>() as u64);
        let mut buf = [0u8; 128];
        for (k, &len) in sent.iter().enumerate() {
            let n = rx.recv(&mut buf).unwrap();
            assert_eq!(&buf[..n], vec![(k % 251) as u8; len].as_slice(), "{k}");
        }
        #[cfg(target_os = "linux")]
        match q.offload {
            Some(true) => {}
            Some(false) => {
                println!("this kernel refused UDP segmentation offload: sent one by one")
            }
            None => panic!("no run was offered for offload"),
        }
    }

    #[test]
    fn a_receiver_that_is_gone_is_counted_not_waited_for() {
        // A port nobody listens on: the first datagram's ICMP reply refuses a later one.
        let gone = UdpSocket::bind("127.0.0.1:0").unwrap();
        let addr = gone.local_addr().unwrap();
        drop(gone);
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        tx.set_nonblocking(true).unwrap();
        tx.connect(addr).unwrap();
        let mut q = Datagrams::default();
        let mut stats = SinkStats::default();
        for _ in 0..3 {
            for _ in 0..10 {
                q.push(2, |buf| buf.extend_from_slice(&[1, 2]));
            }
            q.flush(&tx, &mut stats);
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        assert_eq!(stats.messages_sent + stats.messages_dropped, 30);
        assert_eq!(
            stats.events_sent + stats.events_refused + stats.events_dropped,
            60
        );
        assert!(stats.events_refused > 0, "{stats:?}");
    }
}
