//! Storages: the element type named by a storage's class, and the decoding of its raw
//! little-endian bytes into tensor data, including strided (non-contiguous) views.

use crate::model::TensorData;

/// The element type of a PyTorch storage, from its class name (`torch.FloatStorage`, ...).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageType {
    /// `FloatStorage`: float32.
    F32,
    /// `DoubleStorage`: float64 (read as float32).
    F64,
    /// `HalfStorage`: float16 (read as float32).
    F16,
    /// `BFloat16Storage`: bfloat16 (read as float32).
    BF16,
    /// `LongStorage`: int64.
    I64,
    /// `IntStorage`: int32 (read as int64).
    I32,
    /// `ShortStorage`: int16 (read as int64).
    I16,
    /// `CharStorage`: int8 (read as int64).
    I8,
    /// `ByteStorage` and `UntypedStorage`: uint8 (read as int64).
    U8,
    /// `BoolStorage`: bool (read as int64 0 or 1).
    Bool,
}

impl StorageType {
    /// The type for a storage class, e.g. `("torch", "FloatStorage")`.
    pub(super) fn from_class(module: &str, name: &str) -> Option<Self> {
        if !matches!(module, "torch" | "torch.cuda" | "torch.storage") {
            return None;
        }
        Some(match name {
            "FloatStorage" => StorageType::F32,
            "DoubleStorage" => StorageType::F64,
            "HalfStorage" => StorageType::F16,
            "BFloat16Storage" => StorageType::BF16,
            "LongStorage" => StorageType::I64,
            "IntStorage" => StorageType::I32,
            "ShortStorage" => StorageType::I16,
            "CharStorage" => StorageType::I8,
            "ByteStorage" | "UntypedStorage" => StorageType::U8,
            "BoolStorage" => StorageType::Bool,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            StorageType::F64 | StorageType::I64 => 8,
            StorageType::F32 | StorageType::I32 => 4,
            StorageType::F16 | StorageType::BF16 | StorageType::I16 => 2,
            StorageType::I8 | StorageType::U8 | StorageType::Bool => 1,
        }
    }

    /// The dtype's name as PyTorch spells it.
    pub fn name(self) -> &'static str {
        match self {
            StorageType::F32 => "float32",
            StorageType::F64 => "float64",
            StorageType::F16 => "float16",
            StorageType::BF16 => "bfloat16",
            StorageType::I64 => "int64",
            StorageType::I32 => "int32",
            StorageType::I16 => "int16",
            StorageType::I8 => "int8",
            StorageType::U8 => "uint8",
            StorageType::Bool => "bool",
        }
    }

    /// Whether the elements are floats (read as [`TensorData::F32`]).
    pub fn is_float(self) -> bool {
        matches!(
            self,
            StorageType::F32 | StorageType::F64 | StorageType::F16 | StorageType::BF16
        )
    }
}

/// Whether `stride` is the row-major stride of `shape` (ignoring dimensions of size 1).
pub(super) fn is_contiguous(shape: &[usize], stride: &[usize]) -> bool {
    let mut expected = 1usize;
    for (&n, &s) in shape.iter().zip(stride).rev() {
        if n != 1 && s != expected {
            return false;
        }
        expected = expected.saturating_mul(n);
    }
    true
}

/// Row-major copy of a strided view whose element (0, ..., 0) is `span[0]`.
pub(super) fn gather<T: Copy>(span: &[T], shape: &[usize], stride: &[usize]) -> Vec<T> {
    let numel: usize = shape.iter().product();
    let mut out = Vec::with_capacity(numel);
    if numel == 0 {
        return out;
    }
    let mut index = vec![0usize; shape.len()];
    let mut at = 0usize;
    loop {
        out.push(span[at]);
        // Odometer increment, last dimension fastest.
        let mut d = shape.len();
        loop {
            if d == 0 {
                return out;
            }
            d -= 1;
            index[d] += 1;
            at += stride[d];
            if index[d] < shape[d] {
                break;
            }
            at -= stride[d] * shape[d];
            index[d] = 0;
        }
    }
}

/// Decodes little-endian storage bytes (a whole number of elements) into tensor data.
pub(super) fn decode(dtype: StorageType, bytes: &[u8]) -> TensorData {
    fn each<const N: usize, T>(bytes: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
        bytes
            .chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                f(a)
            })
            .collect()
    }
    match dtype {
        StorageType::F32 => TensorData::F32(each(bytes, f32::from_le_bytes)),
        StorageType::F64 => TensorData::F32(each(bytes, |b| f64::from_le_bytes(b) as f32)),
        StorageType::F16 => TensorData::F32(each(bytes, |b| f16_to_f32(u16::from_le_bytes(b)))),
        StorageType::BF16 => TensorData::F32(each(bytes, |b: [u8; 2]| {
            f32::from_bits(u32::from(u16::from_le_bytes(b)) << 16)
        })),
        StorageType::I64 => TensorData::I64(each(bytes, i64::from_le_bytes)),
        StorageType::I32 => TensorData::I64(each(bytes, |b| i64::from(i32::from_le_bytes(b)))),
        StorageType::I16 => TensorData::I64(each(bytes, |b| i64::from(i16::from_le_bytes(b)))),
        StorageType::I8 => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0] as i8))),
        StorageType::U8 => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0]))),
        StorageType::Bool => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0] != 0))),
    }
}

/// IEEE half precision to single precision (exact).
fn f16_to_f32(h: u16) -> f32 {
    let sign = u32::from(h >> 15) << 31;
    let exp = u32::from((h >> 10) & 0x1f);
    let mant = u32::from(h & 0x3ff);
    if exp == 0 {
        // Zero or subnormal: mant * 2^-24, exact in f32.
        let v = mant as f32 * (1.0 / 16_777_216.0);
        return if sign != 0 { -v } else { v };
    }
    let bits = if exp == 31 {
        sign | 0x7f80_0000 | (mant << 13)
    } else {
        sign | ((exp + 112) << 23) | (mant << 13)
    };
    f32::from_bits(bits)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f16_conversion_is_exact() {
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        assert!(f16_to_f32(0x7c00).is_infinite());
        assert!(f16_to_f32(0x7e00).is_nan());
        assert_eq!(f16_to_f32(0x8000).to_bits(), (-0.0f32).to_bits());
    }

    #[test]
    fn gather_transposes() {
        // A 2x3 row-major matrix viewed as its 3x2 transpose.
        let span = [1, 2, 3, 4, 5, 6];
        assert_eq!(gather(&span, &[3, 2], &[1, 3]), vec![1, 4, 2, 5, 3, 6]);
        assert!(is_contiguous(&[2, 3], &[3, 1]));
        assert!(!is_contiguous(&[3, 2], &[1, 3]));
        assert!(is_contiguous(&[1, 3], &[99, 1]));
    }
}
