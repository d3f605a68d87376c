//! Per-channel statistics of NCHW feature maps, forward and backward.
//!
//! Convention (the oracle's `mean_std`): for every sample `n` and channel `c`, over the `m = H*W`
//! pixels (or the `m` pixels inside a mask),
//!
//! ```text
//! mean = (1/m) sum_i x_i
//! var  = (1/(m-1)) sum_i (x_i - mean)^2          (unbiased)
//! std  = sqrt(var + 1e-5)
//! ```
//!
//! Backward: since `sum_i (x_i - mean) = 0`, the mean drops out of `d var / d x_i` and
//!
//! ```text
//! dL/dx_i = g_mean / m + g_std * (x_i - mean) / ((m - 1) * std)     (i inside the mask, else 0)
//! ```
//!
//! Both passes treat the `N*C` planes independently and in parallel. Each plane is reduced in
//! `f64` in one fixed order (eight interleaved partial sums, combined pairwise), so
//! the result does not depend on the thread count.

use base::Real;
use ndarray::{Array2, Array4, ArrayView2};
use rayon::prelude::*;

use crate::error::{check_shape, Result, StyleError};

/// The constant added to the variance before the square root.
pub const STATS_EPS: f64 = 1e-5;

/// Per-channel mean and standard deviation, each `[N, C]`.
///
/// The same type carries cotangents of statistics (`dL/dmean`, `dL/dstd`) in backward passes.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelStats<T> {
    /// Per-channel means over the pixels, `[N, C]` (or `dL/dmean` in a backward pass).
    pub mean: Array2<T>,
    /// Per-channel standard deviations `sqrt(var + STATS_EPS)` (unbiased variance), `[N, C]`
    /// (or `dL/dstd` in a backward pass).
    pub std: Array2<T>,
}

impl<T: Real> ChannelStats<T> {
    /// Statistics from `[N, C]` means and standard deviations.
    pub fn new(mean: Array2<T>, std: Array2<T>) -> Result<Self> {
        check_shape("channel stats std", std.shape(), mean.shape())?;
        Ok(ChannelStats { mean, std })
    }

    /// Zero statistics (a zero cotangent) of shape `[n, c]`.
    pub fn zeros(n: usize, c: usize) -> Self {
        ChannelStats {
            mean: Array2::zeros((n, c)),
            std: Array2::zeros((n, c)),
        }
    }

    /// Number of samples `N`.
    pub fn batch(&self) -> usize {
        self.mean.nrows()
    }

    /// Number of channels `C`.
    pub fn channels(&self) -> usize {
        self.mean.ncols()
    }

    /// The statistics converted to another scalar type.
    pub fn cast<U: Real>(&self) -> ChannelStats<U> {
        ChannelStats {
            mean: self.mean.mapv(|v| U::lit(v.to_f64_exact())),
            std: self.std.mapv(|v| U::lit(v.to_f64_exact())),
        }
    }

    /// The row used for sample `n` of a batch of `batch` samples: statistics with `N = 1`
    /// broadcast over the batch, otherwise `N` must equal the batch.
    pub(crate) fn row_for(&self, n: usize) -> usize {
        if self.batch() == 1 {
            0
        } else {
            n
        }
    }

    /// Checks that these statistics apply to features of shape `[n, c, _, _]`.
    pub(crate) fn check_applies(&self, what: &'static str, n: usize, c: usize) -> Result<()> {
        if self.channels() != c || (self.batch() != 1 && self.batch() != n) {
            return Err(StyleError::Shape {
                what,
                expected: vec![n, c],
                actual: vec![self.batch(), self.channels()],
            });
        }
        Ok(())
    }
}

/// `(N, C, H, W)` of a feature map.
pub(crate) fn dims<T>(x: &Array4<T>) -> (usize, usize, usize, usize) {
    let d = x.dim();
    (d.0, d.1, d.2, d.3)
}

