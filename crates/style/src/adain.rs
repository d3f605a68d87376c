//! Adaptive instance normalisation (AdaIN) and the 3D style transform `T`, forward and backward.
//!
//! With per-channel statistics from [`crate::stats`] (unbiased variance, eps 1e-5):
//!
//! ```text
//! normalize(x)      = (x - mean_x) / std_x                    (instance normalisation)
//! T_s(y)            = std_s * y + mean_s                      (the 3D transform, on normalised y)
//! adain(c, s)       = T_s(normalize(c))
//! adain_alpha       = alpha * adain(c, s) + (1 - alpha) * c   (content-style trade-off)
//! adain_mix         = sum_i w_i adain(c, s_i)                 (style interpolation; the weights
//!                                                              are used as given, not normalised)
//! ```
//!
//! Style statistics with `N = 1` broadcast over a content batch; otherwise `N` must match.
//! Element-wise arithmetic is carried out in `f64` and rounded once to the output type.

use base::Real;
use ndarray::Array4;

use crate::error::{check_shape, Result, StyleError};
use crate::stats::{channel_stats, dims, map_planes, planes, ChannelStats};

/// `(x - mean) / std` per channel with the given statistics of `x` (`[N, C]`).
pub fn normalize<T: Real>(x: &Array4<T>, stats: &ChannelStats<T>) -> Result<Array4<T>> {
    let (n, c, _, _) = dims(x);
    check_shape("normalize stats", stats.mean.shape(), &[n, c])?;
    check_shape("normalize stats (std)", stats.std.shape(), &[n, c])?;
    Ok(map_planes(x, |i, j, inp, out| {
        let m = stats.mean[[i, j]].to_f64_exact();
        let s = stats.std[[i, j]].to_f64_exact();
        for (o, &v) in out.iter_mut().zip(inp) {
            *o = T::lit((v.to_f64_exact() - m) / s);
        }
    }))
}

/// Instance normalisation with the feature map's own statistics: `normalize(x, stats(x))`.
pub fn instance_normalize<T: Real>(x: &Array4<T>) -> Result<Array4<T>> {
    normalize(x, &channel_stats(x)?)
}

/// Backward of [`instance_normalize`], through the statistics as well. With `y` the normalised
/// map, `m` pixels and cotangent `g`:
/// `dL/dx = (g - mean(g) - y * sum(g * y) / (m - 1)) / std`.
pub fn instance_normalize_backward<T: Real>(x: &Array4<T>, grad: &Array4<T>) -> Result<Array4<T>> {
    check_shape("instance_normalize cotangent", grad.shape(), x.shape())?;
    let stats = channel_stats(x)?;
    Ok(normalize_backward_impl(x, None, &stats, grad))
}

/// The instance-normalisation backward over the pixels of `mask` (all when `None`) with the
/// statistics of those pixels; pixels outside the mask get zero. Shapes are checked by callers.
pub(crate) fn normalize_backward_impl<T: Real>(
    x: &Array4<T>,
    mask: Option<&[bool]>,
    stats: &ChannelStats<T>,
    grad: &Array4<T>,
) -> Array4<T> {
    let g = planes(grad);
    let (_, c, h, w) = dims(x);
    let hw = h * w;
    let inside = |k: usize| mask.is_none_or(|mk| mk[k]);
    let m = (0..hw).filter(|&k| inside(k)).count() as f64;
    map_planes(x, |i, j, inp, out| {
        let mean = stats.mean[[i, j]].to_f64_exact();
        let std = stats.std[[i, j]].to_f64_exact();
        let gp = &g[(i * c + j) * hw..(i * c + j + 1) * hw];
        let (mut sg, mut sgy) = (0.0f64, 0.0f64);
        for (k, (&gv, &xv)) in gp.iter().zip(inp).enumerate() {
            if inside(k) {
                let y = (xv.to_f64_exact() - mean) / std;
                sg += gv.to_f64_exact();
                sgy += gv.to_f64_exact() * y;
            }
        }
        let (gmean, k_y) = (sg / m, sgy / (m - 1.0));
        for (k, ((o, &gv), &xv)) in out.iter_mut().zip(gp).zip(inp).enumerate() {
            if inside(k) {
                let y = (xv.to_f64_exact() - mean) / std;
                *o = T::lit((gv.to_f64_exact() - gmean - y * k_y) / std);
            }
        }
    })
}

/// The 3D transform `T(y) = std_s * y + mean_s` per channel, for features `y` that are already
/// normalised (e.g. lifted Gaussian features).
pub fn style_transform<T: Real>(y: &Array4<T>, style: &ChannelStats<T>) -> Result<Array4<T>> {
    let (n, c, _, _) = dims(y);
    style.check_applies("style statistics", n, c)?;
    Ok(map_planes(y, |i, j, inp, out| {
        let r = style.row_for(i);
        let m = style.mean[[r, j]].to_f64_exact();
        let s = style.std[[r, j]].to_f64_exact();
        for (o, &v) in out.iter_mut().zip(inp) {
            *o = T::lit(s * v.to_f64_exact() + m);
        }
    }))
}

