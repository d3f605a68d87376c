//! The reference tile loops: one pixel and one Gaussian at a time, generic over
//! [`gaussian::Real`].
//!
//! Forward: each pixel walks its row segment's list ([`crate::rows`]) front to back with the rule of
//! [`crate::blend`]. Backward: each pixel re-runs that walk, keeping the blended Gaussians with
//! their transmittances, then sweeps them back to front (see [`crate::backward`] for the
//! maths), adding its contributions to the tile's gradient records. Pixels are visited in tile
//! raster order; a record's geometry terms (and few channels' terms) are summed per tile column
//! first, then column by column from the left, the order [`super::record`] sets.

use std::any::Any;

use gaussian::Real;
use rayon::prelude::*;

use super::record::{
    COLUMN_CHANNELS_MAX, CONIC_A, CONIC_B, CONIC_C, DEPTH, GEOMETRY, MEAN_X, MEAN_Y, OPACITY,
};
use super::{Tile, TileOut};
use crate::blend::{evaluate, pixel_centre, Hit, Splat, TILE_SIZE, TRANSMITTANCE_MIN};
use crate::rows::{at_column, RowEntry, RowLists, SPAN};
use crate::splats::{Cotangents, Splats};

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
pub(crate) struct Scratch<T> {
    packed: Vec<Splat<T>>,
    rows: RowLists,
    blended: Vec<Blended<T>>,
    /// Backward: per tile list entry and tile column, the sums a record takes by column
    /// ([`super::record`]); zero between tiles.
    columns: Vec<T>,
    /// Backward: per tile list entry, the tile columns (bits) whose sums it has.
    touched: Vec<u16>,
}

/// What a scalar forward pass keeps in its bins for the backward pass of the same Gaussians:
/// every Gaussian packed (a `Vec<Splat<T>>` of the pass's real type) and per tile its row lists.
#[derive(Debug)]
pub(crate) struct Kept {
    packed: Box<dyn Any + Send + Sync>,
    lists: Vec<RowLists>,
}

impl Kept {
    pub fn new<T: Real>(packed: Vec<Splat<T>>, lists: Vec<RowLists>) -> Self {
        Kept {
            packed: Box::new(packed),
            lists,
        }
    }

    /// The row lists, one per tile, if they were kept for `packed`: the same real type and,
    /// bit for bit, the same packed Gaussians, which are all that building them reads (with
    /// the tile rectangles, fixed by the bins).
    pub fn lists_for<T: Real>(&self, packed: &[Splat<T>]) -> Option<&[RowLists]> {
        let kept = self.packed.downcast_ref::<Vec<Splat<T>>>()?;
        let same = |a: T, b: T| a.to_f64_exact().to_bits() == b.to_f64_exact().to_bits();
        let matches = kept.len() == packed.len()
            && kept.par_iter().zip(packed).all(|(k, s)| {
                same(k.mx, s.mx)
                    && same(k.my, s.my)
                    && same(k.a, s.a)
                    && same(k.b, s.b)
                    && same(k.c, s.c)
                    && same(k.opacity, s.opacity)
                    && same(k.sigma_cut, s.sigma_cut)
            });
        matches.then_some(&self.lists[..])
    }

    /// The number of tiles whose row lists are kept.
    pub fn tile_count(&self) -> usize {
        self.lists.len()
    }
}

/// Gathers the tile's packed Gaussians (from `all`, one per Gaussian) and builds its row lists
/// unless `kept` has them (row lists kept for the same Gaussians, see [`Kept::lists_for`]);
/// returns its Gaussian ids and the row lists.
fn prepare<'b, T: Real>(
    all: &[Splat<T>],
    tile: Tile<'b>,
    kept: Option<&'b RowLists>,
    packed: &mut Vec<Splat<T>>,
    rows: &'b mut RowLists,
) -> (&'b [u32], &'b RowLists) {
    let ids = tile.ids;
    packed.clear();
    packed.extend(ids.iter().map(|&g| all[g as usize]));
    let rows = match kept {
        Some(kept) => kept,
        None => {
            rows.build(packed, tile.pixel_rect);
            rows
        }
    };
    (ids, rows)
}

impl<T> Scratch<T> {
    /// The row lists the last tile built.
    pub fn rows(&mut self) -> &mut RowLists {
        &mut self.rows
    }
}

/// Blends `tile` into `out` (`all`: every Gaussian packed, as [`Splats::packed`] gives).
pub(crate) fn forward_tile<T: Real>(
    splats: &Splats<T>,
    all: &[Splat<T>],
    tile: Tile<'_>,
    background: &[T],
    scratch: &mut Scratch<T>,
    out: TileOut<'_, T>,
) {
    let d = splats.channel_count;
    let Scratch { packed, rows, .. } = scratch;
    let (ids, rows) = prepare(all, tile, None, packed, rows);
    let (x0, y0, x1, y1) = tile.pixel_rect;
    for py in y0..y1 {
        let cy = pixel_centre::<T>(py);
        for px in x0..x1 {
            let cx = pixel_centre::<T>(px);
            let lx = (px - x0) as u8;
            let row = rows.list(py - y0, lx as usize / SPAN);
            let lp = ((py - y0) * TILE_SIZE + (px - x0)) as usize;
            let pixel = &mut out.image[lp * d..(lp + 1) * d];
            let mut z = T::zero();
            let mut n = 0u32;
            let trans = walk_pixel(row, packed, lx, cx, cy, |k, hit, trans| {
                let w = hit.alpha * trans;
                let g = ids[k] as usize;
                for (o, &c) in pixel.iter_mut().zip(splats.channels_of(g)) {
                    *o += w * c;
                }
                z += w * splats.depths[g];
                n += 1;
            });
            for (o, &b) in pixel.iter_mut().zip(background) {
                *o += trans * b;
            }
            out.alpha[lp] = T::one() - trans;
            out.depth[lp] = z;
            out.count[lp] = n;
        }
    }
}

