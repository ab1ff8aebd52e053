//! The bundled fixture video: 6 s of a synthetic scene (a brick wall, a rolling ball, a turning
//! bar, a blinking lamp, then a camera pan) at 640x480 and 30 fps, made by
//! `examples/make_fixture.rs` and stored as `tests/fixtures/walkby.y4m.zst` (about 290 KB).
//! `v2ce run` replays it when there is neither a camera nor a configured source, and the
//! integration tests drive the pipeline with it.

use std::path::Path;

use super::y4m::Y4mSource;
use super::FrameSource;
use crate::error::{Error, Result};

/// The name that selects the fixture as a source (`--source fixture`).
pub const NAME: &str = "fixture";

/// Where the fixture lives in the source tree.
pub const PATH: &str = "tests/fixtures/walkby.y4m.zst";

const BYTES: &[u8] = include_bytes!("../../tests/fixtures/walkby.y4m.zst");

/// Opens the fixture embedded in the binary.
pub fn open() -> Result<Box<dyn FrameSource>> {
    let origin = Path::new("bundled fixture walkby.y4m.zst");
    let reader =
        zstd::stream::read::Decoder::with_buffer(BYTES).map_err(|e| Error::io(origin, e))?;
    Ok(Box::new(Y4mSource::from_reader(Box::new(reader), origin)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fixture_is_180_frames_of_640x480_at_30_fps() {
        let mut s = open().unwrap();
        assert_eq!(s.size(), (640, 480));
        let mut n = 0;
        let mut last = None;
        while let Some(f) = s.next_frame().unwrap() {
            assert_eq!(f.t, (n as f64 * 1e6 / 30.0).round() as i64);
            last = Some(f);
            n += 1;
        }
        assert_eq!(n, 180);
        // Not a flat frame: the wall's bricks span a wide range of luminance.
        let f = last.unwrap();
        let (lo, hi) = (f.luma.iter().min().unwrap(), f.luma.iter().max().unwrap());
        assert!(*hi > 4 * *lo.max(&1), "{lo}..{hi}");
    }
}
