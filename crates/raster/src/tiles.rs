//! Binning of projected Gaussians into 16x16 screen tiles, sorted front to back per tile.
//!
//! Convention (the oracle's `tile_mask`): a Gaussian with per-axis pixel radii `(rx, ry)`, both
//! positive, touches tiles `[floor((m - r) / 16), ceil((m + r) / 16))` per axis, clamped to the
//! tile grid. Each tile lists the Gaussians touching it in ascending view depth; ties keep
//! ascending Gaussian index (a stable sort, as `torch.sort(stable=True)` over all Gaussians).
//!
//! The depth order comes from a radix sort ([`depth_order`]), linear in the number of Gaussians.
//!
//! Memory: one `u32` per tile-Gaussian intersection plus one `usize` per tile, and transiently
//! per Gaussian its tile rectangle (16 bytes) and a key and index twice for the radix sort (16
//! bytes for `f32` depths, 32 for `f64`), and three `u32`/`usize` per tile.

use base::memory::filled;
use gaussian::Real;
use rayon::prelude::*;

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;

use crate::blend::TILE_SIZE;
use crate::error::{check_len, RasterError};
use crate::kernels::{lanes, scalar, Tile};

/// The per-tile, depth-sorted lists of Gaussian indices for one image.
///
/// After a forward pass ([`crate::rasterize`]) the bins also carry that pass's per-tile row
/// lists ([`crate::rows`]) or blended rows, when they fit [`ROW_LIST_BUDGET_BYTES`], so that
/// the backward pass does not build them again. Those depend on the Gaussians' means, conics
/// and opacities; the backward pass uses them only after checking that they were kept for the
/// Gaussians it is given, so its result never depends on what the bins carry. Equality compares
/// the binning only.
#[derive(Clone, Debug, Default)]
pub struct TileBins {
    width: u32,
    height: u32,
    gaussian_count: usize,
    tiles_x: u32,
    tiles_y: u32,
    /// `offsets[t]..offsets[t + 1]` is tile `t`'s range in `gaussian_ids` (tiles row-major).
    offsets: Vec<usize>,
    /// Gaussian indices, tile-major, front to back within a tile.
    gaussian_ids: Vec<u32>,
    /// What a scalar forward pass kept: its packed Gaussians and the row lists of every tile.
    row_lists: Option<Arc<scalar::Kept>>,
    /// What a lane forward pass kept: its packed Gaussians and the rows each tile blended.
    lanes_kept: Option<Arc<lanes::Kept>>,
}

/// Parts of the depth order binned in parallel (any number gives the same bins).
const BIN_PARTS: usize = 16;

/// At most this many bytes of row lists (scalar loops), or of blended rows (lane kernels, tile
/// by tile), are kept in the bins from the forward pass for the backward pass; beyond it the
/// backward pass builds them again (same values either way).
pub const ROW_LIST_BUDGET_BYTES: usize = 64 << 20;

impl PartialEq for TileBins {
    fn eq(&self, other: &Self) -> bool {
        (
            self.width,
            self.height,
            self.gaussian_count,
            self.tiles_x,
            self.tiles_y,
        ) == (
            other.width,
            other.height,
            other.gaussian_count,
            other.tiles_x,
            other.tiles_y,
        ) && self.offsets == other.offsets
            && self.gaussian_ids == other.gaussian_ids
    }
}

impl Eq for TileBins {}

/// A half-open rectangle of tiles `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileRect {
    /// First tile column (inclusive).
    pub x0: u32,
    /// End tile column (exclusive).
    pub x1: u32,
    /// First tile row (inclusive).
    pub y0: u32,
    /// End tile row (exclusive).
    pub y1: u32,
}

impl TileRect {
    /// Number of tiles in the rectangle.
    pub fn count(&self) -> usize {
        (self.x1 - self.x0) as usize * (self.y1 - self.y0) as usize
    }
}

/// Tiles per axis for an image: `ceil(width / 16)`, `ceil(height / 16)`.
pub fn tile_grid(width: u32, height: u32) -> (u32, u32) {
    (width.div_ceil(TILE_SIZE), height.div_ceil(TILE_SIZE))
}

/// `v` clamped to the tile range `[0, n]` (0 for NaN), with `inside` applied on `(0, n)`.
#[inline]
fn clamp_to_tiles(v: f64, n: u32, inside: impl Fn(f64) -> u32) -> u32 {
    if v.is_nan() || v <= 0.0 {
        0
    } else if v >= n as f64 {
        n
    } else {
        inside(v)
    }
}

/// `floor(v)` clamped to `[0, n]` (0 for NaN), without a call to `floor`: on `(0, n)` the floor
/// of a positive number is its truncation. (The baseline x86-64 target has no rounding
/// instruction, so `floor` is a library call.)
#[inline]
fn floor_clamped<T: Real>(v: T, n: u32) -> u32 {
    clamp_to_tiles(v.to_f64_exact(), n, |v| v as u32)
}

