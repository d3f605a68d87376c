//! Materialisation of a strided tensor view into a contiguous row-major `f32` tensor.
//!
//! A PyTorch tensor is a window into a storage: element `(i_0, .., i_{n-1})` lives at storage
//! element `offset + sum_k i_k * stride_k` (strides and offset in elements). This module checks
//! that every such index lies inside the storage before reading anything, and converts the element
//! type to `f32`: float32 as is, float16 and bfloat16 exactly, float64 rounded to nearest.

use crate::state_dict::TensorF32;

use super::error::FormatError;
use super::pickle::{DType, TensorRef};

/// Byte order of the raw storage bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ByteOrder {
    Little,
    Big,
}

/// The raw bytes of one root storage.
#[derive(Clone, Copy, Debug)]
pub(crate) struct StorageBytes<'a> {
    pub dtype: DType,
    pub order: ByteOrder,
    /// Exactly `numel * dtype.size()` bytes.
    pub bytes: &'a [u8],
}

/// Reads element `i` of `storage` as `f32`. `i` must be in range.
fn element(storage: &StorageBytes, i: usize) -> f32 {
    let size = storage.dtype.size() as usize;
    let b = &storage.bytes[i * size..(i + 1) * size];
    let big = storage.order == ByteOrder::Big;
    match storage.dtype {
        DType::F32 => {
            let a = [b[0], b[1], b[2], b[3]];
            if big {
                f32::from_be_bytes(a)
            } else {
                f32::from_le_bytes(a)
            }
        }
        DType::F64 => {
            let a = [b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]];
            (if big {
                f64::from_be_bytes(a)
            } else {
                f64::from_le_bytes(a)
            }) as f32
        }
        DType::F16 | DType::BF16 => {
            let a = [b[0], b[1]];
            let h = if big {
                u16::from_be_bytes(a)
            } else {
                u16::from_le_bytes(a)
            };
            if storage.dtype == DType::F16 {
                f16_to_f32(h)
            } else {
                bf16_to_f32(h)
            }
        }
        // `materialise` reads float storages only.
        _ => f32::NAN,
    }
}

/// IEEE 754 binary16 to binary32, exactly (NaN payloads kept in the high mantissa bits).
pub(crate) fn f16_to_f32(h: u16) -> f32 {
    let sign = u32::from(h >> 15) << 31;
    let exp = u32::from((h >> 10) & 0x1f);
    let man = u32::from(h & 0x3ff);
    let magnitude = match exp {
        // Zero and subnormals: man * 2^-24, exact in f32.
        0 => (man as f32 * f32::from_bits(0x3380_0000)).to_bits(),
        // Infinity and NaN.
        0x1f => 0x7f80_0000 | (man << 13),
        // Normal: rebias the exponent from 15 to 127.
        _ => ((exp + 112) << 23) | (man << 13),
    };
    f32::from_bits(sign | magnitude)
}

/// bfloat16 to binary32, exactly: bfloat16 is the high half of a binary32.
pub(crate) fn bf16_to_f32(h: u16) -> f32 {
    f32::from_bits(u32::from(h) << 16)
}

/// Copies the tensor `t` (named `name` in errors) out of its root storage `storage` as a
/// contiguous row-major `f32` tensor. `budget` is the number of elements that may still be
/// materialised in this checkpoint; it is decreased by this tensor's element count.
pub(crate) fn materialise(
    name: &str,
    t: &TensorRef,
    storage: &StorageBytes,
    budget: &mut u64,
) -> Result<TensorF32, FormatError> {
    let fail = |reason: String| FormatError::Tensor {
        name: name.to_owned(),
        reason,
    };
    if !storage.dtype.is_float() {
        return Err(fail(format!(
            "{:?} storages are not imported",
            storage.dtype
        )));
    }
    let view = &t.storage;
    let root_len = storage.bytes.len() as u64 / storage.dtype.size();
    // Persistent ids were checked against the declared size, and the bytes against it too.
    if view
        .start
        .checked_add(view.len)
        .is_none_or(|e| e > root_len)
    {
        return Err(fail(format!(
            "storage view [{}, +{}) outside storage {} of {root_len} elements",
            view.start, view.len, view.key
        )));
    }
    let numel = t
        .shape
        .iter()
        .try_fold(1u64, |n, &d| n.checked_mul(d))
        .ok_or_else(|| fail(format!("size {:?} overflows", t.shape)))?;
    if numel > *budget {
        return Err(fail(format!(
            "size {:?} would take the checkpoint past its limit of materialised elements \
             (at most {} per stored element, to bound memory)",
            t.shape,
            super::EXPANSION_LIMIT
        )));
    }
    let shape: Vec<usize> = t.shape.iter().map(|&d| d as usize).collect();
    if numel == 0 {
        *budget -= numel;
        return Ok(TensorF32 {
            shape,
            data: Vec::new(),
        });
    }
    // Size-1 dimensions never move the index: give them stride 0 so that no stride is larger
    // than the largest index, which bounds every partial sum below.
    let stride: Vec<u64> = (t.shape.iter().zip(&t.stride))
        .map(|(&d, &s)| if d == 1 { 0 } else { s })
        .collect();
    let last = (t.shape.iter().zip(&stride))
        .try_fold(t.offset, |acc, (&d, &s)| {
            (d - 1).checked_mul(s).and_then(|x| acc.checked_add(x))
        })
        .filter(|&last| last < view.len)
        .ok_or_else(|| {
            fail(format!(
                "offset {} with size {:?} and stride {:?} reaches past the end of its storage \
                 ({} elements)",
                t.offset, t.shape, t.stride, view.len
            ))
        })?;
    debug_assert!(last < root_len);
    *budget -= numel;

    let start = (view.start + t.offset) as usize;
    let mut data = Vec::with_capacity(numel as usize);
    let contiguous = {
        let mut expect = 1u64;
        let mut ok = true;
        for (&d, &s) in t.shape.iter().zip(&stride).rev() {
            ok &= d == 1 || s == expect;
            expect *= d;
        }
        ok
    };
    if contiguous {
        data.extend((start..start + numel as usize).map(|i| element(storage, i)));
    } else {
        let rank = shape.len();
        let stride: Vec<usize> = stride.iter().map(|&s| s as usize).collect();
        let (inner, inner_stride) = (shape[rank - 1], stride[rank - 1]);
        let mut index = vec![0usize; rank - 1];
        let mut base = start;
        loop {
            data.extend((0..inner).map(|j| element(storage, base + j * inner_stride)));
            // Advance the odometer over the outer dimensions.
            let mut d = rank - 1;
            loop {
                if d == 0 {
                    return Ok(TensorF32 { shape, data });
                }
                d -= 1;
                index[d] += 1;
                base += stride[d];
                if index[d] < shape[d] {
                    break;
                }
                base -= stride[d] * shape[d];
                index[d] = 0;
            }
        }
    }
    Ok(TensorF32 { shape, data })
}
