//! The forward pass: alpha-blends any number of channels per pixel, tile by tile in parallel.
//!
//! Each 16x16 tile blends its depth-sorted Gaussians front to back with the rule of
//! [`crate::blend`]: `out = sum_i w_i c_i + T_final background`, `w_i = alpha_i T_i`,
//! `T_i = prod_{j<i} (1 - alpha_j)`, alpha image `1 - T_final`, depth image `sum_i w_i z_i`.
//!
//! Determinism: every pixel is computed by one thread in a fixed order, so the result does not
//! depend on the number of threads.
//!
//! The scalar loops walk each pixel over its row's list of [`crate::rows`] (the Gaussians that
//! can reach the row, with the columns they can reach); the lane kernels evaluate each Gaussian
//! on the tile rows its ellipse reaches. Either way the Gaussians left out are ones the blending
//! rule skips there. Tiles go to the threads one at a time, longest lists first
//! ([`TileBins::schedule_key`]), which changes no result.
//!
//! Memory: the outputs (`D + 3` reals and one `u32` per pixel), a tile-major staging copy of
//! them of the same size, the [`TileBins`], every Gaussian packed (7 to 10 reals each), and per
//! thread one tile's working memory: for the scalar loops its packed Gaussians (7 reals each)
//! and row lists (8 bytes per Gaussian and row segment it reaches), for the lane kernels `D`
//! reals per pixel. The scalar loops' row lists of all tiles are kept in the returned bins for
//! the backward pass when they fit [`crate::tiles::ROW_LIST_BUDGET_BYTES`] (64 MiB); otherwise
//! none are kept and the backward pass builds them again.

use base::memory::filled;
use gaussian::Real;
use rayon::prelude::*;

use crate::blend::{TILE_PIXELS, TILE_SIZE};
use crate::error::{check_len, RasterError};
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::kernels::{lanes, scalar, Kernel, TileOut, Token};
use crate::rows::RowLists;
pub use crate::splats::Splats;
use crate::tiles::{TileBins, ROW_LIST_BUDGET_BYTES};

/// The rasterizer's forward outputs. Images are row-major, `width x height`; the channel image
/// has `channel_count` values per pixel (channel last).
#[derive(Clone, Debug)]
pub struct Rasterized<T> {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Channels per pixel in `image` (`D`, the [`Splats::channel_count`]).
    pub channel_count: usize,
    /// `sum_i w_i c_i + T_final background`, `height * width * channel_count` values.
    pub image: Vec<T>,
    /// Accumulated opacity `1 - T_final`.
    pub alpha: Vec<T>,
    /// Blend-weighted view depth `sum_i w_i z_i` (not normalised).
    pub depth: Vec<T>,
    /// `depth / alpha`, or 0 where `alpha` is 0: the expected depth of the visible surface.
    pub normalized_depth: Vec<T>,
    /// Number of Gaussians blended into each pixel.
    pub blended: Vec<u32>,
    /// The tile binning, reused by the backward pass.
    pub bins: TileBins,
}

impl<T: Real> Rasterized<T> {
    /// The channel values of pixel `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> &[T] {
        let p = (y as usize * self.width as usize + x as usize) * self.channel_count;
        &self.image[p..p + self.channel_count]
    }

    /// Total number of blended Gaussian-pixel pairs.
    pub fn blended_pairs(&self) -> u64 {
        self.blended.iter().map(|&c| c as u64).sum()
    }
}

/// Rasterizes `splats` into a `width x height` image over `background` (`channel_count` values).
pub fn rasterize<T: Real>(
    splats: &Splats<T>,
    width: u32,
    height: u32,
    background: &[T],
) -> Result<Rasterized<T>, RasterError> {
    splats.validate()?;
    let bins = TileBins::new(width, height, splats.means2d, splats.depths, splats.radii)?;
    rasterize_binned(splats, bins, background)
}