/// `ceil(v)` clamped to `[0, n]` (0 for NaN), without a call to `ceil`: on `(0, n)` the
/// truncation, plus one where that is below `v`.
#[inline]
fn ceil_clamped<T: Real>(v: T, n: u32) -> u32 {
    clamp_to_tiles(v.to_f64_exact(), n, |v| {
        let t = v as u32;
        t + u32::from((t as f64) < v)
    })
}

/// The tiles a Gaussian touches, or `None` when a radius is zero (culled) or the clamped range is
/// empty.
pub fn tile_rect<T: Real>(
    mean2d: [T; 2],
    radii: [u32; 2],
    tiles_x: u32,
    tiles_y: u32,
) -> Option<TileRect> {
    if radii[0] == 0 || radii[1] == 0 {
        return None;
    }
    let tile = T::lit(TILE_SIZE as f64);
    // Computed as the oracle does: m/16 -/+ r/16, then floor/ceil, then clamp to [0, tiles].
    let range = |m: T, r: u32, n: u32| -> (u32, u32) {
        let tm = m / tile;
        let tr = T::lit(r as f64) / tile;
        (floor_clamped(tm - tr, n), ceil_clamped(tm + tr, n))
    };
    let (x0, x1) = range(mean2d[0], radii[0], tiles_x);
    let (y0, y1) = range(mean2d[1], radii[1], tiles_y);
    if x0 < x1 && y0 < y1 {
        Some(TileRect { x0, x1, y0, y1 })
    } else {
        None
    }
}

/// [`tile_rect`] without branches, for loops over many Gaussians that the compiler vectorises:
/// the same rectangle, and an empty one (all zero) where [`tile_rect`] gives `None`.
#[inline(always)]
fn tile_rect_or_empty<T: Real>(
    mean2d: [T; 2],
    radii: [u32; 2],
    tiles_x: u32,
    tiles_y: u32,
) -> TileRect {
    let tile = T::lit(TILE_SIZE as f64);
    // `v` clamped to `[0, n]` (0 for NaN: the comparison is false), then `floor`/`ceil` as
    // `floor_clamped`/`ceil_clamped` take them: on `[0, n]` the floor is the truncation.
    let clamp = |v: T, n: u32| -> f64 {
        let (v, n) = (v.to_f64_exact(), f64::from(n));
        let v = if v > 0.0 { v } else { 0.0 };
        if v < n {
            v
        } else {
            n
        }
    };
    let range = |m: T, r: u32, n: u32| -> (u32, u32) {
        let tm = m / tile;
        let tr = T::lit(r as f64) / tile;
        let lo = clamp(tm - tr, n) as u32;
        let hi = clamp(tm + tr, n);
        let t = hi as u32;
        (lo, t + u32::from(f64::from(t) < hi))
    };
    let (x0, x1) = range(mean2d[0], radii[0], tiles_x);
    let (y0, y1) = range(mean2d[1], radii[1], tiles_y);
    let keep = radii[0] != 0 && radii[1] != 0 && x0 < x1 && y0 < y1;
    let pick = |v: u32| if keep { v } else { 0 };
    TileRect {
        x0: pick(x0),
        x1: pick(x1),
        y0: pick(y0),
        y1: pick(y1),
    }
}

/// Gaussians per parallel block of tile rectangles (any size gives the same bins).
const RECT_BLOCK: usize = 4096;

/// Gaussians per step of the `f32` rectangle lanes (one AVX-512 register of `f32`).
const RECT_LANES: usize = 16;

/// The largest tile grid side for which [`rect_lanes_f32`] computes in `f32`: every tile
/// coordinate up to it, and so every clamped bound and truncation, is exact in `f32`.
const F32_EXACT_TILES: u32 = 1 << 24;

/// The tile rectangles ([`tile_rect_or_empty`]) of a block of Gaussians, and the indices of
/// those that touch a tile (ascending, starting at `first`), as vector code for the
/// instruction set `pulp` picks at run time.
struct RectBlock<'a, T> {
    first: u32,
    means2d: &'a [[T; 2]],
    radii: &'a [[u32; 2]],
    out: &'a mut [TileRect],
    binned: &'a mut Vec<u32>,
    tiles: (u32, u32),
}

impl<T: Real> pulp::WithSimd for RectBlock<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let (tx, ty) = self.tiles;
        let means32 = T::as_f32_slice(self.means2d.as_flattened());
        match means32 {
            Some(m) if tx <= F32_EXACT_TILES && ty <= F32_EXACT_TILES => {
                rect_lanes_f32(m.as_chunks::<2>().0, self.radii, self.out, tx, ty)
            }
            _ => {
                for ((o, &m), &r) in self.out.iter_mut().zip(self.means2d).zip(self.radii) {
                    *o = tile_rect_or_empty(m, r, tx, ty);
                }
            }
        }
        // The binned ones, without a branch per Gaussian: every index is written, and the
        // length moves past it only where the rectangle is not empty.
        let binned = self.binned;
        binned.clear();
        binned.resize(self.out.len(), 0);
        let mut len = 0;
        for (g, r) in (self.first..).zip(self.out.iter()) {
            binned[len] = g;
            len += usize::from(r.x0 < r.x1);
        }
        binned.truncate(len);
    }
}

