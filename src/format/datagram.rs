//! The UDP datagram word layouts that neuromorphic receivers listen for: how one event becomes
//! bytes in a datagram, and back. The sockets are [`crate::sink::udp`]'s and
//! `v2ce listen`'s.
//!
//! Every layout is little-endian and a datagram holds whole events.
//!
//! | format | bytes per event | layout |
//! |---|---|---|
//! | `spif` | 4 (8 with timestamps) | `u32`: bit 31 = 1 when no timestamp word follows, bits 30..16 x, bit 15 polarity (1 = ON), bits 14..0 y; with timestamps bit 31 = 0 and a `u32` word of `t mod 2^32` us follows |
//! | `t64_x16_y16_on8` | 13 | `u64` t, `u16` x, `u16` y, `u8` on (faery) |
//! | `t32_x16_y15_on1` | 8 | `u32` `t mod 2^32`, `u16` x, `u16` `y << 1 \| on` (faery) |

use crate::error::{Error, Result};
use crate::event::Event;

/// The datagram formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum UdpFormat {
    /// SPIF/aestream 32-bit words without timestamps.
    #[default]
    Spif,
    /// SPIF/aestream words, each followed by a 32-bit timestamp word.
    SpifTimestamped,
    /// faery's `t64_x16_y16_on8`.
    T64X16Y16On8,
    /// faery's `t32_x16_y15_on1`.
    T32X16Y15On1,
}

impl UdpFormat {
    /// Parses `spif`, `spif_timestamped`, `t64_x16_y16_on8` or `t32_x16_y15_on1`.
    pub fn from_name(name: &str) -> Result<Self> {
        Ok(match name {
            "spif" => UdpFormat::Spif,
            "spif_timestamped" | "spif-timestamped" => UdpFormat::SpifTimestamped,
            "t64_x16_y16_on8" => UdpFormat::T64X16Y16On8,
            "t32_x16_y15_on1" => UdpFormat::T32X16Y15On1,
            _ => {
                return Err(Error::invalid(
                    "UDP format",
                    format!(
                        "'{name}' (expected spif, spif_timestamped, t64_x16_y16_on8 or t32_x16_y15_on1)"
                    ),
                ))
            }
        })
    }

