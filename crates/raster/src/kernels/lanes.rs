//! The `f32` vector tile loops: [`LANES`] consecutive pixels of a tile row walk the row's
//! Gaussian list together, one Gaussian at a time.
//!
//! Per Gaussian, the falloff, alpha, skip, clamp and stop decisions of all lanes are computed
//! at once, as fixed-size arrays that the compiler turns into vector instructions of the
//! instruction set [`super::Token::run`] compiles them for; a lane mask says which pixels blend
//! it. The channel accumulation (and its backward) then runs per blended lane, vectorised across
//! the channels. A row block stops when every lane has reached the transmittance threshold.
//!
//! Each lane performs exactly the operations of the scalar loops ([`super::scalar`]) in the
//! same order, with the same constants and the same exponential ([`gaussian::exp_f32`]); a
//! value is combined into a lane's state only where that lane's mask is set, and record sums
//! take the blended lanes in ascending pixel order, which is the scalar loops' pixel order. The
//! results are therefore bit-identical to the scalar loops in `f32`.

use gaussian::exp_f32;
use pulp::{Simd, WithSimd};

use super::record::{CONIC_A, CONIC_B, CONIC_C, DEPTH, GEOMETRY, MEAN_X, MEAN_Y, OPACITY};
use super::scalar::dot;
use super::TileOut;
use crate::backward::Cotangents;
use crate::blend::{pixel_centre, Splat, ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN};
use crate::forward::Splats;
use crate::rows::{RowEntry, RowLists};
use crate::tiles::TileBins;

/// Pixels evaluated together: one 256-bit vector of `f32`, one segment of the row lists.
pub(crate) const LANES: usize = crate::rows::SPAN;
/// Lane blocks per tile row.
const BLOCKS: usize = TILE_SIZE as usize / LANES;
/// Entries evaluated ahead of the forward pass's blending (a few more than are typically
/// blended before a block saturates would waste evaluations; far fewer would add branches).
const STAGED: usize = 16;
/// Channels per step of the channel loops; channel rows are padded with zeros to a multiple.
const CHUNK: usize = 8;

/// A set of lanes: bit `l` for lane `l`.
type Mask = u32;

/// The per-lane state a Gaussian leaves in the backward pass's front-to-back walk.
#[derive(Clone, Copy, Debug)]
struct BlendedLanes {
    /// Position in the tile list.
    k: u32,
    /// Lanes that blend the Gaussian.
    blend: Mask,
    /// Lanes where the alpha clamp is active (no gradient through alpha).
    clamped: Mask,
    alpha: [f32; LANES],
    /// Transmittance in front of the Gaussian.
    trans: [f32; LANES],
    falloff: [f32; LANES],
    dx: [f32; LANES],
}

/// Per-thread working memory.
#[derive(Default)]
pub(crate) struct Scratch {
    packed: Vec<Splat<f32>>,
    rows: RowLists,
    /// The tile's channel rows, `padded` values each (zeros after the `D` channels).
    channels: Vec<f32>,
    /// Forward: a block's channel accumulators, `padded` per lane. Backward: the block's
    /// image cotangents in the same layout.
    block: Vec<f32>,
    /// Backward: the tile's channel-gradient records, `padded` per tile Gaussian.
    channel_grads: Vec<f32>,
    blended: Vec<BlendedLanes>,
    /// Backward: the block's image cotangents, channel-major: `[c * LANES + l]`.
    v_image_t: Vec<f32>,
}

impl Scratch {
    /// The row lists the last tile built.
    pub fn rows(&mut self) -> &mut RowLists {
        &mut self.rows
    }
}

/// The lanes where `m` is true.
#[inline(always)]
fn bits(m: &[bool; LANES]) -> Mask {
    let mut b = 0;
    for (l, &on) in m.iter().enumerate() {
        b |= (on as Mask) << l;
    }
    b
}

/// Whether lane `l` is in `m`.
#[inline(always)]
fn has(m: Mask, l: usize) -> bool {
    m >> l & 1 != 0
}

/// Calls `f` with each lane of `m`, ascending.
#[inline(always)]
fn for_each_lane(mut m: Mask, mut f: impl FnMut(usize)) {
    while m != 0 {
        f(m.trailing_zeros() as usize);
        m &= m - 1;
    }
}