/// [`tile_rect_or_empty`] for `f32` means on a grid of at most [`F32_EXACT_TILES`] tiles a
/// side, [`RECT_LANES`] Gaussians at a time, each stage on lane arrays. The same rectangles:
/// the bounds are the same `f32` values (`r as f32` is the rounding of `r` that
/// `T::lit(r as f64)` makes), and the clamp to `[0, n]`, the truncation and the comparison that
/// `tile_rect_or_empty` makes in `f64` are exact in `f32` for `n <= 2^24`.
#[inline(always)]
fn rect_lanes_f32(
    means2d: &[[f32; 2]],
    radii: &[[u32; 2]],
    out: &mut [TileRect],
    tiles_x: u32,
    tiles_y: u32,
) {
    let (nx, ny) = (tiles_x as f32, tiles_y as f32);
    let range = |m: f32, r: u32, n: f32| -> (u32, u32) {
        let tm = m / TILE_SIZE as f32;
        let tr = r as f32 / TILE_SIZE as f32;
        let clamp = |v: f32| {
            let v = if v > 0.0 { v } else { 0.0 };
            if v < n {
                v
            } else {
                n
            }
        };
        let lo = clamp(tm - tr) as u32;
        let hi = clamp(tm + tr);
        let t = hi as u32;
        (lo, t + u32::from((t as f32) < hi))
    };
    let n = out.len().min(means2d.len()).min(radii.len());
    let body = n - n % RECT_LANES;
    for i0 in (0..body).step_by(RECT_LANES) {
        let m = &means2d[i0..i0 + RECT_LANES];
        let r = &radii[i0..i0 + RECT_LANES];
        let mut rect = [[0u32; RECT_LANES]; 4];
        for l in 0..RECT_LANES {
            let (x0, x1) = range(m[l][0], r[l][0], nx);
            let (y0, y1) = range(m[l][1], r[l][1], ny);
            let keep = r[l][0] != 0 && r[l][1] != 0 && x0 < x1 && y0 < y1;
            let pick = |v: u32| if keep { v } else { 0 };
            rect[0][l] = pick(x0);
            rect[1][l] = pick(x1);
            rect[2][l] = pick(y0);
            rect[3][l] = pick(y1);
        }
        for (l, o) in out[i0..i0 + RECT_LANES].iter_mut().enumerate() {
            *o = TileRect {
                x0: rect[0][l],
                x1: rect[1][l],
                y0: rect[2][l],
                y1: rect[3][l],
            };
        }
    }
    for i in body..n {
        out[i] = tile_rect_or_empty(means2d[i], radii[i], tiles_x, tiles_y);
    }
}