/// Backward of [`style_transform`]: returns `(dL/dy, dL/d(style stats))`. The statistics'
/// cotangent has the style's shape (summed over the batch when the style broadcasts):
/// `dL/dmean_s = sum g`, `dL/dstd_s = sum g * y`, `dL/dy = std_s * g`.
pub fn style_transform_backward<T: Real>(
    y: &Array4<T>,
    style: &ChannelStats<T>,
    grad: &Array4<T>,
) -> Result<(Array4<T>, ChannelStats<T>)> {
    let (n, c, h, w) = dims(y);
    style.check_applies("style statistics", n, c)?;
    check_shape("style_transform cotangent", grad.shape(), y.shape())?;
    let hw = h * w;
    let yd = planes(y);
    let g_y = map_planes(grad, |i, j, inp, out| {
        let s = style.std[[style.row_for(i), j]].to_f64_exact();
        for (o, &g) in out.iter_mut().zip(inp) {
            *o = T::lit(s * g.to_f64_exact());
        }
    });
    let gd = planes(grad);
    let mut gm = vec![0.0f64; style.batch() * c];
    let mut gs = vec![0.0f64; style.batch() * c];
    // Fixed order: sample by sample, so a broadcast style sums its batch deterministically.
    for i in 0..n {
        let r = style.row_for(i);
        for j in 0..c {
            let p = (i * c + j) * hw;
            let (mut a, mut b) = (0.0f64, 0.0f64);
            for k in p..p + hw {
                let g = gd[k].to_f64_exact();
                a += g;
                b += g * yd[k].to_f64_exact();
            }
            gm[r * c + j] += a;
            gs[r * c + j] += b;
        }
    }
    let shape = (style.batch(), c);
    let to_arr = |v: Vec<f64>| {
        ndarray::Array2::from_shape_vec(shape, v.into_iter().map(T::lit).collect())
            .expect("length is batch*c")
    };
    Ok((g_y, ChannelStats::new(to_arr(gm), to_arr(gs))?))
}

/// `adain(c, s)` with the style given by its statistics.
pub fn adain_with_stats<T: Real>(
    content: &Array4<T>,
    style: &ChannelStats<T>,
) -> Result<Array4<T>> {
    style_transform(&instance_normalize(content)?, style)
}

/// `adain(c, s) = (c - mean_c) / std_c * std_s + mean_s` from content and style feature maps
/// (they may differ in spatial size).
pub fn adain<T: Real>(content: &Array4<T>, style: &Array4<T>) -> Result<Array4<T>> {
    adain_with_stats(content, &channel_stats(style)?)
}

/// Backward of [`adain_with_stats`]: returns `(dL/dcontent, dL/d(style stats))`. Chain the second
/// through [`crate::stats::channel_stats_backward`] to reach the style features.
pub fn adain_backward<T: Real>(
    content: &Array4<T>,
    style: &ChannelStats<T>,
    grad: &Array4<T>,
) -> Result<(Array4<T>, ChannelStats<T>)> {
    let y = instance_normalize(content)?;
    let (g_y, g_style) = style_transform_backward(&y, style, grad)?;
    Ok((instance_normalize_backward(content, &g_y)?, g_style))
}

/// `alpha * a + (1 - alpha) * b`, element-wise.
pub fn blend<T: Real>(a: &Array4<T>, b: &Array4<T>, alpha: f64) -> Result<Array4<T>> {
    check_shape("blend operands", b.shape(), a.shape())?;
    check_finite("blend alpha", alpha)?;
    let bd = planes(b);
    let (_, c, h, w) = dims(a);
    let hw = h * w;
    Ok(map_planes(a, |i, j, inp, out| {
        let bp = &bd[(i * c + j) * hw..(i * c + j + 1) * hw];
        for ((o, &x), &y) in out.iter_mut().zip(inp).zip(bp) {
            *o = T::lit(alpha * x.to_f64_exact() + (1.0 - alpha) * y.to_f64_exact());
        }
    }))
}

/// The content-style trade-off `alpha * adain(c, s) + (1 - alpha) * c` (alpha 1: full style,
/// alpha 0: the content feature unchanged).
pub fn adain_alpha<T: Real>(
    content: &Array4<T>,
    style: &ChannelStats<T>,
    alpha: f64,
) -> Result<Array4<T>> {
    blend(&adain_with_stats(content, style)?, content, alpha)
}

/// The statistics of a weighted style mixture: `mean = sum_i w_i mean_i`, `std = sum_i w_i std_i`.
/// Because `T_s` is affine in the statistics, `sum_i w_i T_{s_i}(y) = T_mix(y)` exactly, so a
/// mixture is one transform (and can be folded into a decoder like a single style).
pub fn mix_stats<T: Real>(styles: &[(&ChannelStats<T>, f64)]) -> Result<ChannelStats<T>> {
    let Some((first, _)) = styles.first() else {
        return Err(StyleError::Invalid {
            what: "style mixture",
            problem: "no styles given".into(),
        });
    };
    let shape = first.mean.raw_dim();
    let mut mean = ndarray::Array2::<f64>::zeros(shape);
    let mut std = ndarray::Array2::<f64>::zeros(shape);
    for &(style, weight) in styles {
        check_finite("style mixture weight", weight)?;
        check_shape(
            "style mixture member",
            style.mean.shape(),
            first.mean.shape(),
        )?;
        mean.zip_mut_with(&style.mean, |a, &v| *a += weight * v.to_f64_exact());
        std.zip_mut_with(&style.std, |a, &v| *a += weight * v.to_f64_exact());
    }
    ChannelStats::new(mean.mapv(T::lit), std.mapv(T::lit))
}

/// Interpolation between styles: `sum_i w_i adain(c, s_i)`, computed as one transform with
/// [`mix_stats`]. The weights are used as given (the usual choice sums to one; that is left to
/// the caller).
pub fn adain_mix<T: Real>(
    content: &Array4<T>,
    styles: &[(&ChannelStats<T>, f64)],
) -> Result<Array4<T>> {
    adain_with_stats(content, &mix_stats(styles)?)
}

pub(crate) fn check_finite(what: &'static str, value: f64) -> Result<()> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(StyleError::NonFinite { what, value })
    }
}