/// The feature map's data in standard (row-major NCHW) order, copied only if needed.
pub(crate) fn planes<T: Real>(x: &Array4<T>) -> std::borrow::Cow<'_, [T]> {
    match x.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(x.iter().copied().collect()),
    }
}

/// Flattened mask of `[H, W]`, checked against the feature map's spatial size.
fn flat_mask(mask: ArrayView2<bool>, h: usize, w: usize) -> Result<Vec<bool>> {
    check_shape("mask", mask.shape(), &[h, w])?;
    Ok(mask.iter().copied().collect())
}

/// Partial sums of [`sum_f64`]: independent additions that overlap in the pipeline (and fill a
/// vector register of `f64`), where a single running sum waits on every addition.
const SUMS: usize = 8;

/// `sum_{i < n} term(i)` in `f64`: term `i` is added to partial sum `i % SUMS`, and the partial
/// sums are combined pairwise, `((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))`. One fixed
/// order for every `n` and thread count.
#[inline]
pub(crate) fn interleaved_sum(n: usize, term: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0f64; SUMS];
    let whole = n / SUMS * SUMS;
    for base in (0..whole).step_by(SUMS) {
        for (l, a) in acc.iter_mut().enumerate() {
            *a += term(base + l);
        }
    }
    for (a, i) in acc.iter_mut().zip(whole..n) {
        *a += term(i);
    }
    ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
}

/// `sum_i f(x_i)` in `f64` over the elements of `plane` inside `mask` (all when `None`), in the
/// order of [`interleaved_sum`] (an element outside the mask adds zero to its partial sum).
#[inline]
pub(crate) fn sum_f64<T: Real>(plane: &[T], mask: Option<&[bool]>, f: impl Fn(f64) -> f64) -> f64 {
    match mask {
        None => interleaved_sum(plane.len(), |i| f(plane[i].to_f64_exact())),
        Some(m) => {
            let m = &m[..plane.len()];
            interleaved_sum(plane.len(), |i| {
                if m[i] {
                    f(plane[i].to_f64_exact())
                } else {
                    0.0
                }
            })
        }
    }
}

/// `(m, mean, M2)` of one plane in `f64` over the `m` pixels inside `mask` (all when `None`):
/// the mean, then the sum of squared deviations from it (two passes of [`sum_f64`]).
pub(crate) fn plane_moments<T: Real>(plane: &[T], mask: Option<&[bool]>) -> (usize, f64, f64) {
    let m = mask.map_or(plane.len(), |mk| {
        mk[..plane.len()].iter().filter(|&&b| b).count()
    });
    let mean = sum_f64(plane, mask, |v| v) / m as f64;
    let m2 = sum_f64(plane, mask, |v| {
        let d = v - mean;
        d * d
    });
    (m, mean, m2)
}

/// `(mean, std)` of one plane in `f64`, over the masked pixels (all when `mask` is `None`).
pub(crate) fn plane_mean_std<T: Real>(plane: &[T], mask: Option<&[bool]>) -> (f64, f64) {
    let (m, mean, m2) = plane_moments(plane, mask);
    let var = m2 / (m as f64 - 1.0);
    (mean, (var + STATS_EPS).sqrt())
}

fn stats_impl<T: Real>(x: &Array4<T>, mask: Option<&[bool]>) -> Result<ChannelStats<T>> {
    let (n, c, h, w) = dims(x);
    let count = mask.map_or(h * w, |m| m.iter().filter(|&&b| b).count());
    if count < 2 {
        return Err(StyleError::TooFewPixels {
            what: "channel statistics",
            count,
        });
    }
    let data = planes(x);
    let hw = h * w;
    let pairs: Vec<(T, T)> = data
        .par_chunks(hw)
        .map(|plane| {
            let (m, s) = plane_mean_std(plane, mask);
            (T::lit(m), T::lit(s))
        })
        .collect();
    let mean = Array2::from_shape_fn((n, c), |(i, j)| pairs[i * c + j].0);
    let std = Array2::from_shape_fn((n, c), |(i, j)| pairs[i * c + j].1);
    Ok(ChannelStats { mean, std })
}