impl TileBins {
    /// Bins `means2d`/`radii` for a `width x height` image, ordering each tile by `depths`.
    pub fn new<T: Real>(
        width: u32,
        height: u32,
        means2d: &[[T; 2]],
        depths: &[T],
        radii: &[[u32; 2]],
    ) -> Result<TileBins, RasterError> {
        let n = means2d.len();
        check_len("depths", depths.len(), n)?;
        check_len("radii", radii.len(), n)?;
        if width == 0 || height == 0 {
            return Err(RasterError::EmptyImage { width, height });
        }
        if n >= u32::MAX as usize {
            return Err(RasterError::TooManyGaussians(n));
        }
        let (tiles_x, tiles_y) = tile_grid(width, height);
        let tile_count = tiles_x as usize * tiles_y as usize;

        // Every Gaussian's rectangle, empty where it touches no tile.
        let empty = TileRect {
            x0: 0,
            x1: 0,
            y0: 0,
            y1: 0,
        };
        let mut rects = filled(n, empty);
        // Stable depth order of the Gaussians that touch any tile (ties: ascending index).
        // Each block lists its binned Gaussians as it computes their rectangles, and the lists
        // are joined in block order (rayon's `filter().collect()` joins per-split lists
        // through a linked list, a few times slower here).
        let mut binned: Vec<Vec<u32>> = (0..n.div_ceil(RECT_BLOCK)).map(|_| Vec::new()).collect();
        rects
            .par_chunks_mut(RECT_BLOCK)
            .zip(means2d.par_chunks(RECT_BLOCK))
            .zip(radii.par_chunks(RECT_BLOCK))
            .zip(binned.par_iter_mut())
            .enumerate()
            .for_each(|(b, (((out, means2d), radii), binned))| {
                base::isa::dispatch(RectBlock {
                    first: (b * RECT_BLOCK) as u32,
                    means2d,
                    radii,
                    out,
                    binned,
                    tiles: (tiles_x, tiles_y),
                })
            });
        let order = binned.concat();
        let order = depth_order(order, depths);

        // The rectangles in depth order, then the intersections in parts of that order: each
        // part counts its intersections per tile, the counts give every part its own slots in
        // each tile (parts in order), and the parts fill their slots in parallel. The result
        // is the same for any number of parts.
        let sorted: Vec<TileRect> = order.par_iter().map(|&g| rects[g as usize]).collect();
        drop(rects);
        let part_len = sorted.len().div_ceil(BIN_PARTS).max(1);
        let mut cursors: Vec<Vec<usize>> = sorted
            .par_chunks(part_len)
            .map(|part| tile_counts(part, tiles_x, tiles_y))
            .collect();
        // Tile offsets, and each part's first slot per tile.
        let mut offsets = Vec::with_capacity(tile_count + 1);
        let mut total = 0usize;
        for t in 0..tile_count {
            offsets.push(total);
            for part in cursors.iter_mut() {
                let count = part[t];
                part[t] = total;
                total += count;
            }
        }
        offsets.push(total);
        let slots: Vec<AtomicU32> = (0..total)
            .into_par_iter()
            .map(|_| AtomicU32::new(0))
            .collect();
        let tx = tiles_x as usize;
        sorted
            .par_chunks(part_len)
            .zip(order.par_chunks(part_len))
            .zip(cursors.par_iter_mut())
            .for_each(|((part, ids), cursor)| {
                for (r, &g) in part.iter().zip(ids) {
                    for ty in r.y0 as usize..r.y1 as usize {
                        for t in ty * tx + r.x0 as usize..ty * tx + r.x1 as usize {
                            // Every slot is written by exactly one part, once.
                            slots[cursor[t]].store(g, Ordering::Relaxed);
                            cursor[t] += 1;
                        }
                    }
                }
            });
        let gaussian_ids: Vec<u32> = slots.into_par_iter().map(AtomicU32::into_inner).collect();
        Ok(TileBins {
            width,
            height,
            gaussian_count: n,
            tiles_x,
            tiles_y,
            offsets,
            gaussian_ids,
            row_lists: None,
            lanes_kept: None,
        })
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Number of Gaussians the bins were built for (binned or not).
    pub fn gaussian_count(&self) -> usize {
        self.gaussian_count
    }

    /// Tiles per axis.
    pub fn grid(&self) -> (u32, u32) {
        (self.tiles_x, self.tiles_y)
    }

    /// A processing order of the tiles that keeps neighbours close: the Morton (Z-order) code
    /// of tile `t`'s grid position. Tiles processed in this order share more of their
    /// Gaussians with the tiles processed just before.
    pub fn locality_key(&self, t: usize) -> u64 {
        let (x, y) = (
            t as u64 % self.tiles_x as u64,
            t as u64 / self.tiles_x as u64,
        );
        let spread = |mut v: u64| {
            v &= 0xffff_ffff;
            v = (v | v << 16) & 0x0000_ffff_0000_ffff;
            v = (v | v << 8) & 0x00ff_00ff_00ff_00ff;
            v = (v | v << 4) & 0x0f0f_0f0f_0f0f_0f0f;
            v = (v | v << 2) & 0x3333_3333_3333_3333;
            (v | v << 1) & 0x5555_5555_5555_5555
        };
        spread(x) | spread(y) << 1
    }

    /// The order in which the passes hand tiles to their threads, one tile at a time: the
    /// longest lists first (ties in [`TileBins::locality_key`] order). A thread that finishes
    /// then waits at most for a short tile, where with neighbours in runs it could wait for
    /// a run of the scene's busiest tiles. The order changes no result.
    pub fn schedule_key(&self, t: usize) -> (std::cmp::Reverse<usize>, u64) {
        (std::cmp::Reverse(self.range(t).len()), self.locality_key(t))
    }

    /// Number of tiles.
    pub fn tile_count(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Total number of tile-Gaussian intersections.
    pub fn intersection_count(&self) -> usize {
        self.gaussian_ids.len()
    }

    /// The range of tile `t` in the intersection list.
    pub fn range(&self, t: usize) -> std::ops::Range<usize> {
        self.offsets[t]..self.offsets[t + 1]
    }

    /// The Gaussians of tile `t`, front to back.
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.gaussian_ids[self.range(t)]
    }

    /// All intersections, tile-major (tiles row-major), front to back within a tile.
    pub fn gaussian_ids(&self) -> &[u32] {
        &self.gaussian_ids
    }

    /// The pixel rectangle `(x0, y0, x1, y1)` of tile `t`, clipped to the image.
    pub fn pixel_rect(&self, t: usize) -> (u32, u32, u32, u32) {
        let tx = t as u32 % self.tiles_x;
        let ty = t as u32 / self.tiles_x;
        let x0 = tx * TILE_SIZE;
        let y0 = ty * TILE_SIZE;
        (
            x0,
            y0,
            (x0 + TILE_SIZE).min(self.width),
            (y0 + TILE_SIZE).min(self.height),
        )
    }

    /// Tile `t` as the tile loops read it: its Gaussians, its pixels and the image width.
    pub(crate) fn tile_view(&self, t: usize) -> Tile<'_> {
        Tile {
            ids: self.tile(t),
            pixel_rect: self.pixel_rect(t),
            image_width: self.width,
        }
    }