/// One tile's blend weights ([`crate::weights`]): for each of its pixels in tile raster order,
/// the number of Gaussians it blends into `counts`, their ids and weights `alpha_i T_i`
/// (front to back) into `ids_out` and `weights`, and its final transmittance into `trans_out`.
pub(crate) fn weights_tile<T: Real>(
    all: &[Splat<T>],
    tile: Tile<'_>,
    scratch: &mut Scratch<T>,
    counts: &mut Vec<u32>,
    ids_out: &mut Vec<u32>,
    weights: &mut Vec<T>,
    trans_out: &mut Vec<T>,
) {
    let Scratch { packed, rows, .. } = scratch;
    let (ids, rows) = prepare(all, tile, None, packed, rows);
    let (x0, y0, x1, y1) = tile.pixel_rect;
    for py in y0..y1 {
        let cy = pixel_centre::<T>(py);
        for px in x0..x1 {
            let cx = pixel_centre::<T>(px);
            let lx = (px - x0) as u8;
            let row = rows.list(py - y0, lx as usize / SPAN);
            let mut n = 0u32;
            let trans = walk_pixel(row, packed, lx, cx, cy, |k, hit, trans| {
                ids_out.push(ids[k]);
                weights.push(hit.alpha * trans);
                n += 1;
            });
            counts.push(n);
            trans_out.push(trans);
        }
    }
}

/// Accumulates the tile's gradient records (`GEOMETRY + D` reals per tile intersection, in tile
/// order) into `rec` and its background gradient into `bg_grad`; `kept`: the tile's row lists
/// kept by the forward pass of these Gaussians, if any.
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward_tile<T: Real>(
    splats: &Splats<T>,
    all: &[Splat<T>],
    tile: Tile<'_>,
    kept: Option<&RowLists>,
    background: &[T],
    cot: &Cotangents<T>,
    scratch: &mut Scratch<T>,
    rec: &mut [T],
    bg_grad: &mut [T],
) {
    let d = splats.channel_count;
    let stride = GEOMETRY + d;
    let Scratch {
        packed,
        rows,
        blended,
        columns,
        touched,
    } = scratch;
    let (ids, rows) = prepare(all, tile, kept, packed, rows);
    let (x0, y0, x1, y1) = tile.pixel_rect;
    let width = tile.image_width as usize;
    let half = T::lit(0.5);
    // The reals of a record summed by column, and their sums per entry and column.
    let by_column = if d <= COLUMN_CHANNELS_MAX {
        stride
    } else {
        GEOMETRY
    };
    let tile = TILE_SIZE as usize;
    let needed = ids.len() * tile * by_column;
    if columns.len() < needed {
        columns.resize(needed, T::zero());
    }
    touched.clear();
    touched.resize(ids.len(), 0);
    for py in y0..y1 {
        let cy = pixel_centre::<T>(py);
        for px in x0..x1 {
            let cx = pixel_centre::<T>(px);
            let lx = (px - x0) as u8;
            let row = rows.list(py - y0, lx as usize / SPAN);
            let p = py as usize * width + px as usize;

            // Front to back: the forward pass's decisions, alphas and transmittances, over the
            // same row list.
            blended.clear();
            let trans = walk_pixel(row, packed, lx, cx, cy, |k, hit, trans| {
                blended.push(Blended {
                    k: k as u32,
                    hit,
                    trans,
                })
            });

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
                let r = &mut columns[(k * tile + lx as usize) * by_column..][..by_column];
                touched[k] |= 1 << lx;
                let channels = if by_column == stride {
                    &mut r[GEOMETRY..]
                } else {
                    &mut rec[k * stride + GEOMETRY..(k + 1) * stride]
                };
                for (rc, &v) in channels.iter_mut().zip(v_img) {
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
    // The column sums into the records (which start at zero), from the left; the sums are
    // left at zero for the next tile.
    for (k, &cols) in touched.iter().enumerate() {
        let r = &mut rec[k * stride..k * stride + by_column];
        for l in (0..tile).filter(|&l| cols >> l & 1 != 0) {
            let sums = &mut columns[(k * tile + l) * by_column..][..by_column];
            for (a, c) in r.iter_mut().zip(sums) {
                *a += *c;
                *c = T::zero();
            }
        }
    }
}

/// The front-to-back walk of one pixel (tile-local column `lx`, centre `(cx, cy)`) over its
/// row list with the rule of [`crate::blend`]: calls `blend(k, hit, trans)` for each Gaussian it
/// blends, in order, with the transmittance in front of it; returns the final transmittance.
#[inline(always)]
fn walk_pixel<T: Real>(
    row: &[RowEntry],
    packed: &[Splat<T>],
    lx: u8,
    cx: T,
    cy: T,
    mut blend: impl FnMut(usize, Hit<T>, T),
) -> T {
    let t_min = T::lit(TRANSMITTANCE_MIN);
    let mut trans = T::one();
    for k in at_column(row, lx) {
        let Some(hit) = evaluate(&packed[k], cx, cy) else {
            continue;
        };
        let next = trans * (T::one() - hit.alpha);
        if next <= t_min {
            break;
        }
        blend(k, hit, trans);
        trans = next;
    }
    trans
}

/// `sum_i a_i b_i`, accumulated in index order.
#[inline(always)]
pub(crate) fn dot<T: Real>(a: &[T], b: &[T]) -> T {
    let mut s = T::zero();
    for (&x, &y) in a.iter().zip(b) {
        s += x * y;
    }
    s
}