/// Per-channel statistics of a feature map seen one tile at a time: each tile's mean and sum
/// of squared deviations in `f64` (two passes, as [`channel_stats`]), merged by the pairwise
/// rule of Chan, Golub and LeVeque (`M2 = M2_a + M2_b + d^2 n_a n_b / n`, `d` the difference of
/// the means). [`ChannelMoments::stats`] then gives what [`channel_stats`] gives for the whole
/// map, up to the `f64` rounding of the different summation order.
#[derive(Clone, Debug)]
pub struct ChannelMoments {
    batch: usize,
    channels: usize,
    /// Pixels seen per channel.
    count: usize,
    mean: Vec<f64>,
    m2: Vec<f64>,
}

impl ChannelMoments {
    /// Nothing seen yet, for feature maps `[batch, channels, _, _]`.
    pub fn new(batch: usize, channels: usize) -> ChannelMoments {
        ChannelMoments {
            batch,
            channels,
            count: 0,
            mean: vec![0.0; batch * channels],
            m2: vec![0.0; batch * channels],
        }
    }

    /// Adds the pixels of a tile `[batch, channels, h, w]`.
    pub fn add<T: Real>(&mut self, tile: &Array4<T>) -> Result<()> {
        let (n, c, h, w) = dims(tile);
        check_shape("tile", &[n, c], &[self.batch, self.channels])?;
        let k = h * w;
        if k == 0 {
            return Ok(());
        }
        let data = planes(tile);
        let (na, nb) = (self.count as f64, k as f64);
        let total = na + nb;
        for (i, plane) in data.chunks(k).enumerate() {
            let (_, mean_b, m2_b) = plane_moments(plane, None);
            let d = mean_b - self.mean[i];
            self.mean[i] += d * nb / total;
            self.m2[i] += m2_b + d * d * na * nb / total;
        }
        self.count += k;
        Ok(())
    }

    /// Mean and std (`sqrt(unbiased variance + STATS_EPS)`) of everything added, as
    /// [`channel_stats`] of the whole map.
    pub fn stats<T: Real>(&self) -> Result<ChannelStats<T>> {
        if self.count < 2 {
            return Err(StyleError::TooFewPixels {
                what: "channel statistics",
                count: self.count,
            });
        }
        let var = |i: usize| self.m2[i] / (self.count as f64 - 1.0);
        let c = self.channels;
        Ok(ChannelStats {
            mean: Array2::from_shape_fn((self.batch, c), |(n, j)| T::lit(self.mean[n * c + j])),
            std: Array2::from_shape_fn((self.batch, c), |(n, j)| {
                T::lit((var(n * c + j) + STATS_EPS).sqrt())
            }),
        })
    }
}

/// Per-channel mean and std over all `H*W` pixels of `x` (`[N, C, H, W]`).
pub fn channel_stats<T: Real>(x: &Array4<T>) -> Result<ChannelStats<T>> {
    stats_impl(x, None)
}

/// Per-channel mean and std over the pixels where `mask` (`[H, W]`, shared by every sample and
/// channel) is true. At least two pixels must be selected.
pub fn masked_channel_stats<T: Real>(
    x: &Array4<T>,
    mask: ArrayView2<bool>,
) -> Result<ChannelStats<T>> {
    let (_, _, h, w) = dims(x);
    let m = flat_mask(mask, h, w)?;
    stats_impl(x, Some(&m))
}