/// `acc += w * x` over padded channel rows, `CHUNK` channels at a time.
#[inline(always)]
fn axpy(acc: &mut [f32], w: f32, x: &[f32]) {
    let (acc, _) = acc.as_chunks_mut::<CHUNK>();
    let (x, _) = x.as_chunks::<CHUNK>();
    for (a, x) in acc.iter_mut().zip(x) {
        // Whole-array loads and stores: the compiler emits one vector operation per step.
        let (mut sum, x) = (*a, *x);
        for i in 0..CHUNK {
            sum[i] += w * x[i];
        }
        *a = sum;
    }
}

/// One Gaussian evaluated at a block's lanes: the scalar loops' `evaluate`, lane by lane.
struct Eval {
    /// Lanes where the Gaussian is not skipped.
    hit: Mask,
    clamped: Mask,
    dx: [f32; LANES],
    falloff: [f32; LANES],
    alpha: [f32; LANES],
}

/// Evaluates `s` at the pixel centres `cx` of a block in row `cy`, for the lanes of `lanes`
/// (live and in the Gaussian's reach). `None` when no lane is hit, without evaluating the
/// exponential.
#[inline(always)]
fn evaluate(s: &Splat<f32>, lanes: Mask, cx: &[f32; LANES], cy: f32) -> Option<Eval> {
    let (dx, sigma, hit) = sigma_lanes(s, lanes, cx, cy);
    (hit != 0).then(|| alpha_lanes(s, hit, dx, &sigma))
}

/// [`evaluate`] without the early exit: the same lanes and values (`hit` may be empty), with
/// no data-dependent branch.
#[inline(always)]
fn evaluate_all(s: &Splat<f32>, lanes: Mask, cx: &[f32; LANES], cy: f32) -> Eval {
    let (dx, sigma, hit) = sigma_lanes(s, lanes, cx, cy);
    alpha_lanes(s, hit, dx, &sigma)
}

/// The offsets, `sigma` and the lanes of `lanes` where `sigma` is not skipped.
#[inline(always)]
fn sigma_lanes(
    s: &Splat<f32>,
    lanes: Mask,
    cx: &[f32; LANES],
    cy: f32,
) -> ([f32; LANES], [f32; LANES], Mask) {
    let dy = s.my - cy;
    let c_dy2 = s.c * (dy * dy);
    let mut dx = [0f32; LANES];
    let mut sigma = [0f32; LANES];
    let mut keep = [false; LANES];
    for l in 0..LANES {
        dx[l] = s.mx - cx[l];
        sigma[l] = 0.5 * (s.a * (dx[l] * dx[l]) + c_dy2) + s.b * dx[l] * dy;
        keep[l] = !(sigma[l].is_nan() || sigma[l] < 0.0 || sigma[l] > s.sigma_cut);
    }
    (dx, sigma, bits(&keep) & lanes)
}

/// The falloff, clamped alpha and the lanes of `hit` whose alpha is not skipped.
#[inline(always)]
fn alpha_lanes(s: &Splat<f32>, hit: Mask, dx: [f32; LANES], sigma: &[f32; LANES]) -> Eval {
    let alpha_max = ALPHA_MAX as f32;
    let alpha_min = ALPHA_MIN as f32;
    let mut falloff = [0f32; LANES];
    let mut alpha = [0f32; LANES];
    let mut clamped = [false; LANES];
    let mut keep = [false; LANES];
    for l in 0..LANES {
        falloff[l] = exp_f32(-sigma[l]);
        let raw = s.opacity * falloff[l];
        clamped[l] = raw > alpha_max;
        alpha[l] = if clamped[l] { alpha_max } else { raw };
        keep[l] = !(alpha[l].is_nan() || alpha[l] < alpha_min);
    }
    Eval {
        hit: hit & bits(&keep),
        clamped: bits(&clamped),
        dx,
        falloff,
        alpha,
    }
}

