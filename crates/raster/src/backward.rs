//! The backward pass: exact gradients of a scalar loss with respect to every rasterizer input,
//! given its cotangents on the channel image, the alpha image and the depth image.
//!
//! # Per pixel
//! Write the pixel's loss as `L = sum_i w_i g_i + T_final g_bg`, where, for the Gaussians the
//! pixel blends (in order), `g_i = v_image . c_i + v_depth z_i + v_alpha` and
//! `g_bg = v_image . background` (the alpha image `1 - T_final` equals `sum_i w_i`). Then
//! `dL/dc_i = w_i v_image`, `dL/dz_i = w_i v_depth` and `dL/dalpha_i = T_i (g_i - S_i)`, where
//! `S_i` is what the pixel shows behind Gaussian `i` at unit transmittance:
//! `S_last = g_bg`, `S_{i-1} = alpha_i g_i + (1 - alpha_i) S_i`.
//!
//! The pass is exact and division-free: a first front-to-back sweep recomputes each blended
//! Gaussian's `alpha_i` and `T_i` exactly as the forward pass did (the same products in the same
//! order, the same skip and stop decisions) and keeps them in a per-thread list; a second sweep
//! runs back to front over that list, accumulating `S` (a convex combination, hence stable).
//! There is no `T_i = T_{i+1} / (1 - alpha_i)` recovery, which loses precision when
//! `alpha_i` is close to 1.
//!
//! Through `alpha = min(0.999, opacity exp(-sigma))`: when the clamp is active the gradient is zero
//! (as `torch.clamp_max`); otherwise `dalpha/dopacity = exp(-sigma)`, `dalpha/dsigma = -alpha`,
//! `dsigma/dconic = (dx^2 / 2, dx dy, dy^2 / 2)` and `dsigma/dmean2d = (a dx + b dy, b dx + c dy)`.
//! The stop and skip decisions are piecewise constant and carry no gradient.
//!
//! # Determinism and memory
//! Tiles run in parallel. Each tile accumulates its pixels' contributions, in a fixed pixel
//! order, into one partial-gradient record per intersection (`7 + D` reals). Records are then
//! summed per Gaussian in ascending intersection order (tile order), whatever the thread count.
//! Tiles are processed in consecutive batches whose records fit in a budget
//! (`gradient_buffer_values`, default [`DEFAULT_GRADIENT_BUFFER_VALUES`]), so the peak memory is:
//! the outputs, `N (7 + D)` reals of per-Gaussian accumulators, `min(budget, I (7 + D))` reals of
//! records (`I` intersections; a single tile larger than the budget gets a batch of its own),
//! `D` reals per tile for the background gradient, and per thread one tile's packed Gaussians
//! (7 reals each), its row lists (8 bytes per Gaussian and row it reaches, see [`crate::rows`])
//! and one pixel's blend list (4 reals and 2 words per blended Gaussian).

use gaussian::Real;
use rayon::prelude::*;

use crate::blend::{evaluate, pixel_centre, Hit, Splat, TRANSMITTANCE_MIN};
use crate::error::{check_len, RasterError};
use crate::forward::Splats;
use crate::rows::{at_column, RowLists};
use crate::tiles::TileBins;

/// Default budget for the per-intersection gradient records: 2^24 reals (128 MiB in `f64`).
pub const DEFAULT_GRADIENT_BUFFER_VALUES: usize = 1 << 24;

/// Record layout: the first `GEOMETRY` reals of a record.
const MEAN_X: usize = 0;
const MEAN_Y: usize = 1;
const CONIC_A: usize = 2;
const CONIC_B: usize = 3;
const CONIC_C: usize = 4;
const OPACITY: usize = 5;
const DEPTH: usize = 6;
const GEOMETRY: usize = 7;

/// Cotangents of the rasterizer outputs (row-major, like [`crate::Rasterized`]). `None` is a zero
/// cotangent.
#[derive(Clone, Copy, Debug)]
pub struct Cotangents<'a, T> {
    /// `height * width * channel_count` values.
    pub image: &'a [T],
    /// `height * width` values, on the alpha image.
    pub alpha: Option<&'a [T]>,
    /// `height * width` values, on the accumulated depth image `sum_i w_i z_i`.
    pub depth: Option<&'a [T]>,
}

/// Gradients with respect to every rasterizer input.
#[derive(Clone, Debug, PartialEq)]
pub struct SplatGrads<T> {
    pub means2d: Vec<[T; 2]>,
    pub conics: Vec<[T; 3]>,
    /// With respect to the opacities (after the sigmoid).
    pub opacities: Vec<T>,
    pub depths: Vec<T>,
    /// `len() * channel_count`, Gaussian-major.
    pub channels: Vec<T>,
    /// `channel_count` values.
    pub background: Vec<T>,
}

