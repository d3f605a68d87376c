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
//! `alpha_i` is close to 1. The lane kernels' forward pass keeps, in its bins, which tile rows
//! of which Gaussians it blended; given those bins and the same Gaussians, the first sweep
//! evaluates only those rows, with the same operations, instead of walking every Gaussian of
//! the tile again (the same values either way).
//!
//! Through `alpha = min(0.999, opacity exp(-sigma))`: when the clamp is active the gradient is zero
//! (as `torch.clamp_max`); otherwise `dalpha/dopacity = exp(-sigma)`, `dalpha/dsigma = -alpha`,
//! `dsigma/dconic = (dx^2 / 2, dx dy, dy^2 / 2)` and `dsigma/dmean2d = (a dx + b dy, b dx + c dy)`.
//! The stop and skip decisions are piecewise constant and carry no gradient.
//!
//! # Determinism and memory
//! Tiles run in parallel. Each tile accumulates its pixels' contributions, in a fixed pixel
//! order, into one partial-gradient record per intersection (`7 + D` reals), or, when the lane
//! forward pass kept the blended rows of every tile, one per intersection that blends somewhere
//! (the others' records would be zero: a sum that starts at +0 is the same without zero
//! terms, as it never becomes -0). Records are then summed per Gaussian in ascending
//! intersection order (tile order), whatever the thread count; after each batch only the
//! Gaussians with records in it are visited (with one batch, all of them).
//! Tiles are processed in consecutive batches whose records fit in a budget
//! (`gradient_buffer_values`, default [`DEFAULT_GRADIENT_BUFFER_VALUES`]), so the peak memory is:
//! the outputs, `N (7 + D)` reals of per-Gaussian accumulators, `min(budget, I (7 + D))` reals of
//! records (`I` intersections, or the blending ones; a single tile larger than the budget gets a
//! batch of its own), with more than one batch a bit per Gaussian,
//! `D` reals per tile for the background gradient, and per thread one tile's working memory:
//! for the scalar loops its packed Gaussians (7 reals each), its row lists (8 bytes per Gaussian
//! and row it reaches, see [`crate::rows`]) and one pixel's blend list (4 reals and 2 words per
//! blended Gaussian); for the lane kernels every (Gaussian, tile row) it blends in (140 bytes
//! each, and 8 for the row decoded from the forward pass's kept rows) and the tile's image
//! cotangents (`256 D` reals). The bins of a lane forward pass hold its packed Gaussians (40
//! bytes each) and its blended rows (4 bytes each, 8 after a step of 4,095 or more along the
//! tile list, while they fit [`crate::tiles::ROW_LIST_BUDGET_BYTES`]; tiles beyond it are walked
//! again).

use std::mem::MaybeUninit;

use base::memory::{clear_with_capacity, fill_uninit, filled, refill};
use gaussian::Real;
use rayon::prelude::*;

use crate::error::{check_len, RasterError};
use crate::kernels::record::{CONIC_A, CONIC_B, CONIC_C, DEPTH, GEOMETRY, MEAN_X, MEAN_Y, OPACITY};
use crate::kernels::{lanes, prefetch, scalar, Kernel, Token};
pub use crate::splats::Cotangents;
use crate::splats::Splats;
use crate::tiles::TileBins;

/// Default budget for the per-intersection gradient records: 2^24 reals (128 MiB in `f64`).
pub const DEFAULT_GRADIENT_BUFFER_VALUES: usize = 1 << 24;

/// Gradients with respect to every rasterizer input.
#[derive(Clone, Debug, PartialEq)]
pub struct SplatGrads<T> {
    /// With respect to the projected 2D means, in pixels, one `[x, y]` per Gaussian.
    pub means2d: Vec<[T; 2]>,
    /// With respect to the conics `(a, b, c)` (inverse 2D covariances), one per Gaussian.
    pub conics: Vec<[T; 3]>,
    /// With respect to the opacities (after the sigmoid).
    pub opacities: Vec<T>,
    /// With respect to the view-space depths (through the depth image only; the sort order carries
    /// no gradient), one per Gaussian.
    pub depths: Vec<T>,
    /// With respect to the channel values: `len() * channel_count`, Gaussian-major.
    pub channels: Vec<T>,
    /// With respect to the background: `channel_count` values.
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
    rasterize_backward_with(
        splats,
        bins,
        background,
        cot,
        gradient_buffer_values,
        Kernel::auto()?,
    )
}

