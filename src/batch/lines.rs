//! Bounded reading of the batch's text files (manifest, ledgers, config): lines as bytes, each
//! at most a given length, the file at most a given size, so that an endless line, a huge
//! file or a link to `/dev/zero` gets a clear error (or a skipped line) instead of a read
//! without end.

use std::io::{BufRead, Read};
use std::path::Path;

use crate::error::{Error, Result};

/// One line of a file, as [`for_each_line`] hands it on (without its `\n`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Line<'a> {
    /// A line of UTF-8 text.
    Text(&'a str),
    /// A line that is not UTF-8 (e.g. cut inside a character).
    NotUtf8,
    /// A line longer than the limit; its bytes were dropped as they were read.
    TooLong,
}

/// Reads `reader` (the file `path`) line by line, handing each line and its number (from 1)
/// to `each`; a last line without `\n` counts too. A line of more than `max_line` bytes is
/// handed on as [`Line::TooLong`] without being held in memory; more than `max_total` bytes
/// in all is an error naming `path`.
pub(super) fn for_each_line(
    path: &Path,
    mut reader: impl BufRead,
    max_line: usize,
    max_total: u64,
    mut each: impl FnMut(usize, Line<'_>) -> Result<()>,
) -> Result<()> {
    let mut line: Vec<u8> = Vec::new();
    let mut too_long = false;
    let mut total: u64 = 0;
    let mut number = 0usize;
    let mut hand_on = |number: usize, line: &[u8], too_long: bool| {
        let l = if too_long {
            Line::TooLong
        } else {
            std::str::from_utf8(line).map_or(Line::NotUtf8, Line::Text)
        };
        each(number, l)
    };
    loop {
        let chunk = match reader.fill_buf() {
            Ok(c) => c,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(Error::io(path, e)),
        };
        if chunk.is_empty() {
            if !line.is_empty() || too_long {
                hand_on(number + 1, &line, too_long)?;
            }
            return Ok(());
        }
        let newline = chunk.iter().position(|&b| b == b'\n');
        let take = newline.map_or(chunk.len(), |i| i + 1);
        total = total.saturating_add(take as u64);
        if total > max_total {
            return Err(too_large(path, max_total));
        }
        let content = &chunk[..newline.unwrap_or(chunk.len())];
        if !too_long {
            if line.len() + content.len() > max_line {
                too_long = true;
                line = Vec::new();
            } else {
                line.extend_from_slice(content);
            }
        }
        reader.consume(take);
        if newline.is_some() {
            number += 1;
            hand_on(number, &line, too_long)?;
            line.clear();
            too_long = false;
        }
    }
}

/// The whole of the file `path` as text, refused when it is larger than `max` bytes or not
/// UTF-8.
pub(super) fn read_text(path: &Path, max: u64) -> Result<String> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut bytes = Vec::new();
    file.take(max.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > max {
        return Err(too_large(path, max));
    }
    String::from_utf8(bytes).map_err(|e| {
        Error::format(
            path,
            format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
        )
    })
}

fn too_large(path: &Path, max: u64) -> Error {
    Error::format(
        path,
        format!("larger than {max} bytes, the most read of such a file"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(input: impl Read, max_line: usize, max_total: u64) -> Result<Vec<String>> {
        let mut seen = Vec::new();
        for_each_line(
            Path::new("f"),
            std::io::BufReader::with_capacity(7, input),
            max_line,
            max_total,
            |n, l| {
                seen.push(format!("{n}:{l:?}"));
                Ok(())
            },
        )?;
        Ok(seen)
    }

    #[test]
    fn lines_are_bounded_in_length_and_in_all() {
        let text = "ab\n\nc\u{e9}\n0123456789abcdef\nlast".as_bytes();
        assert_eq!(
            lines(text, 10, 100).unwrap(),
            [
                "1:Text(\"ab\")",
                "2:Text(\"\")",
                "3:Text(\"c\u{e9}\")",
                "4:TooLong",
                "5:Text(\"last\")"
            ]
        );
        // A line cut inside a character.
        assert_eq!(
            lines(&[b'a', 0xc3, b'\n', b'b'][..], 10, 100).unwrap(),
            ["1:NotUtf8", "2:Text(\"b\")"]
        );
        // An endless line (/dev/zero) ends at the cap on the whole, naming the file.
        let err = lines(std::io::repeat(0), 10, 1000).unwrap_err().to_string();
        assert!(err.starts_with("f: larger than 1000 bytes"), "{err}");
        let err = lines(std::io::repeat(b'\n'), 10, 1000).unwrap_err();
        assert!(err.to_string().contains("1000"));
        assert_eq!(lines(&b"abc\n"[..], 10, 4).unwrap(), ["1:Text(\"abc\")"]);
        assert!(lines(&b"abc\nd"[..], 10, 4).is_err());
    }

    #[test]
    fn whole_files_are_bounded() {
        let dir = std::env::temp_dir().join(format!("v2ce-batch-lines-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("c.toml");
        std::fs::write(&f, "a = 1\n").unwrap();
        assert_eq!(read_text(&f, 6).unwrap(), "a = 1\n");
        let err = read_text(&f, 5).unwrap_err().to_string();
        assert!(
            err.contains("c.toml") && err.contains("larger than 5"),
            "{err}"
        );
        std::fs::write(&f, b"a = \xff\n").unwrap();
        assert!(read_text(&f, 100)
            .unwrap_err()
            .to_string()
            .contains("UTF-8"));
        let err = read_text(Path::new("/dev/zero"), 1 << 16).unwrap_err();
        assert!(err.to_string().starts_with("/dev/zero: larger"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