/// Folds a cotangent on the normalised depth `depth / alpha` into cotangents on the accumulated
/// depth and the alpha image (adding to `v_depth` and `v_alpha`):
/// `d(z/a)/dz = 1/a`, `d(z/a)/da = -z/a^2`. Pixels with `alpha == 0` (where the normalised depth is
/// defined as 0) receive nothing.
pub fn fold_normalized_depth_cotangent<T: Real>(
    depth: &[T],
    alpha: &[T],
    v_normalized_depth: &[T],
    v_depth: &mut [T],
    v_alpha: &mut [T],
) -> Result<(), RasterError> {
    let n = depth.len();
    check_len("alpha", alpha.len(), n)?;
    check_len("v_normalized_depth", v_normalized_depth.len(), n)?;
    check_len("v_depth", v_depth.len(), n)?;
    check_len("v_alpha", v_alpha.len(), n)?;
    for p in 0..n {
        let a = alpha[p];
        if a > T::zero() {
            v_depth[p] += v_normalized_depth[p] / a;
            v_alpha[p] -= v_normalized_depth[p] * depth[p] / (a * a);
        }
    }
    Ok(())
}

/// Gradients of the loss whose cotangents are `cot`, for the forward pass that produced `bins`
/// (take them from [`crate::Rasterized::bins`]).
pub fn rasterize_backward<T: Real>(
    splats: &Splats<T>,
    bins: &TileBins,
    background: &[T],
    cot: &Cotangents<T>,
) -> Result<SplatGrads<T>, RasterError> {
    rasterize_backward_with_budget(
        splats,
        bins,
        background,
        cot,
        DEFAULT_GRADIENT_BUFFER_VALUES,
    )
}

/// [`rasterize_backward`] with an explicit budget (in reals) for the per-intersection gradient
/// records. The result does not depend on the budget.
pub fn rasterize_backward_with_budget<T: Real>(
    splats: &Splats<T>,
    bins: &TileBins,
    background: &[T],
    cot: &Cotangents<T>,
    gradient_buffer_values: usize,
) -> Result<SplatGrads<T>, RasterError> {
    splats.validate()?;
    let n = splats.len();
    let d = splats.channel_count;
    let (width, height) = (bins.width(), bins.height());
    bins.check(n)?;
    check_len("background", background.len(), d)?;
    let pixels = width as usize * height as usize;
    check_len("v_image", cot.image.len(), pixels * d)?;
    if let Some(v) = cot.alpha {
        check_len("v_alpha", v.len(), pixels)?;
    }
    if let Some(v) = cot.depth {
        check_len("v_depth", v.len(), pixels)?;
    }

    let stride = GEOMETRY + d;
    let mut acc = vec![T::zero(); n * stride];
    let tiles = bins.tile_count();
    let mut tile_bg = vec![T::zero(); tiles * d];
    let mut records: Vec<T> = Vec::new();
    // Group per-Gaussian accumulation into as many contiguous index ranges as there are threads;
    // each Gaussian's sum runs in intersection order whatever the grouping.
    let groups = rayon::current_num_threads().max(1);
    let per_group = n.div_ceil(groups).max(1);

    let mut first = 0;
    while first < tiles {
        // The batch: tiles [first, last) whose records fit the budget (at least one tile).
        let begin = bins.range(first).start;
        let mut last = first + 1;
        while last < tiles && (bins.range(last).end - begin) * stride <= gradient_buffer_values {
            last += 1;
        }
        let end = bins.range(last - 1).end;
        records.clear();
        records.resize((end - begin) * stride, T::zero());

        // Split the records into per-tile slices.
        let mut slices: Vec<(usize, &mut [T], &mut [T])> = Vec::with_capacity(last - first);
        let mut rest: &mut [T] = &mut records;
        let mut bg_rest: &mut [T] = &mut tile_bg[first * d..last * d];
        for t in first..last {
            let (mine, tail) = rest.split_at_mut(bins.range(t).len() * stride);
            let (bg_mine, bg_tail) = bg_rest.split_at_mut(d);
            slices.push((t, mine, bg_mine));
            rest = tail;
            bg_rest = bg_tail;
        }
        slices
            .into_par_iter()
            .for_each_init(Scratch::default, |scratch, (t, rec, bg)| {
                backward_tile(splats, bins, background, cot, t, scratch, rec, bg);
            });

        // Sum the records per Gaussian, in intersection order.
        let ids = &bins.gaussian_ids()[begin..end];
        let records = &records;
        acc.par_chunks_mut(per_group * stride)
            .enumerate()
            .for_each(|(group, acc_group)| {
                let lo = group * per_group;
                let hi = lo + acc_group.len() / stride;
                for (j, &g) in ids.iter().enumerate() {
                    let g = g as usize;
                    if g < lo || g >= hi {
                        continue;
                    }
                    let dst = &mut acc_group[(g - lo) * stride..(g - lo + 1) * stride];
                    for (a, &r) in dst.iter_mut().zip(&records[j * stride..(j + 1) * stride]) {
                        *a += r;
                    }
                }
            });
        first = last;
    }

    let mut background_grad = vec![T::zero(); d];
    for t in 0..tiles {
        for (b, &v) in background_grad.iter_mut().zip(&tile_bg[t * d..(t + 1) * d]) {
            *b += v;
        }
    }
    let mut grads = SplatGrads {
        means2d: Vec::with_capacity(n),
        conics: Vec::with_capacity(n),
        opacities: Vec::with_capacity(n),
        depths: Vec::with_capacity(n),
        channels: Vec::with_capacity(n * d),
        background: background_grad,
    };
    for r in acc.chunks_exact(stride) {
        grads.means2d.push([r[MEAN_X], r[MEAN_Y]]);
        grads.conics.push([r[CONIC_A], r[CONIC_B], r[CONIC_C]]);
        grads.opacities.push(r[OPACITY]);
        grads.depths.push(r[DEPTH]);
        grads.channels.extend_from_slice(&r[GEOMETRY..]);
    }
    Ok(grads)
}

