//! The losses of decoder training and of 3D stylization, each with its gradient.
//!
//! Reductions follow PyTorch's `reduction="mean"`:
//!
//! ```text
//! mse(a, b)  = (1/K) sum_k (a_k - b_k)^2        d/da = 2 (a - b) / K,   d/db = -d/da
//! l1(a, b)   = (1/K) sum_k |a_k - b_k|          d/da = sign(a - b) / K  (sign(0) = 0, as PyTorch)
//! content(g, t)  = mse(g, t)
//! style(G, S)    = sum_l mse(mean(G_l), mean(S_l)) + mse(std(G_l), std(S_l))
//! ```
//!
//! where `l` runs over the encoder levels relu1_1 .. relu_k_1 and the statistics are those of
//! [`crate::stats`] (`[N, C]`, i.e. PyTorch's `[N, C, 1, 1]` tensors, so `K = N*C`). Style
//! statistics with `N = 1` broadcast over a batch, and `K` then counts the broadcast elements,
//! as PyTorch does. Sums run in `f64` in a fixed order: over feature maps (`mse`, `l1`) each
//! plane as [`crate::stats`] sums it and the plane sums in plane order, the rest sequentially.

use base::Real;
use ndarray::{Array2, Array4};

use crate::error::{check_shape, Result, StyleError};
use rayon::prelude::*;

use crate::stats::{
    channel_stats, channel_stats_backward, dims, interleaved_sum, map_planes, planes, ChannelStats,
};

/// Which penalty the alignment loss uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AlignLoss {
    /// Mean squared error (the default).
    #[default]
    Mse,
    /// Mean absolute error.
    L1,
}

/// `sum_i f(a_i - b_i)` in `f64` over two maps of one shape: each `(n, c)` plane is summed in
/// the order of [`interleaved_sum`], the planes in parallel, and the plane sums are added in
/// plane order, so the result does not depend on the thread count.
fn zip_sum<T: Real>(a: &Array4<T>, b: &Array4<T>, f: impl Fn(f64) -> f64 + Sync) -> f64 {
    let (_, _, h, w) = dims(a);
    let hw = (h * w).max(1);
    let (a, b) = (planes(a), planes(b));
    let sums: Vec<f64> = a
        .par_chunks(hw)
        .zip(b.par_chunks(hw))
        .map(|(pa, pb)| {
            interleaved_sum(pa.len(), |i| f(pa[i].to_f64_exact() - pb[i].to_f64_exact()))
        })
        .collect();
    sums.iter().fold(0.0, |s, v| s + v)
}

/// Mean squared error over all elements.
pub fn mse<T: Real>(a: &Array4<T>, b: &Array4<T>) -> Result<T> {
    check_shape("mse operands", b.shape(), a.shape())?;
    let k = a.len() as f64;
    Ok(T::lit(zip_sum(a, b, |d| d * d) / k))
}

/// Gradient of `g * mse(a, b)` w.r.t. `a` (the gradient w.r.t. `b` is its negative).
pub fn mse_backward<T: Real>(a: &Array4<T>, b: &Array4<T>, g: T) -> Result<Array4<T>> {
    check_shape("mse operands", b.shape(), a.shape())?;
    let scale = 2.0 * g.to_f64_exact() / a.len() as f64;
    Ok(elementwise(a, b, |d| scale * d))
}

/// Mean absolute error over all elements.
pub fn l1<T: Real>(a: &Array4<T>, b: &Array4<T>) -> Result<T> {
    check_shape("l1 operands", b.shape(), a.shape())?;
    let k = a.len() as f64;
    Ok(T::lit(zip_sum(a, b, f64::abs) / k))
}

/// Gradient of `g * l1(a, b)` w.r.t. `a` (the gradient w.r.t. `b` is its negative). Where
/// `a == b` the subgradient 0 is used, as in PyTorch.
pub fn l1_backward<T: Real>(a: &Array4<T>, b: &Array4<T>, g: T) -> Result<Array4<T>> {
    check_shape("l1 operands", b.shape(), a.shape())?;
    let scale = g.to_f64_exact() / a.len() as f64;
    Ok(elementwise(a, b, |d| {
        if d > 0.0 {
            scale
        } else if d < 0.0 {
            -scale
        } else {
            0.0
        }
    }))
}

fn elementwise<T: Real>(a: &Array4<T>, b: &Array4<T>, f: impl Fn(f64) -> f64 + Sync) -> Array4<T> {
    let bd = planes(b);
    let (_, c, h, w) = dims(a);
    let hw = h * w;
    map_planes(a, |i, j, inp, out| {
        let bp = &bd[(i * c + j) * hw..(i * c + j + 1) * hw];
        for ((o, &x), &y) in out.iter_mut().zip(inp).zip(bp) {
            *o = T::lit(f(x.to_f64_exact() - y.to_f64_exact()));
        }
    })
}