fn stats_backward_impl<T: Real>(
    x: &Array4<T>,
    mask: Option<&[bool]>,
    stats: &ChannelStats<T>,
    grad: &ChannelStats<T>,
) -> Result<Array4<T>> {
    let (n, c, h, w) = dims(x);
    check_shape("stats of x", stats.mean.shape(), &[n, c])?;
    check_shape("stats of x (std)", stats.std.shape(), &[n, c])?;
    check_shape("stats cotangent (mean)", grad.mean.shape(), &[n, c])?;
    check_shape("stats cotangent (std)", grad.std.shape(), &[n, c])?;
    let hw = h * w;
    let count = mask.map_or(hw, |m| m.iter().filter(|&&b| b).count());
    if count < 2 {
        return Err(StyleError::TooFewPixels {
            what: "channel statistics backward",
            count,
        });
    }
    let m = count as f64;
    let data = planes(x);
    let mut out = vec![T::zero(); n * c * hw];
    out.par_chunks_mut(hw)
        .zip(data.par_chunks(hw))
        .enumerate()
        .for_each(|(p, (o, plane))| {
            let (i, j) = (p / c, p % c);
            let mean = stats.mean[[i, j]].to_f64_exact();
            let std = stats.std[[i, j]].to_f64_exact();
            let gm = grad.mean[[i, j]].to_f64_exact() / m;
            let gs = grad.std[[i, j]].to_f64_exact() / ((m - 1.0) * std);
            for (k, (o, &v)) in o.iter_mut().zip(plane).enumerate() {
                if mask.is_none_or(|mk| mk[k]) {
                    *o = T::lit(gm + gs * (v.to_f64_exact() - mean));
                }
            }
        });
    Ok(Array4::from_shape_vec((n, c, h, w), out).expect("length is n*c*h*w"))
}

/// Backward of [`channel_stats`]: the gradient w.r.t. `x` given `stats = channel_stats(x)` and
/// the cotangents `grad.mean = dL/dmean`, `grad.std = dL/dstd` (each `[N, C]`).
pub fn channel_stats_backward<T: Real>(
    x: &Array4<T>,
    stats: &ChannelStats<T>,
    grad: &ChannelStats<T>,
) -> Result<Array4<T>> {
    stats_backward_impl(x, None, stats, grad)
}

/// Backward of [`masked_channel_stats`]; pixels outside the mask receive zero gradient.
pub fn masked_channel_stats_backward<T: Real>(
    x: &Array4<T>,
    mask: ArrayView2<bool>,
    stats: &ChannelStats<T>,
    grad: &ChannelStats<T>,
) -> Result<Array4<T>> {
    let (_, _, h, w) = dims(x);
    let m = flat_mask(mask, h, w)?;
    stats_backward_impl(x, Some(&m), stats, grad)
}

/// Nearest-neighbour resize of a mask to `[h, w]` (PyTorch's `nearest` rule: output pixel `i`
/// reads input pixel `floor(i * in / out)`), e.g. to bring an image-resolution region mask to the
/// resolution of a feature map.
pub fn resize_mask_nearest(mask: ArrayView2<bool>, h: usize, w: usize) -> Result<Array2<bool>> {
    let (ih, iw) = mask.dim();
    if ih == 0 || iw == 0 {
        return Err(StyleError::Invalid {
            what: "mask resize",
            problem: format!("the input mask is empty ({ih}x{iw})"),
        });
    }
    Ok(Array2::from_shape_fn((h, w), |(y, x)| {
        mask[[y * ih / h, x * iw / w]]
    }))
}

/// Applies `f(n, c, input_plane, output_plane)` to every `(n, c)` plane of `x` in parallel and
/// returns the output map (same shape as `x`).
pub(crate) fn map_planes<T, F>(x: &Array4<T>, f: F) -> Array4<T>
where
    T: Real,
    F: Fn(usize, usize, &[T], &mut [T]) + Sync,
{
    let (n, c, h, w) = dims(x);
    let hw = h * w;
    let data = planes(x);
    let mut out = vec![T::zero(); n * c * hw];
    if hw > 0 {
        out.par_chunks_mut(hw)
            .zip(data.par_chunks(hw))
            .enumerate()
            .for_each(|(p, (o, i))| f(p / c, p % c, i, o));
    }
    Array4::from_shape_vec((n, c, h, w), out).expect("length is n*c*h*w")
}
