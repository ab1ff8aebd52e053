//! What the camera backends share: a started stream as a [`FrameSource`], with the frame read
//! while opening (which proved the stream works) handed out first.

use super::pixels::Layout;
use crate::error::Result;
use crate::frame::{Frame, FrameSource};

/// A camera backend's running stream.
pub(super) trait Stream: Send {
    /// How its buffers are laid out (their width and height are the frames').
    fn layout(&self) -> &Layout;
    /// The next decoded frame, later than the one before.
    fn read(&mut self) -> Result<Option<Frame>>;
    /// What it reads, for logs.
    fn describe(&self) -> String;
}

/// A started camera stream as a frame source.
pub(super) struct CameraSource<S> {
    stream: S,
    /// The first frame, read while opening to prove the stream works.
    pending: Option<Frame>,
}

impl<S: Stream + 'static> CameraSource<S> {
    /// Reads the first frame of `stream` and returns the source, which hands it out first.
    pub(super) fn start(mut stream: S) -> Result<Box<dyn FrameSource>> {
        let pending = stream.read()?;
        Ok(Box::new(CameraSource { stream, pending }))
    }
}

impl<S: Stream> FrameSource for CameraSource<S> {
    fn size(&self) -> (u16, u16) {
        // Checked by the first decoded frame at open.
        let layout = self.stream.layout();
        (layout.width as u16, layout.height as u16)
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        if let Some(f) = self.pending.take() {
            return Ok(Some(f));
        }
        self.stream.read()
    }

    fn describe(&self) -> String {
        self.stream.describe()
    }
}