/// [`rasterize`] with tile bins built beforehand for the same Gaussians and image size.
pub fn rasterize_binned<T: Real>(
    splats: &Splats<T>,
    bins: TileBins,
    background: &[T],
) -> Result<Rasterized<T>, RasterError> {
    rasterize_binned_with(splats, bins, background, Kernel::auto()?)
}

/// [`rasterize_binned`] with the given tile kernel (the result is the same bits with every
/// kernel; see [`crate::kernels`]).
pub fn rasterize_binned_with<T: Real>(
    splats: &Splats<T>,
    bins: TileBins,
    background: &[T],
    kernel: Kernel,
) -> Result<Rasterized<T>, RasterError> {
    splats.validate()?;
    let (width, height) = (bins.width(), bins.height());
    bins.check(splats.len())?;
    // Row lists and blended rows kept from another pass may belong to other Gaussians: build
    // them anew.
    let mut bins = bins;
    bins.keep_rows(None);
    bins.keep_lanes(None);
    let d = splats.channel_count;
    check_len("background", background.len(), d)?;

    let tiles = bins.tile_count();
    // The lane kernels run in f32 only.
    let token = Token::for_kernel(kernel);
    let lanes_in = token.and(splats.as_f32().zip(T::as_f32_slice(background)));
    let packed32 = lanes_in
        .as_ref()
        .map(|(s, _)| lanes::pack(s, height))
        .unwrap_or_default();
    let packed = if lanes_in.is_some() {
        Vec::new()
    } else {
        splats.packed()
    };
    // Staging rows hold at least one channel so that chunking works when `d == 0`.
    let d_stage = d.max(1);
    let mut t_image = filled(tiles * TILE_PIXELS * d_stage, T::zero());
    let mut t_alpha = filled(tiles * TILE_PIXELS, T::zero());
    let mut t_depth = filled(tiles * TILE_PIXELS, T::zero());
    let mut t_count = filled(tiles * TILE_PIXELS, 0u32);
    // The row lists each tile builds, kept for the backward pass while they fit the budget.
    let mut kept: Vec<RowLists> = (0..tiles).map(|_| RowLists::default()).collect();
    // The rows each tile's lane kernel blends, kept for the backward pass while they fit the
    // same budget (tile by tile: a tile without them is walked again).
    let mut kept_blends: Vec<Option<lanes::KeptRows>> = (0..tiles).map(|_| None).collect();
    let kept_bytes = AtomicUsize::new(0);
    // Tiles handed out one at a time, longest lists first (each tile's results do not depend
    // on the order or the thread).
    let mut work: Vec<_> = t_image
        .par_chunks_mut(TILE_PIXELS * d_stage)
        .zip(t_alpha.par_chunks_mut(TILE_PIXELS))
        .zip(t_depth.par_chunks_mut(TILE_PIXELS))
        .zip(t_count.par_chunks_mut(TILE_PIXELS))
        .zip(kept.par_iter_mut().zip(kept_blends.par_iter_mut()))
        .enumerate()
        .collect();
    work.sort_unstable_by_key(|&(t, _)| bins.schedule_key(t));
    work.into_iter().par_bridge().for_each_init(
        <(scalar::Scratch<T>, lanes::Scratch, lanes::KeptRows)>::default,
        |(scalar_scratch, lane_scratch, rows),
         (t, ((((image, alpha), depth), count), (keep, keep_blends)))| {
            let mut out = TileOut {
                image,
                alpha,
                depth,
                count,
            };
            match (token, &lanes_in, out.as_f32()) {
                (Some(token), Some((splats, background)), Some(out)) => {
                    // The lane kernels build no row lists; they keep the rows they blend, in a
                    // buffer of the thread's (grown once, not per tile), copied out to fit.
                    rows.clear();
                    token.run(lanes::ForwardTile {
                        splats,
                        packed: &packed32,
                        tile: bins.tile_view(t),
                        background,
                        scratch: lane_scratch,
                        out,
                        keep: Some(rows),
                    });
                    let bytes = rows.bytes();
                    if kept_bytes.fetch_add(bytes, Ordering::Relaxed) + bytes
                        <= ROW_LIST_BUDGET_BYTES
                    {
                        // A clone holds exactly the words (the thread's buffer keeps its room).
                        *keep_blends = Some(rows.clone());
                    }
                }
                _ => {
                    scalar::forward_tile(
                        splats,
                        &packed,
                        bins.tile_view(t),
                        background,
                        scalar_scratch,
                        out,
                    );
                    let rows = scalar_scratch.rows();
                    let bytes = rows.kept_bytes();
                    if kept_bytes.fetch_add(bytes, Ordering::Relaxed) + bytes
                        <= ROW_LIST_BUDGET_BYTES
                    {
                        *keep = rows.take_kept();
                    }
                }
            }
        },
    );

    // Keep the scalar loops' row lists only if all of them fit.
    let all_fit = lanes_in.is_none() && kept_bytes.into_inner() <= ROW_LIST_BUDGET_BYTES;
    bins.keep_rows(all_fit.then(|| scalar::Kept::new(packed, kept)));
    if lanes_in.is_some() {
        bins.keep_lanes(Some(lanes::Kept {
            packed: packed32,
            blends: kept_blends,
        }));
    }

    // Tile-major staging to row-major images.
    let w = width as usize;
    let h = height as usize;
    let tiles_x = bins.grid().0 as usize;
    let ts = TILE_SIZE as usize;
    let staged =
        |x: usize, y: usize| (y / ts * tiles_x + x / ts) * TILE_PIXELS + (y % ts) * ts + x % ts;
    // Each output element is written once, row by row, into the vectors' spare capacity: the
    // per-pixel outputs in one pass, the channel image in another.
    let mut alpha = Vec::with_capacity(h * w);
    let mut depth = Vec::with_capacity(h * w);
    let mut blended = Vec::with_capacity(h * w);
    let mut normalized_depth = Vec::with_capacity(h * w);
    alpha.spare_capacity_mut()[..h * w]
        .par_chunks_mut(w)
        .zip(depth.spare_capacity_mut()[..h * w].par_chunks_mut(w))
        .zip(blended.spare_capacity_mut()[..h * w].par_chunks_mut(w))
        .zip(normalized_depth.spare_capacity_mut()[..h * w].par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (((a_row, z_row), n_row), nz_row))| {
            for x in 0..w {
                let lp = staged(x, y);
                let (a, z) = (t_alpha[lp], t_depth[lp]);
                a_row[x].write(a);
                z_row[x].write(z);
                n_row[x].write(t_count[lp]);
                nz_row[x].write(if a > T::zero() { z / a } else { T::zero() });
            }
        });
    // SAFETY: the rows above cover the first `h * w` slots of the four vectors (`w > 0`, the
    // same chunking of each), every slot of a row is written, and `for_each` returns only
    // after every row is done.
    unsafe {
        alpha.set_len(h * w);
        depth.set_len(h * w);
        blended.set_len(h * w);
        normalized_depth.set_len(h * w);
    }
    let mut image = Vec::with_capacity(h * w * d);
    if d > 0 {
        image.spare_capacity_mut()[..h * w * d]
            .par_chunks_mut(w * d)
            .enumerate()
            .for_each(|(y, row)| {
                for x in 0..w {
                    let lp = staged(x, y) * d_stage;
                    for (o, &v) in row[x * d..(x + 1) * d].iter_mut().zip(&t_image[lp..lp + d]) {
                        o.write(v);
                    }
                }
            });
        // SAFETY: as above, for the `h * w * d` slots of the image (rows of `w * d > 0`).
        unsafe { image.set_len(h * w * d) };
    }
    Ok(Rasterized {
        width,
        height,
        channel_count: d,
        image,
        alpha,
        depth,
        normalized_depth,
        blended,
        bins,
    })
}
