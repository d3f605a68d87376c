//! Spatial control: different styles in different regions of one content feature map.
//!
//! Each region is a boolean `[H, W]` mask at the feature map's resolution (use
//! [`crate::stats::resize_mask_nearest`] to bring an image mask there) with a style. Inside a
//! region the content is normalised with the statistics of the region's own pixels and given the
//! region's style statistics:
//!
//! ```text
//! out_i = std_s * (c_i - mean_R(c)) / std_R(c) + mean_s        for i in R
//! out_i = c_i                                                   for i in no region
//! ```
//!
//! which is AdaIN applied to the content pixels of the region alone (the approach of the original
//! AdaIN paper's spatial control). Regions must not overlap and must hold at least two pixels.

use base::Real;
use ndarray::{Array4, ArrayView2};

use crate::adain::normalize_backward_impl;
use crate::error::{check_shape, Result, StyleError};
use crate::stats::{dims, map_planes, masked_channel_stats, planes, ChannelStats};

/// One region of spatial control: a mask at feature resolution and the style to give it.
#[derive(Clone, Copy, Debug)]
pub struct Region<'a, T> {
    /// `[H, W]` mask at the content feature map's resolution; `true` marks the region's pixels
    /// (at least two, and no pixel may belong to two regions).
    pub mask: ArrayView2<'a, bool>,
    /// The style statistics given to the region, `[N, C]` (or `[1, C]`, broadcast over the batch).
    pub style: &'a ChannelStats<T>,
}

/// For every pixel, the index of its region (`None` outside all). Checks shapes and overlaps.
fn region_index<T: Real>(
    content: &Array4<T>,
    regions: &[Region<'_, T>],
) -> Result<Vec<Option<usize>>> {
    let (n, c, h, w) = dims(content);
    let mut owner = vec![None; h * w];
    for (r, region) in regions.iter().enumerate() {
        check_shape("region mask", region.mask.shape(), &[h, w])?;
        region
            .style
            .check_applies("region style statistics", n, c)?;
        for (k, &inside) in region.mask.iter().enumerate() {
            if inside {
                if let Some(prev) = owner[k] {
                    return Err(StyleError::Invalid {
                        what: "spatial control",
                        problem: format!(
                            "regions {prev} and {r} overlap at pixel ({}, {})",
                            k / w,
                            k % w
                        ),
                    });
                }
                owner[k] = Some(r);
            }
        }
    }
    Ok(owner)
}

/// Region-wise AdaIN (see the module documentation).
pub fn adain_spatial<T: Real>(content: &Array4<T>, regions: &[Region<'_, T>]) -> Result<Array4<T>> {
    let owner = region_index(content, regions)?;
    let local: Vec<ChannelStats<T>> = regions
        .iter()
        .map(|r| masked_channel_stats(content, r.mask))
        .collect::<Result<_>>()?;
    Ok(map_planes(content, |i, j, inp, out| {
        for (k, (o, &v)) in out.iter_mut().zip(inp).enumerate() {
            *o = match owner[k] {
                None => v,
                Some(r) => {
                    let (cs, ss) = (&local[r], regions[r].style);
                    let y = (v.to_f64_exact() - cs.mean[[i, j]].to_f64_exact())
                        / cs.std[[i, j]].to_f64_exact();
                    let row = ss.row_for(i);
                    T::lit(ss.std[[row, j]].to_f64_exact() * y + ss.mean[[row, j]].to_f64_exact())
                }
            };
        }
    }))
}

/// Backward of [`adain_spatial`] with respect to the content (the styles are constants).
pub fn adain_spatial_backward<T: Real>(
    content: &Array4<T>,
    regions: &[Region<'_, T>],
    grad: &Array4<T>,
) -> Result<Array4<T>> {
    check_shape("adain_spatial cotangent", grad.shape(), content.shape())?;
    let owner = region_index(content, regions)?;
    let (_, c, h, w) = dims(content);
    let hw = h * w;
    // Outside every region the map is the identity.
    let mut out = map_planes(grad, |_, _, g, o| {
        for (k, (o, &g)) in o.iter_mut().zip(g).enumerate() {
            if owner[k].is_none() {
                *o = g;
            }
        }
    });
    for region in regions {
        let stats = masked_channel_stats(content, region.mask)?;
        let mask: Vec<bool> = region.mask.iter().copied().collect();
        let style = region.style;
        let gd = planes(grad);
        // dL/dy = std_s * g inside the region.
        let g_y = map_planes(grad, |i, j, _, o| {
            let s = style.std[[style.row_for(i), j]].to_f64_exact();
            let p = (i * c + j) * hw;
            for (k, o) in o.iter_mut().enumerate() {
                if mask[k] {
                    *o = T::lit(s * gd[p + k].to_f64_exact());
                }
            }
        });
        let g_x = normalize_backward_impl(content, Some(&mask), &stats, &g_y);
        out.zip_mut_with(&g_x, |a, &b| *a += b);
    }
    Ok(out)
}