/// Content loss: `mse(generated, target)`.
pub fn content_loss<T: Real>(generated: &Array4<T>, target: &Array4<T>) -> Result<T> {
    mse(generated, target)
}

/// Gradient of `g * content_loss` w.r.t. the generated features (the target's is its negative).
pub fn content_loss_backward<T: Real>(
    generated: &Array4<T>,
    target: &Array4<T>,
    g: T,
) -> Result<Array4<T>> {
    mse_backward(generated, target, g)
}

/// Alignment loss between the lifted feature map and the normalised encoder feature.
pub fn align_loss<T: Real>(lifted: &Array4<T>, target: &Array4<T>, kind: AlignLoss) -> Result<T> {
    match kind {
        AlignLoss::Mse => mse(lifted, target),
        AlignLoss::L1 => l1(lifted, target),
    }
}

/// Gradient of `g * align_loss` w.r.t. the lifted feature map.
pub fn align_loss_backward<T: Real>(
    lifted: &Array4<T>,
    target: &Array4<T>,
    kind: AlignLoss,
    g: T,
) -> Result<Array4<T>> {
    match kind {
        AlignLoss::Mse => mse_backward(lifted, target, g),
        AlignLoss::L1 => l1_backward(lifted, target, g),
    }
}

/// `(sum of squared differences, K)` between generated `[N, C]` statistics and style statistics
/// broadcast over the batch.
fn stats_sq<T: Real>(
    gen: &Array2<T>,
    style: &ChannelStats<T>,
    pick: fn(&ChannelStats<T>) -> &Array2<T>,
) -> f64 {
    let s = pick(style);
    let mut acc = 0.0f64;
    for ((i, j), &v) in gen.indexed_iter() {
        let d = v.to_f64_exact() - s[[style.row_for(i), j]].to_f64_exact();
        acc += d * d;
    }
    acc
}

fn check_levels<T: Real>(generated: &[Array4<T>], style: &[ChannelStats<T>]) -> Result<()> {
    if generated.is_empty() || generated.len() != style.len() {
        return Err(StyleError::Invalid {
            what: "style loss",
            problem: format!(
                "{} generated feature levels for {} style levels (need the same, at least one)",
                generated.len(),
                style.len()
            ),
        });
    }
    for (g, s) in generated.iter().zip(style) {
        let (n, c, _, _) = dims(g);
        s.check_applies("style loss level statistics", n, c)?;
    }
    Ok(())
}

/// Style loss: the sum over levels of `mse(mean(G_l), mean_s) + mse(std(G_l), std_s)`, with the
/// style's statistics given per level (computed once per style image).
pub fn style_loss<T: Real>(generated: &[Array4<T>], style: &[ChannelStats<T>]) -> Result<T> {
    check_levels(generated, style)?;
    let stats = generated
        .iter()
        .map(channel_stats)
        .collect::<Result<Vec<_>>>()?;
    style_loss_of_stats(&stats, style)
}

/// [`style_loss`] from the statistics of the generated levels (e.g. accumulated tile by tile,
/// [`crate::ChannelMoments`]) instead of the levels themselves.
pub fn style_loss_of_stats<T: Real>(
    generated: &[ChannelStats<T>],
    style: &[ChannelStats<T>],
) -> Result<T> {
    if generated.is_empty() || generated.len() != style.len() {
        return Err(StyleError::Invalid {
            what: "style loss",
            problem: format!(
                "statistics of {} generated feature levels for {} style levels (need the same, \
                 at least one)",
                generated.len(),
                style.len()
            ),
        });
    }
    let mut total = 0.0f64;
    for (gs, s) in generated.iter().zip(style) {
        s.check_applies("style loss level statistics", gs.batch(), gs.channels())?;
        let k = gs.mean.len() as f64;
        total += stats_sq(&gs.mean, s, |x| &x.mean) / k + stats_sq(&gs.std, s, |x| &x.std) / k;
    }
    Ok(T::lit(total))
}

/// Gradient of `g * style_loss` w.r.t. every generated feature level.
pub fn style_loss_backward<T: Real>(
    generated: &[Array4<T>],
    style: &[ChannelStats<T>],
    g: T,
) -> Result<Vec<Array4<T>>> {
    check_levels(generated, style)?;
    generated
        .iter()
        .zip(style)
        .map(|(feat, s)| {
            let gs = channel_stats(feat)?;
            let scale = 2.0 * g.to_f64_exact() / gs.mean.len() as f64;
            let cot = |gen: &Array2<T>, sty: &Array2<T>| {
                Array2::from_shape_fn(gen.raw_dim(), |(i, j)| {
                    T::lit(
                        scale
                            * (gen[[i, j]].to_f64_exact() - sty[[s.row_for(i), j]].to_f64_exact()),
                    )
                })
            };
            let grad = ChannelStats::new(cot(&gs.mean, &s.mean), cot(&gs.std, &s.std))?;
            channel_stats_backward(feat, &gs, &grad)
        })
        .collect()
}