    /// Bytes held by the binning itself (not counting what a forward pass kept for the
    /// backward pass: row lists or blended rows, at most [`ROW_LIST_BUDGET_BYTES`], and the
    /// packed Gaussians they were made for, 40 bytes each for the lane kernels, 28 (`f32`) or
    /// 56 (`f64`) for the scalar loops).
    pub fn memory_bytes(&self) -> usize {
        self.offsets.len() * std::mem::size_of::<usize>()
            + self.gaussian_ids.len() * std::mem::size_of::<u32>()
    }

    /// What the scalar forward pass kept, if it ran last on these bins.
    pub(crate) fn kept_rows(&self) -> Option<&scalar::Kept> {
        self.row_lists.as_deref()
    }

    /// Keeps what a scalar forward pass kept (its packed Gaussians and the row lists of every
    /// tile), or drops it when `None`.
    pub(crate) fn keep_rows(&mut self, kept: Option<scalar::Kept>) {
        self.row_lists = kept
            .filter(|k| k.tile_count() == self.tile_count())
            .map(Arc::new);
    }

    /// What the lane forward pass kept, if it ran last on these bins.
    pub(crate) fn kept_lanes(&self) -> Option<&lanes::Kept> {
        self.lanes_kept.as_deref()
    }

    /// Keeps what a lane forward pass kept (its packed Gaussians and, per tile, the rows it
    /// blended), or drops it when `None`.
    pub(crate) fn keep_lanes(&mut self, kept: Option<lanes::Kept>) {
        self.lanes_kept = kept
            .filter(|k| {
                k.packed.len() == self.gaussian_count && k.blends.len() == self.tile_count()
            })
            .map(Arc::new);
    }

    /// `Ok` when the bins were built for `count` Gaussians.
    pub(crate) fn check(&self, count: usize) -> Result<(), RasterError> {
        if self.gaussian_count == count {
            Ok(())
        } else {
            Err(RasterError::BinsMismatch {
                bins_count: self.gaussian_count,
                count,
            })
        }
    }
}

/// The number of rectangles of `rects` that cover each tile of a `tiles_x x tiles_y` grid
/// (tiles row-major): four corner increments per rectangle, then the two-dimensional prefix
/// sum (differences wrap, the sums are the exact counts).
fn tile_counts(rects: &[TileRect], tiles_x: u32, tiles_y: u32) -> Vec<usize> {
    let (tx, ty) = (tiles_x as usize, tiles_y as usize);
    // Corners on the `(tx + 1) x (ty + 1)` grid.
    let gx = tx + 1;
    let mut corners = vec![0usize; gx * (ty + 1)];
    for r in rects {
        let (x0, x1, y0, y1) = (r.x0 as usize, r.x1 as usize, r.y0 as usize, r.y1 as usize);
        corners[y0 * gx + x0] = corners[y0 * gx + x0].wrapping_add(1);
        corners[y0 * gx + x1] = corners[y0 * gx + x1].wrapping_sub(1);
        corners[y1 * gx + x0] = corners[y1 * gx + x0].wrapping_sub(1);
        corners[y1 * gx + x1] = corners[y1 * gx + x1].wrapping_add(1);
    }
    let mut counts = vec![0usize; tx * ty];
    let mut column = vec![0usize; tx];
    for y in 0..ty {
        let mut run = 0usize;
        for x in 0..tx {
            run = run.wrapping_add(corners[y * gx + x]);
            column[x] = column[x].wrapping_add(run);
            counts[y * tx + x] = column[x];
        }
    }
    counts
}

/// `ids` sorted stably by ascending depth: numeric order (so `-0.0 == 0.0` and equal depths
/// keep their order in `ids`), NaN after every number.
///
/// A least-significant-digit radix sort of order-preserving keys (the depth's bits mapped so
/// that unsigned order is numeric order), one stable counting pass per byte; a byte that all
/// keys share is skipped. Linear in the number of Gaussians. `f32` depths take 32-bit keys (the
/// conversion to `f64` is exact and monotonic, so the order is the same) and run each pass in
/// parallel over 16 parts of the array; `f64` depths take 64-bit keys, one part.
pub fn depth_order<T: Real>(ids: Vec<u32>, depths: &[T]) -> Vec<u32> {
    match T::as_f32_slice(depths) {
        Some(depths) => depth_order_f32(&ids, depths),
        None => depth_order_f64(ids, depths),
    }
}

/// Parts of each parallel radix pass of [`depth_order`]: the parts count their digits, then
/// each scatters its items to its own slots (digits in order, parts in order within a digit),
/// so a pass is the stable counting pass whatever the number of parts or threads.
const SORT_PARTS: usize = 16;