/// [`rasterize_backward_with_budget`] with the given tile kernel (the result is the same bits
/// with every kernel; see [`crate::kernels`]).
pub fn rasterize_backward_with<T: Real>(
    splats: &Splats<T>,
    bins: &TileBins,
    background: &[T],
    cot: &Cotangents<T>,
    gradient_buffer_values: usize,
    kernel: Kernel,
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
    // The gradients, accumulated in place: per Gaussian, geometry and channels.
    let mut geometry = filled(n, [T::zero(); GEOMETRY]);
    let mut channels = filled(n * d, T::zero());
    let tiles = bins.tile_count();
    let mut tile_bg = vec![T::zero(); tiles * d];
    let mut records: Vec<T> = Vec::new();
    // The lane kernels run in f32 only.
    let token = Token::for_kernel(kernel);
    let splats32 = splats.as_f32();
    let background32 = T::as_f32_slice(background);
    // When T is f32 every slice converts.
    let cot32 = T::as_f32_slice(cot.image).map(|image| Cotangents {
        image,
        alpha: cot.alpha.and_then(T::as_f32_slice),
        depth: cot.depth.and_then(T::as_f32_slice),
    });
    let lanes_in = match (token, &splats32, background32, &cot32) {
        (Some(token), Some(s), Some(b), Some(c)) => Some((token, s, b, c)),
        _ => None,
    };
    // The lane forward pass's packed Gaussians and blended rows, when it kept them in the bins
    // for these same Gaussians (checked: bins passed along with other Gaussians are walked
    // again, so the result never depends on what was kept).
    let kept = match (lanes_in, bins.kept_lanes()) {
        (Some((_, s, _, _)), Some(k)) if k.matches(s) => Some(k),
        _ => None,
    };
    let packed_fresh = match (lanes_in, kept) {
        (Some((_, s, _, _)), None) => lanes::pack(s, height),
        _ => Vec::new(),
    };
    let packed32 = kept.map_or(&packed_fresh[..], |k| &k.packed[..]);
    let packed = if lanes_in.is_some() {
        Vec::new()
    } else {
        splats.packed()
    };
    // The scalar forward pass's row lists, when it kept them in the bins for these same
    // Gaussians (checked, as above).
    let kept_rows = match lanes_in {
        None => bins.kept_rows().and_then(|k| k.lists_for(&packed)),
        Some(_) => None,
    };
    // The records: one per tile list entry, or, when the forward pass kept the blended rows of
    // every tile, one per entry that blends somewhere in its tile (the others' records would
    // stay zero, and a sum that starts at +0 is the same without zero terms: it never becomes
    // -0). `record_ids` lists the Gaussian of each record, tile by tile, in list order.
    // Per tile, the Gaussians of its records (its blending positions mapped to their ids).
    let compact: Option<Vec<Vec<u32>>> =
        kept.filter(|k| k.blends.iter().all(Option::is_some))
            .map(|k| {
                k.blends
                    .par_iter()
                    .enumerate()
                    .map(|(t, rows)| {
                        rows.as_ref()
                            .map_or_else(Vec::new, |rows| lanes::blending_ids(rows, bins.tile(t)))
                    })
                    .collect()
            });
    let compact_ids: Vec<u32>;
    let (record_ids, record_start): (&[u32], Vec<usize>) = match &compact {
        Some(tile_ids) => {
            compact_ids = tile_ids.concat();
            let mut start = Vec::with_capacity(tiles + 1);
            let mut total = 0;
            for ids in tile_ids {
                start.push(total);
                total += ids.len();
            }
            start.push(total);
            (&compact_ids, start)
        }
        None => (
            bins.gaussian_ids(),
            (0..tiles)
                .map(|t| bins.range(t).start)
                .chain([bins.intersection_count()])
                .collect(),
        ),
    };
    // Each Gaussian's records in ascending order, so that the sum of its records runs in
    // intersection order in time linear in the records (see `GaussianLists`). Built alongside
    // the first batch's tile pass, which does not read them.
    GaussianLists::check(record_ids)?;
    let mut lists: Option<GaussianLists> = None;
    let mut next = Vec::new();
    let mut present: Vec<u64> = Vec::new();

    let mut first = 0;
    while first < tiles {
        // The batch: tiles [first, last) whose records fit the budget (at least one tile).
        let begin = record_start[first];
        let mut last = first + 1;
        while last < tiles && (record_start[last + 1] - begin) * stride <= gradient_buffer_values {
            last += 1;
        }
        let end = record_start[last];
        // Not filled in advance: each tile's task initialises its own records, in cache (the
        // lane kernels' compact records are each written once, by their Gaussian's group).
        let len = (end - begin) * stride;
        clear_with_capacity(&mut records, len);

        // Split the records into per-tile slices.
        let mut slices = Vec::with_capacity(last - first);
        let mut rest: &mut [MaybeUninit<T>] = &mut records.spare_capacity_mut()[..len];
        let mut bg_rest: &mut [T] = &mut tile_bg[first * d..last * d];
        for t in first..last {
            let count = record_start[t + 1] - record_start[t];
            let (mine, tail) = rest.split_at_mut(count * stride);
            let (bg_mine, bg_tail) = bg_rest.split_at_mut(d);
            slices.push((t, mine, bg_mine));
            rest = tail;
            bg_rest = bg_tail;
        }
        // Handed out one tile at a time, longest lists first (see `TileBins::schedule_key`).
        slices.sort_unstable_by_key(|&(t, _, _)| bins.schedule_key(t));
        let tile_pass = || {
            slices.into_iter().par_bridge().for_each_init(
                <(scalar::Scratch<T>, lanes::Scratch)>::default,
                |(scalar_scratch, lane_scratch), (t, rec, bg)| {
                    let lanes_out = T::as_f32_uninit_mut(rec).zip(T::as_f32_slice_mut(bg));
                    match (&lanes_in, lanes_out) {
                        (Some((token, splats, background, cot)), Some((rec, bg_grad))) => token
                            .run(lanes::BackwardTile {
                                splats,
                                packed: packed32,
                                tile: bins.tile_view(t),
                                background,
                                cot,
                                scratch: lane_scratch,
                                rec,
                                bg_grad,
                                kept: kept.and_then(|k| k.blends[t].as_ref()),
                                compact: compact.is_some(),
                            }),
                        _ => scalar::backward_tile(
                            splats,
                            &packed,
                            bins.tile_view(t),
                            kept_rows.map(|lists| &lists[t]),
                            background,
                            cot,
                            scalar_scratch,
                            fill_uninit(rec, T::zero()),
                            bg,
                        ),
                    }
                },
            )
        };
        let lists = match &mut lists {
            Some(lists) => {
                tile_pass();
                lists
            }
            None => {
                let (built, ()) = rayon::join(|| GaussianLists::new(record_ids, n), tile_pass);
                next = built.start[..n].to_vec();
                lists.insert(built)
            }
        };
        // SAFETY: the tiles' parts cover `records[..len]`, and the tile pass initialised every
        // part: the scalar loops fill theirs with zeros before adding to it, the lane kernels
        // fill a part of one record per list entry, and write a part of compact records
        // record by record after checking that the tile's Gaussians cover it.
        unsafe { records.set_len(len) };

        // Sum the records per Gaussian, in intersection order: each Gaussian takes its
        // intersections of this batch, which follow its cursor in its ascending list.
        let records = &records;
        // One channel chunk per geometry chunk (empty ones when `d == 0`).
        let channel_chunks: Vec<&mut [T]> = if d > 0 {
            channels.chunks_mut(GATHER_CHUNK * d).collect()
        } else {
            (0..n.div_ceil(GATHER_CHUNK)).map(|_| &mut [][..]).collect()
        };
        // With several batches, the Gaussians that have records in this one (a bit each), so
        // that each batch visits those alone instead of every Gaussian; the others' sums would
        // take no term from it. With one batch every Gaussian is visited.
        let single = first == 0 && last == tiles;
        if !single {
            refill(&mut present, n.div_ceil(64), 0);
            for &g in &record_ids[begin..end] {
                present[g as usize / 64] |= 1 << (g % 64);
            }
        }
        let present = (!single).then_some(&present[..]);
        geometry
            .par_chunks_mut(GATHER_CHUNK)
            .zip(channel_chunks)
            .zip(next.par_chunks_mut(GATHER_CHUNK))
            .enumerate()
            .for_each_init(
                Vec::new,
                |members, (chunk, ((geo_chunk, channel_chunk), next_chunk))| {
                    let g0 = chunk * GATHER_CHUNK;
                    // The chunk's Gaussians to visit, ascending (positions in the chunk).
                    members.clear();
                    match present {
                        None => members.extend(0..geo_chunk.len()),
                        Some(bits) => {
                            // GATHER_CHUNK is a multiple of 64: the chunk's words are whole.
                            let words = &bits[g0 / 64..(g0 + geo_chunk.len()).div_ceil(64)];
                            for (w, &word) in words.iter().enumerate() {
                                let mut m = word;
                                while m != 0 {
                                    members.push(w * 64 + m.trailing_zeros() as usize);
                                    m &= m - 1;
                                }
                            }
                        }
                    }
                    for (at, &i) in members.iter().enumerate() {
                        let geo = &mut geo_chunk[i];
                        // With `d == 0` the channel chunks are empty.
                        let dst_channels = &mut channel_chunk[i * d..(i + 1) * d];
                        // The records of a Gaussian a few ahead, from its cursor on.
                        if let Some(&i_ahead) = members.get(at + GATHER_AHEAD) {
                            let from = next_chunk[i_ahead];
                            let ahead = g0 + i_ahead;
                            for &j in &lists.intersections[from..lists.start[ahead + 1]] {
                                let j = j as usize;
                                if j >= end {
                                    break;
                                }
                                prefetch(&records[(j - begin) * stride..(j - begin + 1) * stride]);
                            }
                        }
                        let cursor = &mut next_chunk[i];
                        let stop = lists.start[g0 + i + 1];
                        while *cursor < stop {
                            let j = lists.intersections[*cursor] as usize;
                            if j >= end {
                                break;
                            }
                            let r = &records[(j - begin) * stride..(j - begin + 1) * stride];
                            for (a, &v) in geo.iter_mut().zip(&r[..GEOMETRY]) {
                                *a += v;
                            }
                            for (a, &v) in dst_channels.iter_mut().zip(&r[GEOMETRY..]) {
                                *a += v;
                            }
                            *cursor += 1;
                        }
                    }
                },
            );
        first = last;
    }

    let mut background_grad = vec![T::zero(); d];
    for t in 0..tiles {
        for (b, &v) in background_grad.iter_mut().zip(&tile_bg[t * d..(t + 1) * d]) {
            *b += v;
        }
    }
    // Element-wise copies out of the sums, in one pass of the pool's threads that writes each
    // output element once (into the vectors' spare capacity).
    let mut grads = SplatGrads {
        means2d: Vec::with_capacity(n),
        conics: Vec::with_capacity(n),
        opacities: Vec::with_capacity(n),
        depths: Vec::with_capacity(n),
        channels,
        background: background_grad,
    };
    geometry
        .par_chunks(GATHER_CHUNK)
        .zip(grads.means2d.spare_capacity_mut()[..n].par_chunks_mut(GATHER_CHUNK))
        .zip(grads.conics.spare_capacity_mut()[..n].par_chunks_mut(GATHER_CHUNK))
        .zip(grads.opacities.spare_capacity_mut()[..n].par_chunks_mut(GATHER_CHUNK))
        .zip(grads.depths.spare_capacity_mut()[..n].par_chunks_mut(GATHER_CHUNK))
        .for_each(|((((geo, means2d), conics), opacities), depths)| {
            for (i, r) in geo.iter().enumerate() {
                means2d[i].write([r[MEAN_X], r[MEAN_Y]]);
                conics[i].write([r[CONIC_A], r[CONIC_B], r[CONIC_C]]);
                opacities[i].write(r[OPACITY]);
                depths[i].write(r[DEPTH]);
            }
        });
    // SAFETY: the chunks above cover the first `n` slots of the four vectors (the same
    // chunking of each, matching `geometry`'s `n` rows), every slot of a chunk is written, and
    // `for_each` returns only after every chunk is done.
    unsafe {
        grads.means2d.set_len(n);
        grads.conics.set_len(n);
        grads.opacities.set_len(n);
        grads.depths.set_len(n);
    }
    Ok(grads)
}