/// Applies the transmittance stop to a block: live lanes of `hit` whose transmittance would fall
/// to the threshold stop (they leave `live` and do not blend). Returns the blending lanes and
/// the transmittances in front of the Gaussian, and moves `trans` behind it.
#[inline(always)]
fn advance(
    hit: Mask,
    alpha: &[f32; LANES],
    trans: &mut [f32; LANES],
    live: &mut Mask,
) -> (Mask, [f32; LANES]) {
    let t_min = TRANSMITTANCE_MIN as f32;
    let front = *trans;
    let mut next = [0f32; LANES];
    let mut low = [false; LANES];
    for l in 0..LANES {
        next[l] = trans[l] * (1.0 - alpha[l]);
        low[l] = next[l] <= t_min;
    }
    let hit = hit & *live;
    let stop = hit & bits(&low);
    *live &= !stop;
    let blend = hit & !stop;
    for l in 0..LANES {
        trans[l] = if has(blend, l) { next[l] } else { trans[l] };
    }
    (blend, front)
}

/// The pixel centres of a block and the lanes that lie inside the tile (`width` columns).
#[inline(always)]
fn block_lanes(x0: u32, first: usize, width: usize) -> ([f32; LANES], Mask) {
    let cx = std::array::from_fn(|l| pixel_centre::<f32>(x0 + (first + l) as u32));
    let inside = (1 << LANES.min(width - first)) - 1;
    (cx, inside)
}

/// The lanes of the block starting at tile-local column `first` within a row entry's reach.
#[inline(always)]
fn reach_lanes(e: &RowEntry, first: usize) -> Mask {
    let span = (2u32 << e.x_hi) - (1u32 << e.x_lo);
    (span >> first) & ((1 << LANES) - 1)
}

/// Gathers tile `t`'s packed Gaussians (from `all`, one per Gaussian) and their channel rows
/// (padded to `padded` values), and builds its row lists unless the bins kept them; returns its
/// Gaussian ids.
fn prepare<'b>(
    splats: &Splats<f32>,
    all: &[Splat<f32>],
    bins: &'b TileBins,
    t: usize,
    padded: usize,
    scratch: &mut Scratch,
) -> &'b [u32] {
    let d = splats.channel_count;
    let ids = bins.tile(t);
    scratch.packed.clear();
    scratch.packed.extend(ids.iter().map(|&g| all[g as usize]));
    if bins.kept_rows(t).is_none() {
        scratch.rows.build(&scratch.packed, bins.pixel_rect(t));
    }
    scratch.channels.clear();
    scratch.channels.resize(ids.len() * padded, 0.0);
    for (row, &g) in scratch.channels.chunks_exact_mut(padded).zip(ids) {
        row[..d].copy_from_slice(splats.channels_of(g as usize));
    }
    ids
}

/// `D` rounded up to a whole number of chunks (at least one).
fn padded(d: usize) -> usize {
    d.div_ceil(CHUNK).max(1) * CHUNK
}

/// The forward pass over one tile (see [`super::scalar::forward_tile`]).
pub(crate) struct ForwardTile<'a, 'b> {
    pub splats: &'a Splats<'a, f32>,
    /// Every Gaussian packed ([`Splats::packed`]).
    pub packed: &'a [Splat<f32>],
    pub bins: &'a TileBins,
    pub background: &'a [f32],
    pub t: usize,
    pub scratch: &'b mut Scratch,
    pub out: TileOut<'b, f32>,
}

