//! Datagrams queued back to back and handed to the kernel many per system call (`sendmmsg` on
//! Linux, one `send` each elsewhere), each counted on its own: sent, refused (no receiver on
//! the port) or dropped (full send buffer, network down). At a million events a second a
//! sender makes a few thousand datagrams a second; one call for all that fall due at one
//! wake costs a fraction of a call each.

use std::net::UdpSocket;

use super::SinkStats;

/// Most datagrams one call takes (the kernel's `UIO_MAXIOV`).
const MAX_PER_CALL: usize = 1024;

/// Encoded datagrams waiting for one send call.
#[derive(Debug, Default)]
pub(crate) struct Datagrams {
    /// Every payload, back to back.
    bytes: Vec<u8>,
    /// Per datagram: where its payload ends in `bytes`, and how many events it holds.
    ends: Vec<(usize, usize)>,
}

impl Datagrams {
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
                // The first datagram of the rest was not taken: count it and go on with the
                // next (a receiver that is gone is reported once, on one datagram).
                Err(e) => {
                    let (_, events) = self.datagram(done);
                    stats.messages_dropped += 1;
                    if e.kind() == std::io::ErrorKind::ConnectionRefused {
                        stats.events_refused += events as u64;
                    } else {
                        stats.events_dropped += events as u64;
                    }
                    done += 1;
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

    fn payload(&self, k: usize) -> &[u8] {
        let start = if k == 0 { 0 } else { self.ends[k - 1].0 };
        &self.bytes[start..self.ends[k].0]
    }

    /// Sends datagrams `from..`, as many as the kernel takes in one call; `Ok(n)` with `n >= 1`
    /// sent, or the error of datagram `from`.
    #[cfg(target_os = "linux")]
    fn send_from(&self, socket: &UdpSocket, from: usize) -> std::io::Result<usize> {
        use std::os::fd::AsRawFd;
        let count = self.ends.len() - from;
        let mut iov: Vec<libc::iovec> = (from..self.ends.len())
            .map(|k| {
                let p = self.payload(k);
                libc::iovec {
                    iov_base: p.as_ptr() as *mut libc::c_void,
                    iov_len: p.len(),
                }
            })
            .collect();
        let mut headers: Vec<libc::mmsghdr> = iov
            .iter_mut()
            .map(|v| {
                // SAFETY: an all-zero msghdr is a valid "no address, no control data" header.
                let mut h: libc::mmsghdr = unsafe { std::mem::zeroed() };
                h.msg_hdr.msg_iov = v;
                h.msg_hdr.msg_iovlen = 1;
                h
            })
            .collect();
        // SAFETY: `headers` points at `count` headers, each at one iovec over a live slice of
        // `self.bytes`; none outlives this call, and the kernel only reads them (and writes
        // each header's `msg_len`).
        let sent = unsafe {
            libc::sendmmsg(
                socket.as_raw_fd(),
                headers.as_mut_ptr(),
                count as libc::c_uint,
                0,
            )
        };
        match sent {
            n if n > 0 => Ok(n as usize),
            0 => Err(std::io::ErrorKind::WouldBlock.into()),
            _ => Err(std::io::Error::last_os_error()),
        }
    }

    /// One `send` per datagram where `sendmmsg` does not exist.
    #[cfg(not(target_os = "linux"))]
    fn send_from(&self, socket: &UdpSocket, from: usize) -> std::io::Result<usize> {
        socket.send(self.payload(from)).map(|_| 1)
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
