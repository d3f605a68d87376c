//! Folding the 3D style transform into the decoder's first convolution.
//!
//! For a fixed style, `T(y) = std_s * y + mean_s` is a per-channel affine map, and the decoder
//! starts with a reflection-padded convolution `W * pad(x) + b`. Reflection padding copies
//! pixels, so it commutes with per-channel affine maps, and a constant channel stays constant
//! after padding. Hence, exactly,
//!
//! ```text
//! W * pad(T(y)) + b = W' * pad(y) + b'
//! W'[o, i, kh, kw] = W[o, i, kh, kw] * std_s[i]
//! b'[o]            = b[o] + sum_{i, kh, kw} W[o, i, kh, kw] * mean_s[i]
//! ```
//!
//! The folded decoder renders normalised features directly, skipping the separate pass over the
//! (wide) feature map. A style mixture ([`crate::adain::mix_stats`]) folds the same way.

use base::Real;
use nets::Decoder;

use crate::error::{Result, StyleError};
use crate::stats::ChannelStats;

/// The decoder with `T_s` folded into its first convolution: `fold(g, s)(y) = g(T_s(y))`.
/// The statistics must be a single style (`N = 1`) with the decoder's input width.
pub fn fold_style_transform<T: Real>(
    decoder: &Decoder<T>,
    style: &ChannelStats<T>,
) -> Result<Decoder<T>> {
    let mut folded = decoder.clone();
    let first = folded
        .layers_mut()
        .next()
        .ok_or_else(|| StyleError::Invalid {
            what: "style folding",
            problem: "the decoder has no convolution".into(),
        })?;
    let (o, c, kh, kw) = first.weight.dim();
    if style.batch() != 1 || style.channels() != c {
        return Err(StyleError::Shape {
            what: "style statistics to fold into the decoder",
            expected: vec![1, c],
            actual: vec![style.batch(), style.channels()],
        });
    }
    for oc in 0..o {
        let mut shift = 0.0f64;
        for ic in 0..c {
            let m = style.mean[[0, ic]].to_f64_exact();
            let s = style.std[[0, ic]].to_f64_exact();
            for y in 0..kh {
                for x in 0..kw {
                    let w = first.weight[[oc, ic, y, x]].to_f64_exact();
                    shift += w * m;
                    first.weight[[oc, ic, y, x]] = T::lit(w * s);
                }
            }
        }
        first.bias[oc] = T::lit(first.bias[oc].to_f64_exact() + shift);
    }
    Ok(folded)
}