impl WithSimd for ForwardTile<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, _: S) {
        let ForwardTile {
            splats,
            packed: all,
            bins,
            background,
            t,
            scratch,
            out,
        } = self;
        let d = splats.channel_count;
        let dp = padded(d);
        let ids = prepare(splats, all, bins, t, dp, scratch);
        let Scratch {
            packed,
            rows,
            channels,
            block,
            ..
        } = scratch;
        let rows = bins.kept_rows(t).unwrap_or(rows);
        let (x0, y0, x1, y1) = bins.pixel_rect(t);
        let width = (x1 - x0) as usize;
        for py in y0..y1 {
            let ly = (py - y0) as usize;
            let cy = pixel_centre::<f32>(py);
            for first in (0..BLOCKS).map(|b| b * LANES).take_while(|&f| f < width) {
                let row = rows.list(py - y0, first / LANES);
                let (cx, mut live) = block_lanes(x0, first, width);
                block.clear();
                block.resize(LANES * dp, 0.0);
                let mut trans = [1f32; LANES];
                let mut z = [0f32; LANES];
                let mut n = [0u32; LANES];
                let mut staged = [(0u32, 0 as Mask, [0f32; LANES]); STAGED];
                // Evaluate the next entries until STAGED ones hit some lane (without
                // data-dependent branches: every entry is written, a hit one is kept), then
                // blend those in order.
                let mut next_entry = 0;
                'walk: while next_entry < row.len() {
                    let mut m = 0;
                    while next_entry < row.len() && m < STAGED {
                        let e = &row[next_entry];
                        next_entry += 1;
                        let lanes = reach_lanes(e, first) & live;
                        let ev = evaluate_all(&packed[e.k as usize], lanes, &cx, cy);
                        staged[m] = (e.k, ev.hit, ev.alpha);
                        m += (ev.hit != 0) as usize;
                    }
                    for &(k, hit, alpha) in &staged[..m] {
                        let k = k as usize;
                        let (blend, front) = advance(hit, &alpha, &mut trans, &mut live);
                        let depth = splats.depths[ids[k] as usize];
                        let mut w = [0f32; LANES];
                        for l in 0..LANES {
                            w[l] = alpha[l] * front[l];
                            let b = has(blend, l);
                            z[l] = if b { z[l] + w[l] * depth } else { z[l] };
                            n[l] += b as u32;
                        }
                        let col = &channels[k * dp..(k + 1) * dp];
                        for_each_lane(blend, |l| axpy(&mut block[l * dp..(l + 1) * dp], w[l], col));
                        if live == 0 {
                            break 'walk;
                        }
                    }
                }
                let lp0 = ly * TILE_SIZE as usize + first;
                for l in 0..LANES.min(width - first) {
                    let acc = &block[l * dp..l * dp + d];
                    let pixel = &mut out.image[(lp0 + l) * d..(lp0 + l + 1) * d];
                    for ((o, &a), &b) in pixel.iter_mut().zip(acc).zip(background) {
                        *o = a + trans[l] * b;
                    }
                    out.alpha[lp0 + l] = 1.0 - trans[l];
                    out.depth[lp0 + l] = z[l];
                    out.count[lp0 + l] = n[l];
                }
            }
        }
    }
}

/// The backward pass over one tile (see [`super::scalar::backward_tile`]).
pub(crate) struct BackwardTile<'a, 'b> {
    pub splats: &'a Splats<'a, f32>,
    /// Every Gaussian packed ([`Splats::packed`]).
    pub packed: &'a [Splat<f32>],
    pub bins: &'a TileBins,
    pub background: &'a [f32],
    pub cot: &'a Cotangents<'a, f32>,
    pub t: usize,
    pub scratch: &'b mut Scratch,
    pub rec: &'b mut [f32],
    pub bg_grad: &'b mut [f32],
}