/// [`depth_order`] for `f32` depths. An item is the key in the high 32 bits and the index in
/// the low ones; the slots of a pass are atomics only so that the parts can write disjoint
/// slots of one array without `unsafe` (relaxed stores, plain stores on the common targets).
fn depth_order_f32(ids: &[u32], depths: &[f32]) -> Vec<u32> {
    let key = |g: u32| -> u64 {
        let d = depths[g as usize];
        if d.is_nan() {
            return u64::from(u32::MAX);
        }
        // -0.0 sorts with 0.0.
        let bits = if d == 0.0 { 0 } else { d.to_bits() };
        u64::from(if bits >> 31 == 1 {
            !bits
        } else {
            bits | 1 << 31
        })
    };
    let n = ids.len();
    if n == 0 {
        return Vec::new();
    }
    let mut src: Vec<AtomicU64> = ids
        .par_iter()
        .map(|&g| AtomicU64::new(key(g) << 32 | u64::from(g)))
        .collect();
    let mut dst: Vec<AtomicU64> = (0..n).into_par_iter().map(|_| AtomicU64::new(0)).collect();
    let part_len = n.div_ceil(SORT_PARTS);
    for byte in 0..4 {
        let digit = |item: u64| (item >> (32 + 8 * byte)) as usize & 0xff;
        let mut starts: Vec<[usize; 256]> = src
            .par_chunks(part_len)
            .map(|part| {
                let mut counts = [0usize; 256];
                for item in part {
                    counts[digit(item.load(Ordering::Relaxed))] += 1;
                }
                counts
            })
            .collect();
        let mut next = 0;
        let mut shared = false;
        for b in 0..256 {
            let first = next;
            for counts in starts.iter_mut() {
                let count = counts[b];
                counts[b] = next;
                next += count;
            }
            shared |= next - first == n;
        }
        if shared {
            continue;
        }
        src.par_chunks(part_len)
            .zip(starts.par_iter_mut())
            .for_each(|(part, start)| {
                for item in part {
                    let item = item.load(Ordering::Relaxed);
                    let b = digit(item);
                    // Every slot is written by exactly one part, once per pass.
                    dst[start[b]].store(item, Ordering::Relaxed);
                    start[b] += 1;
                }
            });
        std::mem::swap(&mut src, &mut dst);
    }
    src.into_par_iter()
        .map(|item| item.into_inner() as u32)
        .collect()
}