    /// The name [`UdpFormat::from_name`] accepts.
    pub fn name(self) -> &'static str {
        match self {
            UdpFormat::Spif => "spif",
            UdpFormat::SpifTimestamped => "spif_timestamped",
            UdpFormat::T64X16Y16On8 => "t64_x16_y16_on8",
            UdpFormat::T32X16Y15On1 => "t32_x16_y15_on1",
        }
    }

    /// Bytes one event takes.
    pub fn event_bytes(self) -> usize {
        match self {
            UdpFormat::Spif => 4,
            UdpFormat::SpifTimestamped | UdpFormat::T32X16Y15On1 => 8,
            UdpFormat::T64X16Y16On8 => 13,
        }
    }

    /// Largest column and row the format holds.
    pub fn max_pixel(self) -> (u16, u16) {
        match self {
            UdpFormat::Spif | UdpFormat::SpifTimestamped => (0x7FFF, 0x7FFF),
            UdpFormat::T64X16Y16On8 => (u16::MAX, u16::MAX),
            UdpFormat::T32X16Y15On1 => (u16::MAX, 0x7FFF),
        }
    }

    /// Appends one event's bytes.
    pub fn encode(self, e: &Event, out: &mut Vec<u8>) {
        match self {
            UdpFormat::Spif | UdpFormat::SpifTimestamped => {
                let stamped = self == UdpFormat::SpifTimestamped;
                let w = ((!stamped as u32) << 31)
                    | ((e.x as u32 & 0x7FFF) << 16)
                    | ((e.on as u32) << 15)
                    | (e.y as u32 & 0x7FFF);
                out.extend_from_slice(&w.to_le_bytes());
                if stamped {
                    out.extend_from_slice(&(e.t as u32).to_le_bytes());
                }
            }
            UdpFormat::T64X16Y16On8 => {
                out.extend_from_slice(&(e.t as u64).to_le_bytes());
                out.extend_from_slice(&e.x.to_le_bytes());
                out.extend_from_slice(&e.y.to_le_bytes());
                out.push(e.on as u8);
            }
            UdpFormat::T32X16Y15On1 => {
                out.extend_from_slice(&(e.t as u32).to_le_bytes());
                out.extend_from_slice(&e.x.to_le_bytes());
                out.extend_from_slice(&((e.y << 1) | e.on as u16).to_le_bytes());
            }
        }
    }

    /// Decodes one datagram (the inverse of [`UdpFormat::encode`]; times are what the format
    /// carries: full for `t64`, modulo 2^32 for `t32` and timestamped SPIF, -1 for plain SPIF).
    ///
    /// Times are not checked here: a `t64` sender may put any `i64` in them, so a receiver that
    /// computes with them checks them first ([`crate::time::check`]; `v2ce listen` refuses such a
    /// datagram).
    pub fn decode(self, datagram: &[u8], out: &mut Vec<Event>) {
        let u16_at = |b: &[u8], i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
        let u32_at = |b: &[u8], i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        for b in datagram.chunks_exact(self.event_bytes()) {
            out.push(match self {
                UdpFormat::Spif | UdpFormat::SpifTimestamped => {
                    let w = u32_at(b, 0);
                    let t = if w >> 31 == 0 && b.len() == 8 {
                        u32_at(b, 4) as i64
                    } else {
                        -1
                    };
                    let x = ((w >> 16) & 0x7FFF) as u16;
                    Event::new(t, x, (w & 0x7FFF) as u16, (w >> 15) & 1 == 1)
                }
                UdpFormat::T64X16Y16On8 => {
                    let mut t = [0u8; 8];
                    t.copy_from_slice(&b[..8]);
                    Event::new(
                        u64::from_le_bytes(t) as i64,
                        u16_at(b, 8),
                        u16_at(b, 10),
                        b[12] != 0,
                    )
                }
                UdpFormat::T32X16Y15On1 => {
                    let yo = u16_at(b, 6);
                    Event::new(u32_at(b, 0) as i64, u16_at(b, 4), yo >> 1, yo & 1 == 1)
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_follow_the_documented_layout() {
        let e = Event::new(0x1_2345_6789, 0x123, 0x45, true);
        let mut b = Vec::new();
        UdpFormat::Spif.encode(&e, &mut b);
        assert_eq!(
            b,
            (0x8000_0000u32 | 0x123 << 16 | 1 << 15 | 0x45).to_le_bytes()
        );
        b.clear();
        UdpFormat::SpifTimestamped.encode(&e, &mut b);
        assert_eq!(&b[..4], (0x123u32 << 16 | 1 << 15 | 0x45).to_le_bytes());
        assert_eq!(&b[4..], 0x2345_6789u32.to_le_bytes());
        b.clear();
        UdpFormat::T32X16Y15On1.encode(&e, &mut b);
        assert_eq!(b, [0x89, 0x67, 0x45, 0x23, 0x23, 0x01, 0x8B, 0x00]);
        b.clear();
        UdpFormat::T64X16Y16On8.encode(&e, &mut b);
        assert_eq!(b.len(), 13);
        assert_eq!(&b[..8], 0x1_2345_6789u64.to_le_bytes());
    }

    #[test]
    fn decode_inverts_encode() {
        let events = [
            Event::new(70_000, 345, 259, true),
            Event::new(70_001, 0, 0, false),
        ];
        for f in [
            UdpFormat::SpifTimestamped,
            UdpFormat::T64X16Y16On8,
            UdpFormat::T32X16Y15On1,
        ] {
            let mut b = Vec::new();
            events.iter().for_each(|e| f.encode(e, &mut b));
            let mut back = Vec::new();
            f.decode(&b, &mut back);
            assert_eq!(back, events, "{}", f.name());
        }
    }
}