/// Gaussians per task of the gradient gather (any multiple of 64 gives the same result).
const GATHER_CHUNK: usize = 2048;
const _: () = assert!(GATHER_CHUNK.is_multiple_of(64));

/// Gaussians ahead whose records the gather prefetches.
const GATHER_AHEAD: usize = 8;

/// The intersections of each Gaussian, ascending: Gaussian `g`'s are
/// `intersections[start[g]..start[g + 1]]` (a counting sort of the tile lists by Gaussian).
struct GaussianLists {
    start: Vec<usize>,
    intersections: Vec<u32>,
}

impl GaussianLists {
    /// `Ok` when the intersections `ids` can be listed (their positions fit `u32`).
    fn check(ids: &[u32]) -> Result<(), RasterError> {
        if ids.len() > u32::MAX as usize {
            return Err(RasterError::TooManyIntersections(ids.len()));
        }
        Ok(())
    }

    /// The lists of the intersections `ids` (of Gaussians `0..n`; [`GaussianLists::check`]ed).
    fn new(ids: &[u32], n: usize) -> GaussianLists {
        let mut start = vec![0usize; n + 1];
        for &g in ids {
            start[g as usize + 1] += 1;
        }
        for g in 0..n {
            start[g + 1] += start[g];
        }
        let mut cursor = start[..n].to_vec();
        let mut intersections = vec![0u32; ids.len()];
        for (j, &g) in ids.iter().enumerate() {
            let c = &mut cursor[g as usize];
            intersections[*c] = j as u32;
            *c += 1;
        }
        GaussianLists {
            start,
            intersections,
        }
    }
}