impl WithSimd for BackwardTile<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, _: S) {
        let BackwardTile {
            splats,
            packed: all,
            bins,
            background,
            cot,
            t,
            scratch,
            rec,
            bg_grad,
        } = self;
        let d = splats.channel_count;
        let dp = padded(d);
        let stride = GEOMETRY + d;
        let ids = prepare(splats, all, bins, t, dp, scratch);
        let Scratch {
            packed,
            rows,
            channels,
            block,
            channel_grads,
            blended,
            v_image_t,
        } = scratch;
        let rows = bins.kept_rows(t).unwrap_or(rows);
        let (x0, y0, x1, y1) = bins.pixel_rect(t);
        let width = (x1 - x0) as usize;
        let image_width = bins.width() as usize;
        v_image_t.clear();
        v_image_t.resize(d * LANES, 0.0);
        channel_grads.clear();
        channel_grads.resize(ids.len() * dp, 0.0);
        block.clear();
        block.resize(LANES * dp, 0.0);
        for py in y0..y1 {
            let cy = pixel_centre::<f32>(py);
            for first in (0..BLOCKS).map(|b| b * LANES).take_while(|&f| f < width) {
                let row = rows.list(py - y0, first / LANES);
                let (cx, mut live) = block_lanes(x0, first, width);
                let count = LANES.min(width - first);

                // Front to back: the forward pass's decisions, alphas and transmittances.
                blended.clear();
                let mut trans = [1f32; LANES];
                for e in row {
                    let lanes = reach_lanes(e, first) & live;
                    if lanes == 0 {
                        continue;
                    }
                    let Some(ev) = evaluate(&packed[e.k as usize], lanes, &cx, cy) else {
                        continue;
                    };
                    let (blend, front) = advance(ev.hit, &ev.alpha, &mut trans, &mut live);
                    if blend != 0 {
                        blended.push(BlendedLanes {
                            k: e.k,
                            blend,
                            clamped: ev.clamped,
                            alpha: ev.alpha,
                            trans: front,
                            falloff: ev.falloff,
                            dx: ev.dx,
                        });
                    }
                    if live == 0 {
                        break;
                    }
                }

                // The block's cotangents, in both layouts.
                let p0 = py as usize * image_width + x0 as usize + first;
                let v_img = &cot.image[p0 * d..(p0 + count) * d];
                let mut v_alpha = [0f32; LANES];
                let mut v_depth = [0f32; LANES];
                let mut behind = [0f32; LANES];
                for l in 0..LANES {
                    let v = if l < count {
                        &v_img[l * d..(l + 1) * d]
                    } else {
                        &[]
                    };
                    block[l * dp..(l + 1) * dp].fill(0.0);
                    block[l * dp..l * dp + v.len()].copy_from_slice(v);
                    for c in 0..d {
                        v_image_t[c * LANES + l] = v.get(c).copied().unwrap_or(0.0);
                    }
                    if l < count {
                        v_alpha[l] = cot.alpha.map_or(0.0, |a| a[p0 + l]);
                        v_depth[l] = cot.depth.map_or(0.0, |z| z[p0 + l]);
                        for (b, &vc) in bg_grad.iter_mut().zip(v) {
                            *b += trans[l] * vc;
                        }
                        behind[l] = dot(v, background);
                    }
                }

                // Back to front.
                for bl in blended.iter().rev() {
                    let k = bl.k as usize;
                    let g = ids[k] as usize;
                    let s = &packed[k];
                    let z = splats.depths[g];
                    let mut own = [0f32; LANES];
                    for (c, &col) in channels[k * dp..k * dp + d].iter().enumerate() {
                        let v = &v_image_t[c * LANES..(c + 1) * LANES];
                        for l in 0..LANES {
                            own[l] += v[l] * col;
                        }
                    }
                    let dy = s.my - cy;
                    let mut w = [0f32; LANES];
                    let mut geo = [[0f32; LANES]; GEOMETRY];
                    for l in 0..LANES {
                        let (alpha, front, dx) = (bl.alpha[l], bl.trans[l], bl.dx[l]);
                        let own_l = own[l] + v_depth[l] * z + v_alpha[l];
                        w[l] = alpha * front;
                        geo[DEPTH][l] = w[l] * v_depth[l];
                        let v_a = front * (own_l - behind[l]);
                        let next = alpha * own_l + (1.0 - alpha) * behind[l];
                        behind[l] = if has(bl.blend, l) { next } else { behind[l] };
                        geo[OPACITY][l] = v_a * bl.falloff[l];
                        let v_sigma = -(v_a * alpha);
                        geo[CONIC_A][l] = v_sigma * 0.5 * dx * dx;
                        geo[CONIC_B][l] = v_sigma * dx * dy;
                        geo[CONIC_C][l] = v_sigma * 0.5 * dy * dy;
                        geo[MEAN_X][l] = v_sigma * (s.a * dx + s.b * dy);
                        geo[MEAN_Y][l] = v_sigma * (s.b * dx + s.c * dy);
                    }
                    let r = &mut rec[k * stride..k * stride + GEOMETRY];
                    let grads = &mut channel_grads[k * dp..(k + 1) * dp];
                    for_each_lane(bl.blend, |l| {
                        axpy(grads, w[l], &block[l * dp..(l + 1) * dp]);
                        r[DEPTH] += geo[DEPTH][l];
                        if !has(bl.clamped, l) {
                            for j in [OPACITY, CONIC_A, CONIC_B, CONIC_C, MEAN_X, MEAN_Y] {
                                r[j] += geo[j][l];
                            }
                        }
                    });
                }
            }
        }
        // The channel records start at zero, so copying the sums equals adding them.
        for (r, grads) in rec
            .chunks_exact_mut(stride)
            .zip(channel_grads.chunks_exact(dp))
        {
            r[GEOMETRY..].copy_from_slice(&grads[..d]);
        }
    }
}
