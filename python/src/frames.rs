//! Frames from numpy arrays: uint8 (sRGB-encoded gray, as video and photos; `linear` for raw
//! 8-bit sensor values), uint16 (linear 0..65535, as APS frames) or float32 (linear 0..1),
//! converted to the library's linear luminance a frame at a time as the pipeline asks, from the
//! caller's buffer (no copy of the frames).

use numpy::{
    PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray3, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use v2ce::error::Error;
use v2ce::frame::{color, Frame, FrameSource, SourceEncoding, FULL_SCALE};

/// One frame's pixels in the caller's type.
#[derive(Clone, Copy)]
enum Pixels<'a> {
    U8(&'a [u8]),
    U16(&'a [u16]),
    F32(&'a [f32]),
}

impl Pixels<'_> {
    fn name(&self) -> &'static str {
        match self {
            Pixels::U8(_) => "uint8",
            Pixels::U16(_) => "uint16",
            Pixels::F32(_) => "float32",
        }
    }

    /// Linear luminance, 0..=FULL_SCALE.
    fn luma(&self, linear: bool) -> Result<Vec<u16>, String> {
        Ok(match *self {
            Pixels::U8(v) if linear => v.iter().map(|&p| u16::from(p) * 257).collect(),
            Pixels::U8(v) => {
                let lut = color::srgb_to_linear_lut();
                v.iter().map(|&p| lut[p as usize].round() as u16).collect()
            }
            Pixels::U16(v) => v.to_vec(),
            Pixels::F32(v) => {
                if let Some(bad) = v.iter().position(|p| !p.is_finite()) {
                    return Err(format!("pixel {bad} is {}", v[bad]));
                }
                v.iter()
                    .map(|&p| (p * f32::from(FULL_SCALE)).round().clamp(0.0, 65535.0) as u16)
                    .collect()
            }
        })
    }
}

fn type_error(what: &str, found: &Bound<'_, PyUntypedArray>) -> PyErr {
    let dtype = found
        .dtype()
        .str()
        .map(|s| s.to_string())
        .unwrap_or_default();
    PyValueError::new_err(format!(
        "{what}: dtype {dtype}; expected uint8 (sRGB gray), uint16 (linear) or float32 (linear 0..1)"
    ))
}

/// A `(N, H, W)` array borrowed read-only.
pub enum FramesView<'py> {
    /// sRGB (or linear) 8-bit.
    U8(PyReadonlyArray3<'py, u8>, bool),
    /// Linear 16-bit.
    U16(PyReadonlyArray3<'py, u16>),
    /// Linear float.
    F32(PyReadonlyArray3<'py, f32>),
}

impl<'py> FramesView<'py> {
    /// Borrows `frames`, which must be C-contiguous `(N, H, W)` of a supported dtype.
    pub fn new(frames: &Bound<'py, PyUntypedArray>, linear: bool) -> PyResult<Self> {
        if frames.ndim() != 3 {
            return Err(PyValueError::new_err(format!(
                "frames: {} dimensions; expected (N, H, W) gray frames",
                frames.ndim()
            )));
        }
        let view = if let Ok(a) = frames.cast::<PyArray3<u8>>() {
            FramesView::U8(a.try_readonly()?, linear)
        } else if let Ok(a) = frames.cast::<PyArray3<u16>>() {
            FramesView::U16(a.try_readonly()?)
        } else if let Ok(a) = frames.cast::<PyArray3<f32>>() {
            FramesView::F32(a.try_readonly()?)
        } else {
            return Err(type_error("frames", frames));
        };
        Ok(view)
    }

    fn shape(&self) -> [usize; 3] {
        let s = match self {
            FramesView::U8(a, _) => a.shape(),
            FramesView::U16(a) => a.shape(),
            FramesView::F32(a) => a.shape(),
        };
        [s[0], s[1], s[2]]
    }

    fn pixels(&self) -> PyResult<Pixels<'_>> {
        let contiguous = || PyValueError::new_err("frames: not C-contiguous");
        Ok(match self {
            FramesView::U8(a, _) => Pixels::U8(a.as_slice().map_err(|_| contiguous())?),
            FramesView::U16(a) => Pixels::U16(a.as_slice().map_err(|_| contiguous())?),
            FramesView::F32(a) => Pixels::F32(a.as_slice().map_err(|_| contiguous())?),
        })
    }

    /// A frame source reading this array at `times` (us, one per frame, increasing).
    ///
    /// # Safety
    /// The source reads the array through a pointer that outlives the borrow's lifetime as the
    /// type system sees it: the caller must keep `self` alive, and the array unmodified, until
    /// the source has been dropped.
    pub unsafe fn source(&self, times: Vec<i64>) -> PyResult<ArraySource> {
        let [n, h, w] = self.shape();
        if n == 0 {
            return Err(PyValueError::new_err("frames: no frames"));
        }
        if times.len() != n {
            return Err(PyValueError::new_err(format!(
                "times_us has {} values for {n} frames",
                times.len()
            )));
        }
        if let Some(k) = times.windows(2).position(|p| p[1] <= p[0]) {
            return Err(PyValueError::new_err(format!(
                "times_us must increase: frame {} at {} us comes after {} us",
                k + 1,
                times[k + 1],
                times[k]
            )));
        }
        crate::times_in_range("times_us", &times)?;
        for p in times.windows(2) {
            v2ce::time::span("times_us", p[0], p[1]).map_err(crate::py_err)?;
        }
        let (width, height) = sensor(w, h)?;
        if let Pixels::F32(v) = self.pixels()? {
            if let Some(bad) = v.iter().position(|p| !p.is_finite()) {
                let per = w * h;
                return Err(PyValueError::new_err(format!(
                    "frames: frame {}, pixel ({}, {}) is {}",
                    bad / per,
                    bad % per % w,
                    bad % per / w,
                    v[bad]
                )));
            }
        }
        let linear = match self {
            FramesView::U8(_, linear) => *linear,
            _ => true,
        };
        let pixels = self.pixels()?;
        // SAFETY: see the function's contract.
        let pixels: Pixels<'static> = unsafe { std::mem::transmute(pixels) };
        Ok(ArraySource {
            pixels,
            times,
            width,
            height,
            next: 0,
            linear,
        })
    }
}

fn sensor(w: usize, h: usize) -> PyResult<(u16, u16)> {
    let fit = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
    v2ce::limits::frame_size("frames", fit(w), fit(h))
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok((w as u16, h as u16))
}

/// Frames read from a numpy buffer the caller keeps alive (see [`FramesView::source`]).
pub struct ArraySource {
    pixels: Pixels<'static>,
    times: Vec<i64>,
    width: u16,
    height: u16,
    next: usize,
    linear: bool,
}

// SAFETY: the buffer is only read, and the caller keeps it alive and unmodified while the
// source exists (`FramesView::source`).
unsafe impl Send for ArraySource {}

impl FrameSource for ArraySource {
    fn size(&self) -> (u16, u16) {
        (self.width, self.height)
    }

    fn next_frame(&mut self) -> v2ce::Result<Option<Frame>> {
        let k = self.next;
        let Some(&t) = self.times.get(k) else {
            return Ok(None);
        };
        self.next += 1;
        let len = self.width as usize * self.height as usize;
        let range = k * len..(k + 1) * len;
        let one = match self.pixels {
            Pixels::U8(v) => Pixels::U8(&v[range]),
            Pixels::U16(v) => Pixels::U16(&v[range]),
            Pixels::F32(v) => Pixels::F32(&v[range]),
        };
        let luma = one
            .luma(self.linear)
            .map_err(|e| Error::invalid("frames", format!("frame {k}: {e}")))?;
        Ok(Some(Frame::new(t, (self.width, self.height), luma)))
    }

    fn describe(&self) -> String {
        format!(
            "{} numpy frames ({} x {}, {})",
            self.times.len(),
            self.width,
            self.height,
            self.pixels.name()
        )
    }

    fn frames_hint(&self) -> Option<u64> {
        Some(self.times.len() as u64)
    }

    fn encoding(&self) -> SourceEncoding {
        if self.linear {
            SourceEncoding::Linear
        } else {
            SourceEncoding::Srgb
        }
    }
}

/// One `(H, W)` frame at `t`, which must be `size` (width, height).
pub fn one_frame(
    frame: &Bound<'_, PyUntypedArray>,
    t: i64,
    size: (u16, u16),
    linear: bool,
) -> PyResult<Frame> {
    let shape = frame.shape();
    if shape != [size.1 as usize, size.0 as usize] {
        return Err(PyValueError::new_err(format!(
            "frame of shape {shape:?}; this simulator takes ({}, {})",
            size.1, size.0
        )));
    }
    let luma = if let Ok(a) = frame.cast::<PyArray2<u8>>() {
        let a = a.try_readonly()?;
        let v = a.as_array();
        let v: Vec<u8> = v.iter().copied().collect();
        Pixels::U8(&v).luma(linear)
    } else if let Ok(a) = frame.cast::<PyArray2<u16>>() {
        let a = a.try_readonly()?;
        let v: Vec<u16> = a.as_array().iter().copied().collect();
        Pixels::U16(&v).luma(true)
    } else if let Ok(a) = frame.cast::<PyArray2<f32>>() {
        let a = a.try_readonly()?;
        let v: Vec<f32> = a.as_array().iter().copied().collect();
        Pixels::F32(&v).luma(true)
    } else {
        return Err(type_error("frame", frame));
    }
    .map_err(|e| PyValueError::new_err(format!("frame at {t} us: {e}")))?;
    Ok(Frame::new(t, size, luma))
}
