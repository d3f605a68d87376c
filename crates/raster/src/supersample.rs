//! Box supersampling: an image rendered at `s` times a target resolution, averaged over each
//! `s x s` block into one target pixel ([`box_mean`]), and its adjoint, which spreads a target
//! pixel's cotangent evenly over its block ([`box_mean_backward`]).
//!
//! A map rendered directly at a coarse resolution (the standard networks' feature maps, 1/4 or
//! 1/8 of the image a side) samples the Gaussians at the coarse pixel centres only: a Gaussian
//! smaller than a coarse pixel that lies between two centres neither shows nor receives a
//! gradient, and appears or vanishes as the view moves. The mean of the `s x s` block of a
//! render `s` times finer is the map averaged over the coarse pixel's footprint instead, as the
//! encoder's pooled features summarise an image block. With the camera scaled by exactly `s`
//! (intrinsics times `s`, size times `s`), fine pixel `(s x + i, s y + j)` covers the sub-square
//! `(i, j)` of coarse pixel `(x, y)` (pixel `k` covers `[k, k + 1)` on either grid).
//!
//! Images are HWC, `channels` values per pixel, like the rasterizer's. Block sums run in a fixed
//! order (rows of the block top to bottom, each left to right), coarse rows in parallel, so the
//! result does not depend on the number of threads. At `s = 1` both are the identity and borrow
//! their input rather than copy it.

use std::borrow::Cow;

use gaussian::Real;
use rayon::prelude::*;

use crate::error::{check_len, RasterError};

/// The `width x height` image whose pixel `(x, y)` is the mean of the `s x s` block at
/// `(s x, s y)` of `fine`, an `(s width) x (s height)` image; `s = 1` borrows `fine` as it is.
pub fn box_mean<T: Real>(
    fine: &[T],
    width: usize,
    height: usize,
    channels: usize,
    s: usize,
) -> Result<Cow<'_, [T]>, RasterError> {
    check_factor(s)?;
    let fw = width * s;
    check_len("fine image", fine.len(), fw * height * s * channels)?;
    if s == 1 {
        return Ok(Cow::Borrowed(fine));
    }
    let scale = T::lit(1.0 / (s * s) as f64);
    let mut out = vec![T::lit(0.0); width * height * channels];
    if channels == 0 || width == 0 {
        return Ok(Cow::Owned(out));
    }
    out.par_chunks_mut(width * channels)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_mut(channels).enumerate() {
                for j in 0..s {
                    let start = ((s * y + j) * fw + s * x) * channels;
                    for i in 0..s {
                        let src = &fine[start + i * channels..start + (i + 1) * channels];
                        for (o, &v) in px.iter_mut().zip(src) {
                            *o += v;
                        }
                    }
                }
                for o in px.iter_mut() {
                    *o *= scale;
                }
            }
        });
    Ok(Cow::Owned(out))
}

/// The adjoint of [`box_mean`]: the `(s width) x (s height)` cotangent of the fine image from
/// the `width x height` cotangent `grad` of the mean, each fine pixel receiving its block's
/// value divided by `s * s`; `s = 1` borrows `grad` as it is.
pub fn box_mean_backward<T: Real>(
    grad: &[T],
    width: usize,
    height: usize,
    channels: usize,
    s: usize,
) -> Result<Cow<'_, [T]>, RasterError> {
    check_factor(s)?;
    check_len("mean cotangent", grad.len(), width * height * channels)?;
    if s == 1 {
        return Ok(Cow::Borrowed(grad));
    }
    let scale = T::lit(1.0 / (s * s) as f64);
    let fw = width * s;
    let mut fine = vec![T::lit(0.0); fw * height * s * channels];
    if channels == 0 || width == 0 {
        return Ok(Cow::Owned(fine));
    }
    fine.par_chunks_mut(fw * channels)
        .enumerate()
        .for_each(|(fy, row)| {
            let y = fy / s;
            for (fx, px) in row.chunks_mut(channels).enumerate() {
                let src = &grad[(y * width + fx / s) * channels..][..channels];
                for (o, &g) in px.iter_mut().zip(src) {
                    *o = g * scale;
                }
            }
        });
    Ok(Cow::Owned(fine))
}

fn check_factor(s: usize) -> Result<(), RasterError> {
    if s == 0 {
        return Err(RasterError::Supersample(s));
    }
    Ok(())
}