/// [`depth_order`] for any depths, through their exact `f64` values.
fn depth_order_f64<T: Real>(ids: Vec<u32>, depths: &[T]) -> Vec<u32> {
    let key = |g: u32| -> u64 {
        let d = depths[g as usize].to_f64_exact();
        if d.is_nan() {
            return u64::MAX;
        }
        // -0.0 sorts with 0.0.
        let bits = if d == 0.0 { 0 } else { d.to_bits() };
        if bits >> 63 == 1 {
            !bits
        } else {
            bits | 1 << 63
        }
    };
    let mut items: Vec<(u64, u32)> = ids.into_iter().map(|g| (key(g), g)).collect();
    let mut counts = vec![[0usize; 256]; 8];
    for &(k, _) in &items {
        for (byte, c) in counts.iter_mut().enumerate() {
            c[(k >> (8 * byte)) as usize & 0xff] += 1;
        }
    }
    let mut spare = vec![(0u64, 0u32); items.len()];
    for (byte, c) in counts.iter().enumerate() {
        if c.contains(&items.len()) {
            continue;
        }
        let mut start = [0usize; 256];
        let mut total = 0;
        for (s, &x) in start.iter_mut().zip(c) {
            *s = total;
            total += x;
        }
        for &item in &items {
            let b = (item.0 >> (8 * byte)) as usize & 0xff;
            spare[start[b]] = item;
            start[b] += 1;
        }
        std::mem::swap(&mut items, &mut spare);
    }
    items.into_iter().map(|(_, g)| g).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Ascending order on reals for a comparison sort: numeric order, NaN after every number.
    fn numeric(a: f64, b: f64) -> std::cmp::Ordering {
        match a.partial_cmp(&b) {
            Some(o) => o,
            None => a.is_nan().cmp(&b.is_nan()),
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(100))]

        // Every tile lists exactly the Gaussians whose tile rectangle covers it, in the stable
        // depth order, for any image size and enough Gaussians that several parts bin them.
        #[test]
        fn each_tile_lists_the_gaussians_covering_it_front_to_back(
            width in 1u32..90, height in 1u32..90,
            gaussians in prop::collection::vec(
                (-20.0f32..110.0, -20.0f32..110.0, 0u32..40, 0u32..40, 0u32..6),
                0..600,
            ),
        ) {
            let means: Vec<[f32; 2]> = gaussians.iter().map(|g| [g.0, g.1]).collect();
            let radii: Vec<[u32; 2]> = gaussians.iter().map(|g| [g.2, g.3]).collect();
            // Few distinct depths: many ties.
            let depths: Vec<f32> = gaussians.iter().map(|g| g.4 as f32).collect();
            let bins = TileBins::new(width, height, &means, &depths, &radii).unwrap();
            let (tx, ty) = tile_grid(width, height);
            for t in 0..bins.tile_count() {
                let (x, y) = (t as u32 % tx, t as u32 / tx);
                let mut expected: Vec<u32> = (0..means.len() as u32)
                    .filter(|&g| {
                        tile_rect(means[g as usize], radii[g as usize], tx, ty)
                            .is_some_and(|r| r.x0 <= x && x < r.x1 && r.y0 <= y && y < r.y1)
                    })
                    .collect();
                expected.sort_by(|&a, &b| depths[a as usize].total_cmp(&depths[b as usize]));
                prop_assert_eq!(bins.tile(t), &expected[..], "tile {}", t);
            }
            // The schedule is a total order of the tiles (one key each), longest lists first.
            let mut order: Vec<usize> = (0..bins.tile_count()).collect();
            order.sort_by_key(|&t| bins.schedule_key(t));
            for pair in order.windows(2) {
                prop_assert!(bins.schedule_key(pair[0]) < bins.schedule_key(pair[1]));
                prop_assert!(bins.tile(pair[0]).len() >= bins.tile(pair[1]).len());
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        // The branch-free rectangle is `tile_rect`'s, or empty where that is `None`, in f32 and
        // f64: means anywhere (non-finite ones included), zero and huge radii, any grid.
        #[test]
        fn the_branch_free_rectangle_is_tile_rect(
            pick in 0usize..6, raw in -1e4f64..1e4, whole in -3i64..300,
            frac in prop::sample::select(vec![0.0, 1e-7, 0.5, 0.999_99, -1e-7]),
            my in -400.0f64..400.0,
            rx in prop::sample::select(vec![0u32, 1, 7, 16, 17, 100, 4_000_000_000]),
            ry in 0u32..70, tx in 0u32..40, ty in 0u32..40,
        ) {
            let mx = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, raw, (whole * 16) as f64 + frac,
                whole as f64 + frac][pick];
            let empty = TileRect { x0: 0, x1: 0, y0: 0, y1: 0 };
            let r64 = tile_rect([mx, my], [rx, ry], tx, ty).unwrap_or(empty);
            prop_assert_eq!(tile_rect_or_empty([mx, my], [rx, ry], tx, ty), r64);
            let m32 = [mx as f32, my as f32];
            let r32 = tile_rect(m32, [rx, ry], tx, ty).unwrap_or(empty);
            prop_assert_eq!(tile_rect_or_empty(m32, [rx, ry], tx, ty), r32);
        }
    }

    /// One [`RectBlock`] (the lanes in `f32` on grids they take, the generic loop otherwise).
    fn rect_block<T: Real>(
        first: u32,
        means2d: &[[T; 2]],
        radii: &[[u32; 2]],
        tiles: (u32, u32),
    ) -> (Vec<TileRect>, Vec<u32>) {
        let mut out = vec![
            TileRect {
                x0: 9,
                x1: 9,
                y0: 9,
                y1: 9
            };
            means2d.len()
        ];
        let mut binned = vec![7; 3];
        base::isa::dispatch(RectBlock {
            first,
            means2d,
            radii,
            out: &mut out,
            binned: &mut binned,
            tiles,
        });
        (out, binned)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]

        // A block's rectangles are `tile_rect`'s (empty where that is `None`) and it lists the
        // Gaussians with one, for f32 means on grids the f32 lanes take and on larger ones
        // (the generic loop), lane blocks and a tail, means anywhere (non-finite ones too).
        #[test]
        fn a_rectangle_block_gives_tile_rect_and_lists_the_binned(
            gaussians in prop::collection::vec(
                (0usize..6, -1e4f64..1e4, -3i64..300,
                 prop::sample::select(vec![0.0, 1e-7, 0.5, 0.999_99, -1e-7]), -400.0f64..400.0,
                 prop::sample::select(vec![0u32, 1, 7, 16, 17, 100, 4_000_000_000]), 0u32..70),
                0..80),
            tx in prop::sample::select(vec![0u32, 1, 13, 40, F32_EXACT_TILES, F32_EXACT_TILES + 1]),
            ty in prop::sample::select(vec![0u32, 1, 13, 40, F32_EXACT_TILES, u32::MAX]),
            first in 0u32..1000,
        ) {
            let means: Vec<[f32; 2]> = gaussians
                .iter()
                .map(|&(pick, raw, whole, frac, my, _, _)| {
                    let mx = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, raw,
                        (whole * 16) as f64 + frac, whole as f64 + frac][pick];
                    [mx as f32, my as f32]
                })
                .collect();
            let radii: Vec<[u32; 2]> = gaussians.iter().map(|g| [g.5, g.6]).collect();
            let empty = TileRect { x0: 0, x1: 0, y0: 0, y1: 0 };
            let expected: Vec<TileRect> = means
                .iter()
                .zip(&radii)
                .map(|(&m, &r)| tile_rect(m, r, tx, ty).unwrap_or(empty))
                .collect();
            let expected_binned: Vec<u32> = (first..)
                .zip(&expected)
                .filter(|(_, r)| r.count() > 0)
                .map(|(g, _)| g)
                .collect();
            let (rects, binned) = rect_block(first, &means, &radii, (tx, ty));
            prop_assert_eq!(rects, expected);
            prop_assert_eq!(binned, expected_binned);
        }
    }

    /// With more Gaussians than one rectangle block ([`RECT_BLOCK`]) and culled ones in every
    /// block, each tile still lists exactly the Gaussians covering it, in the stable depth
    /// order (a reference built one tile at a time).
    #[test]
    fn gaussians_listed_in_several_blocks_bin_as_one_list() {
        let n = 3 * RECT_BLOCK + 123;
        // A fixed pseudo-random scene: a linear congruential sequence, no fixture.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 33) as u32
        };
        let (width, height) = (70, 50);
        let means: Vec<[f32; 2]> = (0..n)
            .map(|_| {
                [
                    (next() % 900) as f32 / 10.0 - 10.0,
                    (next() % 700) as f32 / 10.0 - 10.0,
                ]
            })
            .collect();
        // About one in five culled (a zero radius).
        let radii: Vec<[u32; 2]> = (0..n).map(|_| [next() % 5 * 4, next() % 24]).collect();
        let depths: Vec<f32> = (0..n).map(|_| (next() % 50) as f32).collect();
        let bins = TileBins::new(width, height, &means, &depths, &radii).unwrap();
        let (tx, ty) = tile_grid(width, height);
        let mut listed = 0;
        for t in 0..bins.tile_count() {
            let (x, y) = (t as u32 % tx, t as u32 / tx);
            let mut expected: Vec<u32> = (0..n as u32)
                .filter(|&g| {
                    tile_rect(means[g as usize], radii[g as usize], tx, ty)
                        .is_some_and(|r| r.x0 <= x && x < r.x1 && r.y0 <= y && y < r.y1)
                })
                .collect();
            expected.sort_by(|&a, &b| depths[a as usize].total_cmp(&depths[b as usize]));
            assert_eq!(bins.tile(t), &expected[..], "tile {t}");
            listed += expected.len();
        }
        assert_eq!(bins.intersection_count(), listed);
        assert!(
            listed > n,
            "the scene should cover several tiles per Gaussian"
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]

        // The clamped floor and ceiling without library calls are the library's, clamped as
        // the oracle clamps them, in f32 and f64, near integers and tile-grid ends included.
        #[test]
        fn the_clamped_floor_and_ceiling_are_the_library_ones(
            whole in -3i64..70, frac in prop::sample::select(vec![
                0.0, 1e-9, 0.25, 0.5, 0.999_999, -1e-9, -0.5,
            ]), raw in -1e3f64..1e3, pick in 0usize..5, n in 0u32..66,
        ) {
            let v = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, raw, whole as f64 + frac][pick];
            let clamp = |v: f64| -> u32 {
                if v.is_nan() || v <= 0.0 { 0 } else if v >= n as f64 { n } else { v as u32 }
            };
            prop_assert_eq!(floor_clamped(v, n), clamp(v.floor()));
            prop_assert_eq!(ceil_clamped(v, n), clamp(v.ceil()));
            let v32 = v as f32;
            prop_assert_eq!(floor_clamped(v32, n), clamp(v32.floor() as f64));
            prop_assert_eq!(ceil_clamped(v32, n), clamp(v32.ceil() as f64));
        }

        // Any depths, with many ties, signed zeros, infinities and NaNs: the same order as a
        // stable comparison sort, in f32 and f64.
        #[test]
        fn the_radix_depth_order_is_the_stable_numeric_order(
            picks in prop::collection::vec((0usize..14, -1e6f64..1e6), 0..400),
        ) {
            // 1e-40 and -1e-40 are subnormal in f32.
            let specials = [
                0.0, -0.0, 1.0, 1.0, -1.0, f64::INFINITY, f64::NEG_INFINITY, f64::NAN,
                f64::MIN_POSITIVE, -1e-300, 1e-40, -1e-40,
            ];
            let depths: Vec<f64> = picks
                .iter()
                .map(|&(i, v)| if i < specials.len() { specials[i] } else { v })
                .collect();
            let ids: Vec<u32> = (0..depths.len() as u32).rev().collect();
            let mut expected = ids.clone();
            expected.sort_by(|&i, &j| numeric(depths[i as usize], depths[j as usize]));
            prop_assert_eq!(depth_order(ids.clone(), &depths), expected.clone());
            let d32: Vec<f32> = depths.iter().map(|&d| d as f32).collect();
            let mut expected32 = ids.clone();
            expected32.sort_by(|&i, &j| {
                numeric(d32[i as usize] as f64, d32[j as usize] as f64)
            });
            prop_assert_eq!(depth_order(ids, &d32), expected32);
        }
    }
}
