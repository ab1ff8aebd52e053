//! CDR (OMG Common Data Representation, XCDR version 1), the byte layout of ROS 2 messages on
//! DDS and in rosbag2 files: a 4-byte encapsulation header (`00 01` little-endian, `00 00`
//! big-endian, then two option bytes), then each field aligned to its own size counted from the
//! end of that header. Strings are a `u32` length counting a closing NUL, then the bytes and
//! the NUL; sequences a `u32` count, then the elements.
//!
//! [`Reader`] takes bytes from outside: every length is checked against the bytes that are
//! left before anything is allocated, so a message can claim no more memory than it brings.

use std::fmt;

/// Why a message could not be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CdrError(pub String);

impl fmt::Display for CdrError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CdrError {}

fn err<T>(message: impl Into<String>) -> Result<T, CdrError> {
    Err(CdrError(message.into()))
}

/// The encapsulation header of little-endian plain CDR (what v2ce writes).
pub const CDR_LE: [u8; 4] = [0, 1, 0, 0];

/// Writes one message, little-endian, encapsulation header first.
#[derive(Debug, Default)]
pub struct Writer {
    buf: Vec<u8>,
}

impl Writer {
    /// A message with `capacity` bytes reserved after the header.
    pub fn with_capacity(capacity: usize) -> Self {
        let mut buf = Vec::with_capacity(capacity + 4);
        buf.extend_from_slice(&CDR_LE);
        Writer { buf }
    }

    fn align(&mut self, n: usize) {
        let pos = self.buf.len() - 4;
        let pad = (n - pos % n) % n;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    /// A `bool` (one byte, 0 or 1).
    pub fn bool(&mut self, v: bool) {
        self.buf.push(v as u8);
    }

    /// An `int32`.
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `uint32`.
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `uint64`.
    pub fn u64(&mut self, v: u64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `string` (length with its NUL, bytes, NUL).
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    /// A `uint8[]` (count, bytes).
    pub fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.buf.extend_from_slice(b);
    }

    /// The message's bytes, header included.
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Reads one message from its bytes (encapsulation header first).
#[derive(Debug)]
pub struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> Reader<'a> {
    /// A reader over a whole message; refuses a header that is not plain CDR (XCDR1).
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        if data.len() < 4 {
            return err(format!(
                "a message of {} byte(s) is shorter than its CDR header",
                data.len()
            ));
        }
        let little = match [data[0], data[1]] {
            [0, 0] => false,
            [0, 1] => true,
            [a, b] => {
                return err(format!(
                    "representation 0x{a:02x}{b:02x} is not plain CDR (0x0000 or 0x0001)"
                ))
            }
        };
        Ok(Reader {
            data: &data[4..],
            pos: 0,
            little,
        })
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], CdrError> {
        let left = self.data.len() - self.pos;
        if n > left {
            return err(format!(
                "{what}: {n} byte(s) claimed at offset {} but {left} left in the message",
                self.pos + 4
            ));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn align(&mut self, n: usize, what: &str) -> Result<(), CdrError> {
        let pad = (n - self.pos % n) % n;
        self.take(pad, what).map(|_| ())
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], CdrError> {
        self.align(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        if !self.little {
            a.reverse();
        }
        Ok(a)
    }

    /// A `bool`; a byte other than 0 or 1 is an error.
    pub fn bool(&mut self, what: &str) -> Result<bool, CdrError> {
        match self.take(1, what)?[0] {
            0 => Ok(false),
            1 => Ok(true),
            b => err(format!("{what}: {b} is not a boolean")),
        }
    }

    /// An `int32`.
    pub fn i32(&mut self, what: &str) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    /// A `uint32`.
    pub fn u32(&mut self, what: &str) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    /// A `uint64`.
    pub fn u64(&mut self, what: &str) -> Result<u64, CdrError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    /// A `string` of at most `max` bytes, UTF-8, closed by its NUL.
    pub fn string(&mut self, what: &str, max: usize) -> Result<String, CdrError> {
        let n = self.u32(what)? as usize;
        if n == 0 || n - 1 > max {
            return err(format!(
                "{what}: a string length of {n} (expected 1 to {})",
                max + 1
            ));
        }
        let b = self.take(n, what)?;
        if b[n - 1] != 0 {
            return err(format!("{what}: the string does not end with NUL"));
        }
        match std::str::from_utf8(&b[..n - 1]) {
            Ok(s) => Ok(s.to_owned()),
            Err(_) => err(format!("{what}: the string is not UTF-8")),
        }
    }

    /// A `uint8[]`, borrowed from the message (its count checked against what is left).
    pub fn bytes(&mut self, what: &str) -> Result<&'a [u8], CdrError> {
        let n = self.u32(what)? as usize;
        self.take(n, what)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_round_trip_with_alignment() {
        let mut w = Writer::with_capacity(0);
        w.bool(true);
        w.u64(7);
        w.string("evt3");
        w.bool(false);
        w.bytes(&[1, 2, 3]);
        w.i32(-5);
        let b = w.finish();
        // bool at 0, u64 aligned to 8, string length at 16.
        assert_eq!(&b[4 + 8..4 + 16], &7u64.to_le_bytes());
        let mut r = Reader::new(&b).unwrap();
        assert!(r.bool("a").unwrap());
        assert_eq!(r.u64("b").unwrap(), 7);
        assert_eq!(r.string("c", 10).unwrap(), "evt3");
        assert!(!r.bool("d").unwrap());
        assert_eq!(r.bytes("e").unwrap(), &[1, 2, 3]);
        assert_eq!(r.i32("f").unwrap(), -5);
    }

    #[test]
    fn big_endian_messages_are_read() {
        let b = [0, 0, 0, 0, 0, 0, 0, 9, 0, 0, 0, 2, 0xAB, 0xCD];
        let mut r = Reader::new(&b).unwrap();
        assert_eq!(r.u32("a").unwrap(), 9);
        assert_eq!(r.bytes("b").unwrap(), &[0xAB, 0xCD]);
    }

    #[test]
    fn lengths_past_the_message_are_errors_not_allocations() {
        let mut w = Writer::with_capacity(0);
        w.u32(u32::MAX);
        let b = w.finish();
        assert!(Reader::new(&b).unwrap().bytes("events").is_err());
        assert!(Reader::new(&b).unwrap().string("s", 1 << 20).is_err());
        assert!(Reader::new(&[0, 1]).is_err());
        assert!(Reader::new(&[0, 7, 0, 0]).is_err());
        let mut r = Reader::new(&[0, 1, 0, 0, 2]).unwrap();
        assert!(r.bool("b").is_err());
    }
}
