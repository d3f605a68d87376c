//! 2x2 max-pooling with stride 2 (PyTorch `MaxPool2d(2, 2)`), forward and backward.
//!
//! Output size per axis: `floor(H/2)` with [`PoolRounding::Floor`] and `ceil(H/2)` with
//! [`PoolRounding::Ceil`] (`ceil_mode=True`; with kernel = stride = 2 and no padding every ceil
//! window starts inside the input, and a window that hangs over the bottom or right edge takes the
//! maximum of its pixels inside the input). Ties pick the first maximum in row-major window order,
//! as PyTorch does, and the backward pass routes each output gradient to that pixel.

use base::Real;
use ndarray::{Array4, ArrayView4};
use rayon::prelude::*;

use crate::conv::zeroed;

/// How the pooled size is rounded when the input size is odd.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoolRounding {
    /// `floor(H/2)`: the last row/column of an odd input is dropped.
    Floor,
    /// `ceil(H/2)` (`ceil_mode=True`): the last window covers only the last row/column.
    Ceil,
}

impl PoolRounding {
    /// Pooled length of an axis of length `len`.
    pub fn pooled(self, len: usize) -> usize {
        match self {
            PoolRounding::Floor => len / 2,
            PoolRounding::Ceil => len.div_ceil(2),
        }
    }

    /// `"floor"` or `"ceil"`.
    pub fn as_str(self) -> &'static str {
        match self {
            PoolRounding::Floor => "floor",
            PoolRounding::Ceil => "ceil",
        }
    }
}

/// Where each pooled value came from: for every output element, the index `0..4` of the maximum
/// within its 2x2 window (`2*dy + dx`), plus the input size.
#[derive(Clone, Debug)]
pub struct PoolArgmax {
    input_hw: (usize, usize),
    which: Vec<u8>,
}

/// Max-pooling forward: `[N,C,H,W]` to `[N,C,H',W']`, returning the arg-max record for backward.
///
/// # Panics
/// If the pooled size would be zero (only possible with `Floor` and `H < 2` or `W < 2`).
pub fn max_pool2x2<T: Real>(x: ArrayView4<T>, rounding: PoolRounding) -> (Array4<T>, PoolArgmax) {
    let (n, c, h, w) = x.dim();
    let (ho, wo) = (rounding.pooled(h), rounding.pooled(w));
    assert!(
        ho > 0 && wo > 0,
        "max-pool of a {h}x{w} input with {rounding:?} rounding is empty"
    );
    let x = x.as_standard_layout();
    let xs = x.as_slice().expect("standard layout");
    let mut out = Array4::<T>::zeros((n, c, ho, wo));
    let mut which = vec![0u8; n * c * ho * wo];
    out.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(ho * wo)
        .zip(which.par_chunks_mut(ho * wo))
        .enumerate()
        .for_each(|(plane, (o, wh))| {
            let xin = &xs[plane * h * w..(plane + 1) * h * w];
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut best = T::neg_infinity();
                    let mut arg = 0u8;
                    let mut first = true;
                    for d in 0..4u8 {
                        let (y, xx) = (2 * oy + (d as usize >> 1), 2 * ox + (d as usize & 1));
                        if y < h && xx < w {
                            let v = xin[y * w + xx];
                            if first || v > best {
                                best = v;
                                arg = d;
                                first = false;
                            }
                        }
                    }
                    o[oy * wo + ox] = best;
                    wh[oy * wo + ox] = arg;
                }
            }
        });
    (
        out,
        PoolArgmax {
            input_hw: (h, w),
            which,
        },
    )
}

/// Max-pooling backward: routes `dy [N,C,H',W']` to the arg-max pixels of an `[N,C,H,W]` input.
pub fn max_pool2x2_backward<T: Real>(dy: ArrayView4<T>, argmax: &PoolArgmax) -> Array4<T> {
    let (n, c, ho, wo) = dy.dim();
    let (h, w) = argmax.input_hw;
    assert_eq!(
        argmax.which.len(),
        n * c * ho * wo,
        "max-pool backward: shape mismatch"
    );
    let dy = dy.as_standard_layout();
    let ds = dy.as_slice().expect("standard layout");
    let mut dx = zeroed::<T>((n, c, h, w));
    dx.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(h * w)
        .enumerate()
        .for_each(|(p, plane)| {
            let base = p * ho * wo;
            for oy in 0..ho {
                for ox in 0..wo {
                    let d = argmax.which[base + oy * wo + ox] as usize;
                    plane[(2 * oy + (d >> 1)) * w + 2 * ox + (d & 1)] += ds[base + oy * wo + ox];
                }
            }
        });
    dx
}