/// One blended Gaussian of the current pixel: its position in the tile list, its hit, and the
/// transmittance in front of it.
#[derive(Clone, Copy, Debug)]
struct Blended<T> {
    k: u32,
    hit: Hit<T>,
    trans: T,
}

/// Per-thread working memory.
#[derive(Default)]
struct Scratch<T> {
    packed: Vec<Splat<T>>,
    rows: RowLists,
    blended: Vec<Blended<T>>,
}

/// Accumulates one tile's gradient records (`7 + D` reals per tile intersection, in tile order)
/// and its background gradient.
#[allow(clippy::too_many_arguments)]
fn backward_tile<T: Real>(
    splats: &Splats<T>,
    bins: &TileBins,
    background: &[T],
    cot: &Cotangents<T>,
    t: usize,
    scratch: &mut Scratch<T>,
    rec: &mut [T],
    bg_grad: &mut [T],
) {
    let d = splats.channel_count;
    let stride = GEOMETRY + d;
    let ids = bins.tile(t);
    let Scratch {
        packed,
        rows,
        blended,
    } = scratch;
    packed.clear();
    packed.extend(ids.iter().map(|&g| splats.splat(g as usize)));
    let (x0, y0, x1, y1) = bins.pixel_rect(t);
    rows.build(packed, (x0, y0, x1, y1));
    let width = bins.width() as usize;
    let t_min = T::lit(TRANSMITTANCE_MIN);
    let half = T::lit(0.5);
    for py in y0..y1 {
        let cy = pixel_centre::<T>(py);
        let row = rows.row(py - y0);
        for px in x0..x1 {
            let cx = pixel_centre::<T>(px);
            let lx = (px - x0) as u8;
            let p = py as usize * width + px as usize;

            // Front to back: the forward pass's decisions, alphas and transmittances, over the
            // same row list.
            blended.clear();
            let mut trans = T::one();
            for k in at_column(row, lx) {
                let Some(hit) = evaluate(&packed[k], cx, cy) else {
                    continue;
                };
                let next = trans * (T::one() - hit.alpha);
                if next <= t_min {
                    break;
                }
                blended.push(Blended {
                    k: k as u32,
                    hit,
                    trans,
                });
                trans = next;
            }

            let v_img = &cot.image[p * d..(p + 1) * d];
            let v_alpha = cot.alpha.map_or(T::zero(), |v| v[p]);
            let v_depth = cot.depth.map_or(T::zero(), |v| v[p]);
            for (b, &v) in bg_grad.iter_mut().zip(v_img) {
                *b += trans * v;
            }

            // Back to front: S, the pixel's value behind the current Gaussian.
            let mut behind = dot(v_img, background);
            for bl in blended.iter().rev() {
                let k = bl.k as usize;
                let g = ids[k] as usize;
                let s = &packed[k];
                let Hit {
                    dx,
                    dy,
                    falloff,
                    alpha,
                    clamped,
                } = bl.hit;
                let z = splats.depths[g];
                let own = dot(v_img, splats.channels_of(g)) + v_depth * z + v_alpha;
                let w = alpha * bl.trans;
                let r = &mut rec[k * stride..(k + 1) * stride];
                for (rc, &v) in r[GEOMETRY..].iter_mut().zip(v_img) {
                    *rc += w * v;
                }
                r[DEPTH] += w * v_depth;
                let v_a = bl.trans * (own - behind);
                behind = alpha * own + (T::one() - alpha) * behind;
                if !clamped {
                    r[OPACITY] += v_a * falloff;
                    let v_sigma = -(v_a * alpha);
                    r[CONIC_A] += v_sigma * half * dx * dx;
                    r[CONIC_B] += v_sigma * dx * dy;
                    r[CONIC_C] += v_sigma * half * dy * dy;
                    r[MEAN_X] += v_sigma * (s.a * dx + s.b * dy);
                    r[MEAN_Y] += v_sigma * (s.b * dx + s.c * dy);
                }
            }
        }
    }
}

#[inline(always)]
fn dot<T: Real>(a: &[T], b: &[T]) -> T {
    let mut s = T::zero();
    for (&x, &y) in a.iter().zip(b) {
        s += x * y;
    }
    s
}
