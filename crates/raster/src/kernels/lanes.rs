//! The `f32` vector tile loops: a tile row of [`LANES`] = 16 pixels is one vector, and a
//! tile's Gaussians are taken one at a time, front to back, each evaluated on the rows of the
//! tile it can reach.
//!
//! Per Gaussian and row, the falloff, alpha, skip, clamp and stop decisions of the row's 16
//! pixels are computed at once, as fixed-size arrays that the compiler turns into vector
//! instructions of the instruction set [`super::Token::run`] compiles them for (one 512-bit
//! vector with AVX-512, two 256-bit ones with AVX2, four 128-bit ones with NEON or SSE2), with
//! comparisons and selects through that instruction set's mask operations ([`LaneIsa`]); a lane
//! mask says which pixels blend it. The channel loops are unrolled for the common channel
//! counts ([`Fixed`]). The rows a Gaussian can reach come from its ellipse, once
//! per Gaussian ([`crate::rows::reach_rows`]); no per-row list is built. The tile keeps every
//! pixel's transmittance and stop state, so walking the Gaussians in the outer loop gives each
//! pixel the same Gaussians in the same order as the scalar loops' per-pixel walk. A tile stops
//! when every pixel has reached the transmittance threshold.
//!
//! Forward, the channel accumulation runs per blended lane, vectorised across channels, or for
//! few channels (colour) per channel, vectorised across the row's lanes.
//! Backward, a first front-to-back walk keeps, for every row a Gaussian blends in, its lanes,
//! transmittances and falloffs; a second walk takes the Gaussians back to front (the rows of one
//! Gaussian in ascending order), computing every pixel's gradient terms at once across the row
//! and adding them to per-column sums of the Gaussian's record, all lanes at once (the channel
//! terms of more than a few channels lane by lane in ascending pixel order), in the order of
//! [`super::record`]. The forward pass keeps the (Gaussian, row, lanes) it blends ([`RowRef`],
//! 4 bytes each in [`KeptRows`], in the bins); when the backward pass gets them for the same
//! Gaussians, its first walk becomes a replay of those rows
//! ([`replay`]): the same evaluations and transmittance products, skipping the Gaussians and
//! rows that blend nowhere.
//!
//! Each lane performs exactly the operations of the scalar loops ([`super::scalar`]) in the
//! same order, with the same constants and the same exponential ([`gaussian::exp_f32`]); a
//! value is combined into a lane's state only where that lane's mask is set, and every record
//! sum takes the pixels in the scalar loops' order. The results are therefore bit-identical to
//! the scalar loops in `f32`.

use std::mem::MaybeUninit;

use base::memory::fill_uninit;
use gaussian::{exp_f32, exp_f32_in_range, EXP_F32_HIGH, EXP_F32_LOW};
use rayon::prelude::*;

use super::record::{
    COLUMN_CHANNELS_MAX, CONIC_A, CONIC_B, CONIC_C, DEPTH, GEOMETRY, MEAN_X, MEAN_Y, OPACITY,
};
use super::scalar::dot;
use super::{prefetch, Tile, TileOut};
use crate::blend::{pixel_centre, Splat, ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN};
use crate::rows::reach_rows;
use crate::splats::{Cotangents, Splats};

/// Pixels evaluated together: one tile row.
pub(crate) const LANES: usize = TILE_SIZE as usize;

/// A set of lanes (bit `l` for lane `l`) or of tile rows (bit `r` for row `r`).
type Mask = u32;

/// An instruction set the lane kernels run at: the comparisons whose results become lane masks.
pub(crate) trait LaneIsa: Copy {
    /// The lanes where `a <= b` (never where either is NaN).
    #[inline(always)]
    fn le(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        mask_by(a, b, |x, y| x <= y)
    }

    /// The lanes where `a < b` (never where either is NaN).
    #[inline(always)]
    fn lt(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        mask_by(a, b, |x, y| x < y)
    }

    /// `a` in the lanes of `m`, `b` in the others.
    #[inline(always)]
    fn select(self, m: Mask, a: &[f32; LANES], b: &[f32; LANES]) -> [f32; LANES] {
        std::array::from_fn(|l| if has(m, l) { a[l] } else { b[l] })
    }
}

/// The lanes where `f(a[l], b[l])`, one lane at a time.
#[inline(always)]
fn mask_by(a: &[f32; LANES], b: &[f32; LANES], f: impl Fn(f32, f32) -> bool) -> Mask {
    let mut m = 0;
    for l in 0..LANES {
        m |= (f(a[l], b[l]) as Mask) << l;
    }
    m
}

#[cfg(target_arch = "x86_64")]
impl LaneIsa for pulp::x86::V4 {
    #[inline(always)]
    fn le(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        self.cmp_le_f32x16(pulp::cast(*a), pulp::cast(*b)).0 as Mask
    }
    #[inline(always)]
    fn lt(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        self.cmp_lt_f32x16(pulp::cast(*a), pulp::cast(*b)).0 as Mask
    }
    #[inline(always)]
    fn select(self, m: Mask, a: &[f32; LANES], b: &[f32; LANES]) -> [f32; LANES] {
        let mask = pulp::b16(m as u16);
        pulp::cast(self.select_f32x16(mask, pulp::cast(*a), pulp::cast(*b)))
    }
}

/// Two 8-lane comparisons and their sign masks.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn v3_mask<const OP: i32>(simd: pulp::x86::V3, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
    let (a, b): ([[f32; 8]; 2], [[f32; 8]; 2]) = (pulp::cast(*a), pulp::cast(*b));
    let half = |i: usize| {
        let m = simd
            .avx
            ._mm256_cmp_ps::<OP>(pulp::cast(a[i]), pulp::cast(b[i]));
        simd.avx._mm256_movemask_ps(m) as Mask
    };
    half(0) | half(1) << 8
}

#[cfg(target_arch = "x86_64")]
impl LaneIsa for pulp::x86::V3 {
    #[inline(always)]
    fn le(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        v3_mask::<{ std::arch::x86_64::_CMP_LE_OQ }>(self, a, b)
    }
    #[inline(always)]
    fn lt(self, a: &[f32; LANES], b: &[f32; LANES]) -> Mask {
        v3_mask::<{ std::arch::x86_64::_CMP_LT_OQ }>(self, a, b)
    }
}

/// NEON and the baseline target: the lane-by-lane comparisons, which the compiler vectorises.
#[cfg(target_arch = "aarch64")]
impl LaneIsa for pulp::aarch64::Neon {}

impl LaneIsa for pulp::Scalar {}

/// A lane kernel: runs inside code compiled for the instruction set `isa` stands for.
pub(crate) trait LaneOp {
    type Output;
    fn run<I: LaneIsa>(self, isa: I) -> Self::Output;
}

/// The channel count `D` of a pass: a constant for the common counts (so that the channel loops
/// are unrolled into whole vectors), or any count.
trait Width: Copy {
    /// `D` reals, zero: a channel accumulator (an array, kept in registers, when `D` is fixed).
    type Acc: AsMut<[f32]> + AsRef<[f32]>;

    fn d(self) -> usize;

    fn zeros(self) -> Self::Acc;

    /// `own[i][l] = sum_c v_i[c][l] * col[c]` (channels in order) for two row blocks `v_0`
    /// and `v_1` of `D` channel vectors each: two independent sums at once.
    #[inline(always)]
    fn dots(self, v_0: &[f32], v_1: &[f32], col: &[f32]) -> [[f32; LANES]; 2] {
        let mut own = [[0f32; LANES]; 2];
        let (v_0, v_1) = (v_0.as_chunks::<LANES>().0, v_1.as_chunks::<LANES>().0);
        for ((a, b), &col_c) in v_0.iter().zip(v_1).zip(&col[..self.d()]) {
            for l in 0..LANES {
                own[0][l] += a[l] * col_c;
                own[1][l] += b[l] * col_c;
            }
        }
        own
    }

    /// [`Width::dots`] for four row blocks.
    #[inline(always)]
    fn dots4(self, v: [&[f32]; 4], col: &[f32]) -> [[f32; LANES]; 4] {
        let mut own = [[0f32; LANES]; 4];
        let [v_0, v_1, v_2, v_3] = v;
        let (v_0, v_1) = (v_0.as_chunks::<LANES>().0, v_1.as_chunks::<LANES>().0);
        let (v_2, v_3) = (v_2.as_chunks::<LANES>().0, v_3.as_chunks::<LANES>().0);
        let blocks = v_0.iter().zip(v_1).zip(v_2).zip(v_3);
        for ((((a, b), e), f), &col_c) in blocks.zip(&col[..self.d()]) {
            for l in 0..LANES {
                own[0][l] += a[l] * col_c;
                own[1][l] += b[l] * col_c;
                own[2][l] += e[l] * col_c;
                own[3][l] += f[l] * col_c;
            }
        }
        own
    }

    /// `acc[i] += w * x[i]` for `i < D`.
    #[inline(always)]
    fn axpy(self, acc: &mut [f32], w: f32, x: &[f32]) {
        for (a, &x) in acc[..self.d()].iter_mut().zip(x) {
            *a += w * x;
        }
    }

    /// [`Width::axpy`] for the backward pass's per-lane sums: when `D` is a whole number of
    /// vectors, one loop over the channels. (There the compiler vectorised `axpy`'s
    /// chunk-by-chunk form across the chunks at 64 channels, with scatters: the backward pass
    /// took three times as long. In the forward pass the chunks are faster.)
    #[inline(always)]
    fn axpy_backward(self, acc: &mut [f32], w: f32, x: &[f32]) {
        let d = self.d();
        if d.is_multiple_of(LANES) {
            for (a, &x) in acc[..d].iter_mut().zip(&x[..d]) {
                *a += w * x;
            }
        } else {
            self.axpy(acc, w, x);
        }
    }
}

/// `D` known at compile time.
#[derive(Clone, Copy)]
struct Fixed<const D: usize>;

impl<const D: usize> Width for Fixed<D> {
    /// On a cache line, so that the whole-vector stores of [`Width::axpy`] span one line each.
    type Acc = Aligned<[f32; D]>;

    #[inline(always)]
    fn d(self) -> usize {
        D
    }

    #[inline(always)]
    fn zeros(self) -> Aligned<[f32; D]> {
        Aligned([0.0; D])
    }

    #[inline(always)]
    fn dots(self, v_0: &[f32], v_1: &[f32], col: &[f32]) -> [[f32; LANES]; 2] {
        let v_0: &[[f32; LANES]; D] = v_0.as_chunks().0.try_into().expect("D channels");
        let v_1: &[[f32; LANES]; D] = v_1.as_chunks().0.try_into().expect("D channels");
        let col: &[f32; D] = col.try_into().expect("D channels");
        let mut own = [[0f32; LANES]; 2];
        for c in 0..D {
            for l in 0..LANES {
                own[0][l] += v_0[c][l] * col[c];
                own[1][l] += v_1[c][l] * col[c];
            }
        }
        own
    }

    #[inline(always)]
    fn dots4(self, v: [&[f32]; 4], col: &[f32]) -> [[f32; LANES]; 4] {
        let [v_0, v_1, v_2, v_3] = v;
        let v_0: &[[f32; LANES]; D] = v_0.as_chunks().0.try_into().expect("D channels");
        let v_1: &[[f32; LANES]; D] = v_1.as_chunks().0.try_into().expect("D channels");
        let v_2: &[[f32; LANES]; D] = v_2.as_chunks().0.try_into().expect("D channels");
        let v_3: &[[f32; LANES]; D] = v_3.as_chunks().0.try_into().expect("D channels");
        let col: &[f32; D] = col.try_into().expect("D channels");
        let mut own = [[0f32; LANES]; 4];
        for c in 0..D {
            for l in 0..LANES {
                own[0][l] += v_0[c][l] * col[c];
                own[1][l] += v_1[c][l] * col[c];
                own[2][l] += v_2[c][l] * col[c];
                own[3][l] += v_3[c][l] * col[c];
            }
        }
        own
    }

    #[inline(always)]
    fn axpy(self, acc: &mut [f32], w: f32, x: &[f32]) {
        let acc: &mut [f32; D] = (&mut acc[..D]).try_into().expect("D accumulators");
        let x: &[f32; D] = x[..D].try_into().expect("D channels");
        let (acc_chunks, acc_tail) = acc.as_chunks_mut::<LANES>();
        let (x_chunks, x_tail) = x.as_chunks::<LANES>();
        for (a, x) in acc_chunks.iter_mut().zip(x_chunks) {
            // Whole-array loads and stores: one vector operation per step.
            let (mut sum, x) = (*a, *x);
            for i in 0..LANES {
                sum[i] += w * x[i];
            }
            *a = sum;
        }
        for (a, &x) in acc_tail.iter_mut().zip(x_tail) {
            *a += w * x;
        }
    }
}

/// Any `D`.
#[derive(Clone, Copy)]
struct Any(usize);

impl Width for Any {
    type Acc = Vec<f32>;

    #[inline(always)]
    fn d(self) -> usize {
        self.0
    }

    fn zeros(self) -> Vec<f32> {
        vec![0.0; self.0]
    }
}

/// Calls `$body` with `$w` bound to the [`Width`] of `$d`: a constant for each count listed
/// (e.g. 3 for colour, 32 for features, 35 for both), [`Any`] otherwise.
macro_rules! with_width {
    ($d:expr, [$($n:literal),*], |$w:ident| $body:expr) => {
        match $d {
            $($n => {
                let $w = Fixed::<$n>;
                $body
            })*
            d => {
                let $w = Any(d);
                $body
            }
        }
    };
}

/// Gaussians ahead in a tile list whose data is prefetched: far enough to hide a memory
/// access behind the work of the Gaussians between.
const PREFETCH_AHEAD: usize = 8;

/// A Gaussian as the lane kernels read it: packed, with its depth and the image rows it can
/// reach.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LaneSplat {
    s: Splat<f32>,
    depth: f32,
    /// Image rows `rows.0..rows.1`; outside them the Gaussian is certainly skipped.
    rows: (u32, u32),
}

/// Every Gaussian of `splats` packed for an image of `height` rows, computed once per pass.
///
/// The Gaussians first (each one's alpha cut takes a logarithm), then their rows in blocks, as
/// vector code for the instruction set `pulp` picks at run time ([`reach_rows`] has no
/// branches; its `f64` operations are the same in every lane, so are its results).
pub(crate) fn pack(splats: &Splats<f32>, height: u32) -> Vec<LaneSplat> {
    let mut packed: Vec<LaneSplat> = (0..splats.len())
        .into_par_iter()
        .map(|g| LaneSplat {
            s: splats.splat(g),
            depth: splats.depths[g],
            rows: (0, 0),
        })
        .collect();
    packed
        .par_chunks_mut(PACK_BLOCK)
        .for_each(|block| base::isa::dispatch(ReachRows { block, height }));
    packed
}

/// Gaussians per parallel work item of [`pack`]'s rows.
const PACK_BLOCK: usize = 4096;

/// [`reach_rows`] of a block of packed Gaussians.
struct ReachRows<'a> {
    block: &'a mut [LaneSplat],
    height: u32,
}

impl pulp::WithSimd for ReachRows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        for ls in self.block.iter_mut() {
            ls.rows = reach_rows(&ls.s, self.height);
        }
    }
}

/// The tile rows (bits, relative to the tile's first row `y0`) of the image rows `rows` that
/// lie in `y0..y1`.
#[inline(always)]
fn row_mask(rows: (u32, u32), y0: u32, y1: u32) -> Mask {
    let lo = rows.0.clamp(y0, y1) - y0;
    let hi = rows.1.clamp(y0, y1) - y0;
    // hi <= 16: shifts below 32.
    ((1 << hi) - 1) & !((1 << lo) - 1)
}

/// The state a row of a Gaussian leaves in the backward pass's front-to-back walk.
///
/// Its two vectors first, each on a cache line of its own: a vector load across two lines costs
/// about two loads on some processors.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct RowBlend {
    /// Transmittance in front of the Gaussian.
    trans: [f32; LANES],
    falloff: [f32; LANES],
    /// Position in the tile list.
    k: u32,
    /// Tile row.
    row: u32,
    /// Lanes that blend the Gaussian.
    blend: Mask,
}

/// A value on cache-line boundaries: the per-row vectors of a tile (`Aligned<[[f32; LANES];
/// LANES]>`) each on a line of their own.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Aligned<T>(T);

impl<T> std::ops::Deref for Aligned<T> {
    type Target = T;
    #[inline(always)]
    fn deref(&self) -> &T {
        &self.0
    }
}

impl<const D: usize> AsRef<[f32]> for Aligned<[f32; D]> {
    fn as_ref(&self) -> &[f32] {
        &self.0
    }
}

impl<const D: usize> AsMut<[f32]> for Aligned<[f32; D]> {
    fn as_mut(&mut self) -> &mut [f32] {
        &mut self.0
    }
}

impl<T> std::ops::DerefMut for Aligned<T> {
    #[inline(always)]
    fn deref_mut(&mut self) -> &mut T {
        &mut self.0
    }
}

/// A (Gaussian, tile row) the forward pass blended: its position in the tile list, the row and
/// the lanes that blend it, in the walk's order. Kept for the backward pass ([`Kept`]) as
/// [`KeptRows`], which then replays these rows instead of walking the tile again.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct RowRef {
    k: u32,
    row: u16,
    blend: u16,
}

/// A tile's blended rows ([`RowRef`]), in the walk's order, in one 32-bit word each: the lanes
/// in bits 0 to 15, the tile row in bits 16 to 19, and in bits 20 to 31 the step from the
/// previous row's list position (from 0 before the first row). The walk takes the list front to
/// back, so the steps are never negative; a step of [`KeptRows::ESCAPE`] or more is written as
/// `ESCAPE` followed by a word holding the position itself.
///
/// Half the bytes of a [`RowRef`]: the benchmark's frame of a million Gaussians at 800x800 keeps
/// 38.6 MB of these words, which at 8 bytes a row passed the 64 MiB budget of kept rows
/// ([`crate::tiles::ROW_LIST_BUDGET_BYTES`]), so that its last tiles were walked again and its
/// records kept per intersection.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct KeptRows {
    words: Vec<u32>,
    /// The position of the last row pushed.
    last: u32,
}

impl KeptRows {
    /// The step field's escape value, and the largest step it cannot hold.
    const ESCAPE: u32 = (1 << 12) - 1;

    /// No rows, keeping the buffer.
    pub fn clear(&mut self) {
        self.words.clear();
        self.last = 0;
    }

    /// Appends the row `row` (below 16) of list position `k` (no smaller than the last row's),
    /// blended by the lanes `blend`.
    #[inline(always)]
    pub fn push(&mut self, k: u32, row: u32, blend: u32) {
        debug_assert!(k >= self.last && row < 16 && blend <= 0xffff);
        let step = k - self.last;
        let head = blend | row << 16;
        if step < Self::ESCAPE {
            self.words.push(head | step << 20);
        } else {
            self.words.extend([head | Self::ESCAPE << 20, k]);
        }
        self.last = k;
    }

    /// The bytes its words take.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.words.as_slice())
    }

    /// At least the number of rows (the words: one per row, two for an escaped step).
    pub fn len_bound(&self) -> usize {
        self.words.len()
    }

    /// The rows, in the order they were pushed.
    pub fn iter(&self) -> KeptRowsIter<'_> {
        KeptRowsIter {
            words: self.words.iter(),
            k: 0,
        }
    }
}

/// The rows of a [`KeptRows`], decoded.
#[derive(Clone)]
pub(crate) struct KeptRowsIter<'a> {
    words: std::slice::Iter<'a, u32>,
    k: u32,
}

impl Iterator for KeptRowsIter<'_> {
    type Item = RowRef;

    #[inline(always)]
    fn next(&mut self) -> Option<RowRef> {
        let w = *self.words.next()?;
        let step = w >> 20;
        self.k = if step == KeptRows::ESCAPE {
            // An escape is always followed by its position: `push` writes both words.
            *self.words.next().unwrap_or(&self.k)
        } else {
            self.k + step
        };
        Some(RowRef {
            k: self.k,
            row: (w >> 16 & 0xf) as u16,
            blend: w as u16,
        })
    }
}

/// The Gaussians that `rows` (a tile's kept rows, in the walk's order) blend, in the order of
/// the tile list `ids` (which the rows' positions index): a Gaussian's rows are consecutive in
/// the walk, and the walk takes the list front to back.
///
/// Without a branch on the data: each row's Gaussian is written at the end of the result, which
/// grows only where the row's position differs from the previous row's (`docs/performance.md`,
/// "The SH gradients written once, and the blending positions without a branch"). The result
/// holds at most one entry per list position, so its buffer is the list's length plus the one
/// slot that a row of the last Gaussian writes past the end, not one per row.
pub(crate) fn blending_ids(rows: &KeptRows, ids: &[u32]) -> Vec<u32> {
    // At least one word per row.
    let bound = rows.len_bound();
    let mut rows = rows.iter();
    let Some(first) = rows.next() else {
        return Vec::new();
    };
    let mut out = vec![0u32; bound.min(ids.len() + 1)];
    let (mut len, mut last) = (1, first.k);
    out[0] = ids[last as usize];
    for r in rows {
        // `len` is the number of distinct positions before `r`: at most the index of `r` among
        // the rows, and at most the list's length.
        out[len] = ids[r.k as usize];
        len += usize::from(r.k != last);
        last = r.k;
    }
    out.truncate(len);
    out
}

/// What a lane forward pass keeps in its bins for the backward pass of the same Gaussians:
/// every Gaussian packed, and per tile the rows it blended ([`KeptRows`]), for the tiles whose
/// lists fit the budget.
#[derive(Debug, Default)]
pub(crate) struct Kept {
    pub packed: Vec<LaneSplat>,
    pub blends: Vec<Option<KeptRows>>,
}

impl Kept {
    /// Whether these were kept for `splats`: the same count and, bit for bit, the same means,
    /// conics, opacities and depths, which are all that packing and the blend decisions read
    /// (with the image height, fixed by the bins).
    pub fn matches(&self, splats: &Splats<f32>) -> bool {
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits();
        self.packed.len() == splats.len()
            && self.packed.par_iter().enumerate().all(|(g, ls)| {
                let ([mx, my], [a, b, c]) = (splats.means2d[g], splats.conics[g]);
                let s = &ls.s;
                same(s.mx, mx)
                    && same(s.my, my)
                    && same(s.a, a)
                    && same(s.b, b)
                    && same(s.c, c)
                    && same(s.opacity, splats.opacities[g])
                    && same(ls.depth, splats.depths[g])
            })
    }
}

/// Per-thread working memory.
#[derive(Default)]
pub(crate) struct Scratch {
    /// Forward: the tile's channel accumulators: per tile row and channel a vector of the row's
    /// pixels (`[(r * D + c) * LANES + l]`) when `D <= CHANNEL_MAJOR_MAX`, else `line_padded(D)`
    /// per pixel.
    acc: Vec<f32>,
    /// Backward: the rows blended, in the front-to-back walk's order.
    blended: Vec<RowBlend>,
    /// Backward: the tile's kept rows, decoded.
    decoded: Vec<RowRef>,
    /// Backward: where each Gaussian's rows start in `blended`, then `blended.len()`.
    starts: Vec<usize>,
    /// Backward: the tile's image cotangents, channel-major per row: `[(r * D + c) * LANES + l]`.
    v_image_t: Vec<f32>,
    /// Backward, when `D <= COLUMN_CHANNELS_MAX`: a Gaussian's channel gradients per tile
    /// column, `[c * LANES + l]`, zero between Gaussians.
    columns: Vec<f32>,
}

/// Whether lane `l` is in `m`.
#[inline(always)]
fn has(m: Mask, l: usize) -> bool {
    m >> l & 1 != 0
}

/// Calls `f` with each set bit of `m`, ascending.
#[inline(always)]
fn for_each_bit(mut m: Mask, mut f: impl FnMut(usize)) {
    while m != 0 {
        f(m.trailing_zeros() as usize);
        m &= m - 1;
    }
}

/// Evaluates `s` at the pixel centres `cx` of the row with centre `cy`: the scalar loops'
/// `evaluate`, lane by lane, for the lanes of `lanes`. Writes every lane's falloff and alpha and
/// returns the lanes where the Gaussian is not skipped: [`row_sigma`], then (unless no lane
/// passes its test and `EVERY_ROW` is off) [`row_falloff`].
#[inline(always)]
fn evaluate_row<const EVERY_ROW: bool, I: LaneIsa>(
    isa: I,
    s: &Splat<f32>,
    lanes: Mask,
    cx: &[f32; LANES],
    cy: f32,
    falloff: &mut [f32; LANES],
    alpha: &mut [f32; LANES],
) -> Mask {
    let mut sigma = [0f32; LANES];
    let hit = row_sigma(isa, s, lanes, cx, cy, &mut sigma);
    if !EVERY_ROW && hit == 0 {
        return 0;
    }
    hit & row_falloff(isa, s, &sigma, falloff, alpha)
}

/// The first half of [`evaluate_row`]: every lane's `sigma` (the exponent of the falloff), and
/// the lanes of `lanes` whose `sigma` passes the skip test.
///
/// The skip test is the scalar loops' negated: `!(sigma.is_nan() || sigma < 0 || sigma > cut)`
/// is `0 <= sigma && sigma <= cut`, as ordered comparisons are false on NaN.
#[inline(always)]
fn row_sigma<I: LaneIsa>(
    isa: I,
    s: &Splat<f32>,
    lanes: Mask,
    cx: &[f32; LANES],
    cy: f32,
    sigma: &mut [f32; LANES],
) -> Mask {
    let dy = s.my - cy;
    let c_dy2 = s.c * (dy * dy);
    for l in 0..LANES {
        let dx = s.mx - cx[l];
        sigma[l] = 0.5 * (s.a * (dx * dx) + c_dy2) + s.b * dx * dy;
    }
    isa.le(&[0.0; LANES], sigma) & isa.le(sigma, &[s.sigma_cut; LANES]) & lanes
}

/// The second half of [`evaluate_row`]: every lane's falloff and alpha from its `sigma`, and
/// the lanes whose alpha passes the skip test (`!(alpha.is_nan() || alpha < ALPHA_MIN)` is
/// `ALPHA_MIN <= alpha`). The exponential is evaluated on every lane, so no branch depends on
/// the data; outside the lanes whose `sigma` passes its test it is taken at `sigma` clamped to
/// `[0, cut]`, a value that is never used.
#[inline(always)]
fn row_falloff<I: LaneIsa>(
    isa: I,
    s: &Splat<f32>,
    sigma: &[f32; LANES],
    falloff: &mut [f32; LANES],
    alpha: &mut [f32; LANES],
) -> Mask {
    // The exponential of `-sigma` clamped to `[0, cut]`: in the lanes that pass the test that
    // is `-sigma` itself (`-0.0` becomes `+0.0`, whose exponential is the same 1). The other
    // lanes' values are never used; clamped, they cannot be subnormal (far from the centre
    // `exp(-sigma)` is, which makes every vector instruction that touches it, here and in the
    // blend and gradient arithmetic of the row, take a slow microcode path on some
    // processors): the falloff is at least `exp(-cut)`, so for a positive opacity the alpha is
    // about `ALPHA_MIN` or more. Clamping rather than selecting by the test's lanes keeps the
    // mask operations off the exponential's long dependency chain.
    // With a cut in `[-EXP_F32_HIGH, -EXP_F32_LOW]` every argument lies in the range where
    // `exp_f32_in_range` gives `exp_f32`'s bits, without its range handling on the chain.
    // Plain loops: `array::from_fn` with this body is not always inlined, and out of line it
    // runs without the instruction set's features.
    if (-EXP_F32_HIGH..=-EXP_F32_LOW).contains(&s.sigma_cut) {
        for l in 0..LANES {
            let x = if sigma[l] > 0.0 { sigma[l] } else { 0.0 };
            let x = if x < s.sigma_cut { x } else { s.sigma_cut };
            falloff[l] = exp_f32_in_range(-x);
        }
    } else {
        for l in 0..LANES {
            let x = if sigma[l] > 0.0 { sigma[l] } else { 0.0 };
            let x = if x < s.sigma_cut { x } else { s.sigma_cut };
            falloff[l] = exp_f32(-x);
        }
    }
    (*alpha, _) = alphas(isa, s.opacity, falloff);
    isa.le(&[ALPHA_MIN as f32; LANES], alpha)
}

/// `min(ALPHA_MAX, opacity falloff)` of every lane as the scalar loops compute it
/// (`if raw > ALPHA_MAX { ALPHA_MAX } else { raw }`), and the lanes where the clamp is active:
/// no gradient flows through alpha there.
#[inline(always)]
fn alphas<I: LaneIsa>(isa: I, opacity: f32, falloff: &[f32; LANES]) -> ([f32; LANES], Mask) {
    let alpha_max = [ALPHA_MAX as f32; LANES];
    let raw: [f32; LANES] = std::array::from_fn(|l| opacity * falloff[l]);
    let clamped = isa.lt(&alpha_max, &raw);
    (isa.select(clamped, &alpha_max, &raw), clamped)
}

/// Applies the transmittance stop to a row: live lanes of `hit` whose transmittance would fall
/// to the threshold stop (they leave `live` and do not blend). Returns the blending lanes and
/// the transmittances in front of the Gaussian, and moves `trans` behind it.
#[inline(always)]
fn advance<I: LaneIsa>(
    isa: I,
    hit: Mask,
    alpha: &[f32; LANES],
    trans: &mut [f32; LANES],
    live: &mut Mask,
) -> (Mask, [f32; LANES]) {
    let front = *trans;
    let next: [f32; LANES] = std::array::from_fn(|l| trans[l] * (1.0 - alpha[l]));
    let hit = hit & *live;
    let stop = hit & isa.le(&next, &[TRANSMITTANCE_MIN as f32; LANES]);
    *live &= !stop;
    let blend = hit & !stop;
    *trans = isa.select(blend, &next, trans);
    (blend, front)
}

/// The pixel state of a tile during the front-to-back walk.
struct Walk {
    /// Per tile row, the lanes that have not stopped (and lie inside the image).
    live: [Mask; LANES],
    /// The rows with a live lane.
    live_rows: Mask,
    trans: Aligned<[[f32; LANES]; LANES]>,
}

impl Walk {
    /// Every pixel of a `width x height` tile live at unit transmittance.
    fn new(width: usize, height: usize) -> Walk {
        let inside = (1 << width) - 1;
        Walk {
            live: std::array::from_fn(|r| if r < height { inside } else { 0 }),
            live_rows: (1 << height) - 1,
            trans: Aligned([[1.0; LANES]; LANES]),
        }
    }

    /// Walks the tile's Gaussians front to back, calling `blend(k, g, row, lanes, alpha,
    /// falloff, front)` for each Gaussian (position `k` in the tile list, id `g`) and tile row
    /// where some lane blends it, with the transmittances in front of it. Stops when every
    /// pixel has stopped. `channels` (`D` per Gaussian) is only prefetched.
    ///
    /// With `EVERY_ROW` (the forward pass), every row a Gaussian reaches is evaluated first:
    /// the `sigma` of every row, then the exponential of the rows some lane of which passes
    /// the `sigma` test, with no branch on the data within a row: the rows are independent, so
    /// their long dependency chains overlap; then the transmittance stop runs row by row.
    /// Without it (the backward pass), each row is evaluated and stopped in turn, and a row no
    /// lane of which is hit skips its exponential. Each pixel sees the scalar loops' operations
    /// in their order either way. Measured with one thread on 100k Gaussians at 256x256, in
    /// alternating runs: evaluating every row first (exponentials included) takes 0.78 (3
    /// channels) and 0.84 (35 channels) of the forward pass's time, but makes the backward
    /// pass's first walk (which keeps every blended row) slower; leaving out the exponentials
    /// of the rows no lane reaches took another 10 % (3 channels) and 7 % (35 channels) off
    /// the forward pass on two threads.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn run<const EVERY_ROW: bool, I: LaneIsa>(
        &mut self,
        isa: I,
        packed: &[LaneSplat],
        channels: &[f32],
        d: usize,
        tile: Tile<'_>,
        mut blend: impl FnMut(usize, usize, usize, Mask, &[f32; LANES], &[f32; LANES], &[f32; LANES]),
    ) {
        let (x0, y0, _, y1) = tile.pixel_rect;
        let cx: [f32; LANES] = std::array::from_fn(|l| pixel_centre::<f32>(x0 + l as u32));
        let cy: [f32; LANES] = std::array::from_fn(|r| pixel_centre::<f32>(y0 + r as u32));
        let ids = tile.ids;
        // Per row of the current Gaussian, its evaluation (`EVERY_ROW`; otherwise only the
        // first row is used, for the row being evaluated). Every entry read was written for the
        // same Gaussian first: a row's sigma, falloff and alpha are read only when its hit (after
        // the sigma test) is not empty, and its hit only when the row is in that Gaussian's rows.
        let mut sigma = Aligned([[0f32; LANES]; LANES]);
        let mut falloff = Aligned([[0f32; LANES]; LANES]);
        let mut alpha = Aligned([[0f32; LANES]; LANES]);
        let mut hit = [0 as Mask; LANES];
        for (k, &g) in ids.iter().enumerate() {
            if let Some(&ahead) = ids.get(k + PREFETCH_AHEAD) {
                let ahead = ahead as usize;
                prefetch(std::slice::from_ref(&packed[ahead]));
                prefetch(&channels[ahead * d..(ahead + 1) * d]);
            }
            let ls = &packed[g as usize];
            let rows = row_mask(ls.rows, y0, y1) & self.live_rows;
            // The transmittance stop of row `r`, then the blend.
            macro_rules! step {
                ($r:expr, $hit:expr, $alpha:expr, $falloff:expr) => {{
                    let r = $r;
                    let (lanes, front) =
                        advance(isa, $hit, $alpha, &mut self.trans[r], &mut self.live[r]);
                    if self.live[r] == 0 {
                        self.live_rows &= !(1 << r);
                    }
                    if lanes != 0 {
                        blend(k, g as usize, r, lanes, $alpha, $falloff, &front);
                    }
                }};
            }
            if EVERY_ROW {
                // The rows some lane of which passes the `sigma` test; only they take the
                // exponential (the other rows' hits are empty either way).
                let mut tested: Mask = 0;
                for_each_bit(rows, |r| {
                    hit[r] = row_sigma(isa, &ls.s, self.live[r], &cx, cy[r], &mut sigma[r]);
                    tested |= ((hit[r] != 0) as Mask) << r;
                });
                for_each_bit(tested, |r| {
                    hit[r] &= row_falloff(isa, &ls.s, &sigma[r], &mut falloff[r], &mut alpha[r]);
                });
                for_each_bit(tested, |r| {
                    if hit[r] != 0 {
                        step!(r, hit[r], &alpha[r], &falloff[r]);
                    }
                });
            } else {
                for_each_bit(rows, |r| {
                    let (falloff, alpha) = (&mut falloff[0], &mut alpha[0]);
                    let hit = evaluate_row::<false, I>(
                        isa,
                        &ls.s,
                        self.live[r],
                        &cx,
                        cy[r],
                        falloff,
                        alpha,
                    );
                    if hit != 0 {
                        step!(r, hit, alpha, falloff);
                    }
                });
            }
            if self.live_rows == 0 {
                break;
            }
        }
    }
}

/// Replays the rows a forward pass kept for a tile (first pixel `(x0, y0)`, Gaussian ids `ids`):
/// pushes each row's [`RowBlend`] onto `blended` and returns every pixel's final transmittance.
///
/// Each row is evaluated as [`evaluate_row`] evaluates it in the walk, and the transmittance of
/// its blending lanes moves as [`advance`] moves it, in the walk's order; the lanes that do not
/// blend keep theirs. So the transmittances, falloffs and lanes are the walk's, bit for bit,
/// without evaluating the rows and Gaussians that blend nowhere.
#[inline(always)]
fn replay<I: LaneIsa>(
    isa: I,
    packed: &[LaneSplat],
    ids: &[u32],
    x0: u32,
    y0: u32,
    rows: &[RowRef],
    blended: &mut Vec<RowBlend>,
) -> Aligned<[[f32; LANES]; LANES]> {
    let cx: [f32; LANES] = std::array::from_fn(|l| pixel_centre::<f32>(x0 + l as u32));
    let mut trans = Aligned([[1f32; LANES]; LANES]);
    let mut falloff = [0f32; LANES];
    let mut alpha = [0f32; LANES];
    // One row each: no reallocation (and copy) while pushing, nor of what the buffer held.
    base::memory::clear_with_capacity(blended, rows.len());
    for (i, rr) in rows.iter().enumerate() {
        if let Some(ahead) = rows.get(i + PREFETCH_AHEAD) {
            prefetch(std::slice::from_ref(
                &packed[ids[ahead.k as usize] as usize],
            ));
        }
        let r = rr.row as usize;
        let s = &packed[ids[rr.k as usize] as usize].s;
        let cy = pixel_centre::<f32>(y0 + r as u32);
        let blend = rr.blend as Mask;
        evaluate_row::<true, I>(isa, s, blend, &cx, cy, &mut falloff, &mut alpha);
        let front = trans[r];
        let mut next = [0f32; LANES];
        for l in 0..LANES {
            next[l] = front[l] * (1.0 - alpha[l]);
        }
        trans[r] = isa.select(blend, &next, &front);
        blended.push(RowBlend {
            k: rr.k,
            row: r as u32,
            blend,
            trans: front,
            falloff,
        });
    }
    trans
}

/// `f32`s in a cache line.
const LINE_FLOATS: usize = 16;

/// `D` rounded up to whole cache lines: the stride of the forward pass's per-pixel accumulators.
fn line_padded(d: usize) -> usize {
    d.div_ceil(LINE_FLOATS).max(1) * LINE_FLOATS
}

/// `len` zeros in `buf`, starting on a cache line: `buf` is cleared and refilled with room to
/// spare, and the returned window starts at its first element on a line boundary.
fn zeroed_on_lines(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    buf.clear();
    buf.resize(len + LINE_FLOATS, 0.0);
    // An f32 address is a multiple of 4, so at most 15 elements precede a 64-byte boundary;
    // `min` only guards the documented "cannot align" answer, which leaves the window unaligned
    // but correct.
    let start = buf
        .as_ptr()
        .align_offset(LINE_FLOATS * std::mem::size_of::<f32>())
        .min(LINE_FLOATS);
    &mut buf[start..start + len]
}

/// The most channels for which the forward pass accumulates a blended row channel by channel,
/// all lanes at once (`D` vector operations per row, whatever the number of lanes that blend);
/// above it, pixel by pixel across channels (per blended lane, `D / LANES` vector operations).
/// Measured on 100k Gaussians at 256x256 (about 3.3 blending lanes per row): channel-major is
/// faster at 3 and 8 channels, no faster at 16 and slower at 35.
const CHANNEL_MAJOR_MAX: usize = LANES / 2;

/// The forward pass over one tile (see [`super::scalar::forward_tile`]).
pub(crate) struct ForwardTile<'a, 'b> {
    pub splats: &'a Splats<'a, f32>,
    /// Every Gaussian packed ([`pack`]).
    pub packed: &'a [LaneSplat],
    pub tile: Tile<'a>,
    pub background: &'a [f32],
    pub scratch: &'b mut Scratch,
    pub out: TileOut<'b, f32>,
    /// Receives the rows the tile blends, for the backward pass (when given).
    pub keep: Option<&'b mut KeptRows>,
}

impl LaneOp for ForwardTile<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<I: LaneIsa>(self, isa: I) {
        with_width!(self.splats.channel_count, [3, 32, 35, 64], |w| {
            self.forward(isa, w)
        })
    }
}

impl ForwardTile<'_, '_> {
    #[inline(always)]
    fn forward<I: LaneIsa, W: Width>(self, isa: I, wd: W) {
        let ForwardTile {
            splats,
            packed,
            tile,
            background,
            scratch,
            out,
            mut keep,
        } = self;
        let d = wd.d();
        let dp = line_padded(d);
        let channel_major = d <= CHANNEL_MAJOR_MAX;
        let (x0, y0, x1, y1) = tile.pixel_rect;
        let (width, height) = ((x1 - x0) as usize, (y1 - y0) as usize);
        // Each pixel's accumulator starts on a cache line (`dp` is a whole number of lines), so
        // that no vector store of the channel loop spans two lines.
        let acc = zeroed_on_lines(&mut scratch.acc, LANES * LANES * dp);
        let mut z = Aligned([[0f32; LANES]; LANES]);
        let mut n = [[0u32; LANES]; LANES];
        let mut walk = Walk::new(width, height);
        walk.run::<true, I>(
            isa,
            packed,
            splats.channels,
            d,
            tile,
            |k, g, r, lanes, alpha, _, front| {
                if let Some(keep) = keep.as_deref_mut() {
                    // k < 2^32 (bins hold u32 ids), r < 16 and lanes < 2^16.
                    keep.push(k as u32, r as u32, lanes);
                }
                let depth = packed[g].depth;
                let col = splats.channels_of(g);
                let w: [f32; LANES] = std::array::from_fn(|l| alpha[l] * front[l]);
                let z_next: [f32; LANES] = std::array::from_fn(|l| z[r][l] + w[l] * depth);
                z[r] = isa.select(lanes, &z_next, &z[r]);
                for (l, n) in n[r].iter_mut().enumerate() {
                    *n += (lanes >> l) & 1;
                }
                if channel_major {
                    // Every lane at once, each channel a vector; lanes that do not blend keep
                    // their sums.
                    let row = &mut acc[r * d * LANES..(r + 1) * d * LANES];
                    for (a, &c) in row.as_chunks_mut::<LANES>().0.iter_mut().zip(col) {
                        let next: [f32; LANES] = std::array::from_fn(|l| a[l] + w[l] * c);
                        *a = isa.select(lanes, &next, a);
                    }
                } else {
                    for_each_bit(lanes, |l| {
                        let p = r * LANES + l;
                        wd.axpy(&mut acc[p * dp..(p + 1) * dp], w[l], col);
                    });
                }
            },
        );
        for r in 0..height {
            for l in 0..width {
                let p = r * LANES + l;
                let trans = walk.trans[r][l];
                let pixel = &mut out.image[p * d..(p + 1) * d];
                for (c, (o, &b)) in pixel.iter_mut().zip(background).enumerate() {
                    let a = if channel_major {
                        acc[(r * d + c) * LANES + l]
                    } else {
                        acc[p * dp + c]
                    };
                    *o = a + trans * b;
                }
                out.alpha[p] = 1.0 - trans;
                out.depth[p] = z[r][l];
                out.count[p] = n[r][l];
            }
        }
    }
}

/// The backward pass over one tile (see [`super::scalar::backward_tile`]).
pub(crate) struct BackwardTile<'a, 'b> {
    pub splats: &'a Splats<'a, f32>,
    /// Every Gaussian packed ([`pack`]).
    pub packed: &'a [LaneSplat],
    pub tile: Tile<'a>,
    pub background: &'a [f32],
    pub cot: &'a Cotangents<'a, f32>,
    pub scratch: &'b mut Scratch,
    /// Not yet written: one record per tile list entry, or, with `compact`, per Gaussian that
    /// blends in the tile. The pass initialises all of it.
    pub rec: &'b mut [MaybeUninit<f32>],
    pub bg_grad: &'b mut [f32],
    /// The rows the forward pass of the same Gaussians blended in this tile, when it kept them.
    pub kept: Option<&'a KeptRows>,
    /// Whether `rec` holds records only for the Gaussians `kept` blends, in list order
    /// ([`blending_ids`]); otherwise one per tile list entry.
    pub compact: bool,
}

impl LaneOp for BackwardTile<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<I: LaneIsa>(self, isa: I) {
        with_width!(self.splats.channel_count, [3, 32, 35, 64], |w| {
            self.backward(isa, w)
        })
    }
}

impl BackwardTile<'_, '_> {
    #[inline(always)]
    fn backward<I: LaneIsa, W: Width>(self, isa: I, wd: W) {
        let BackwardTile {
            splats,
            packed,
            tile,
            background,
            cot,
            scratch,
            rec,
            bg_grad,
            kept,
            compact,
        } = self;
        let d = wd.d();
        let stride = GEOMETRY + d;
        let ids = tile.ids;
        let Scratch {
            blended,
            decoded,
            starts,
            v_image_t,
            columns,
            ..
        } = scratch;
        let by_column = d <= COLUMN_CHANNELS_MAX;
        let columns = zeroed_on_lines(columns, if by_column { d * LANES } else { 0 });
        let (x0, y0, x1, y1) = tile.pixel_rect;
        let (width, height) = ((x1 - x0) as usize, (y1 - y0) as usize);
        let image_width = tile.image_width as usize;
        let pixel = |r: usize, l: usize| (y0 as usize + r) * image_width + x0 as usize + l;

        // Front to back: the forward pass's decisions and transmittances, replayed from the
        // rows it kept, or found by walking the tile again.
        blended.clear();
        let final_trans = match kept {
            Some(kept) => {
                // Decoded once into the thread's buffer (a tile's rows, in cache), so that the
                // replay can look ahead for its prefetches.
                decoded.clear();
                decoded.extend(kept.iter());
                replay(isa, packed, ids, x0, y0, decoded, blended)
            }
            None => {
                let mut walk = Walk::new(width, height);
                walk.run::<false, I>(
                    isa,
                    packed,
                    splats.channels,
                    d,
                    tile,
                    |k, _, r, lanes, _, falloff, front| {
                        blended.push(RowBlend {
                            k: k as u32,
                            row: r as u32,
                            blend: lanes,
                            trans: *front,
                            falloff: *falloff,
                        })
                    },
                );
                walk.trans
            }
        };

        // The tile's cotangents, and what each pixel shows behind its last Gaussian.
        // On cache lines: each row's channel vectors are whole lines.
        let v_image_t = zeroed_on_lines(v_image_t, LANES * d * LANES);
        let mut v_alpha = Aligned([[0f32; LANES]; LANES]);
        let mut v_depth = Aligned([[0f32; LANES]; LANES]);
        let mut behind = Aligned([[0f32; LANES]; LANES]);
        for r in 0..height {
            for l in 0..width {
                let p = pixel(r, l);
                let v = &cot.image[p * d..(p + 1) * d];
                for (c, &vc) in v.iter().enumerate() {
                    v_image_t[(r * d + c) * LANES + l] = vc;
                }
                v_alpha[r][l] = cot.alpha.map_or(0.0, |a| a[p]);
                v_depth[r][l] = cot.depth.map_or(0.0, |z| z[p]);
                let trans = final_trans[r][l];
                for (b, &vc) in bg_grad.iter_mut().zip(v) {
                    *b += trans * vc;
                }
                behind[r][l] = dot(v, background);
            }
        }

        // Where each Gaussian's rows start (a Gaussian's rows are consecutive in the walk),
        // found without a branch on the data: each row writes its index at the current count,
        // and only a Gaussian's first row advances the count.
        starts.clear();
        starts.resize(blended.len() + 1, 0);
        let mut groups = 0;
        let mut previous = u32::MAX;
        for (i, b) in blended.iter().enumerate() {
            starts[groups] = i;
            groups += (b.k != previous) as usize;
            previous = b.k;
        }
        starts[groups] = blended.len();
        if compact {
            // The forward pass kept this tile's rows, and its blending Gaussians (`blending_ids`,
            // which gave `rec` its length) are the groups of those rows: each group writes its
            // record below, so every record is written once.
            assert_eq!(
                groups * stride,
                rec.len(),
                "one compact record per blending Gaussian"
            );
        } else {
            // Records of the list entries that blend nowhere stay zero.
            fill_uninit(rec, 0.0);
        }

        // Back to front, one Gaussian at a time; its rows in ascending order.
        let cx: [f32; LANES] = std::array::from_fn(|l| pixel_centre::<f32>(x0 + l as u32));
        // One channel accumulator for the tile, cleared per Gaussian: with `Any` width it is a
        // heap buffer, which per Gaussian would be an allocation per tile list entry.
        let mut grads = wd.zeros();
        for group in (0..groups).rev() {
            if let Some(ahead) = group.checked_sub(PREFETCH_AHEAD) {
                let g = ids[blended[starts[ahead]].k as usize] as usize;
                prefetch(&splats.channels[g * d..(g + 1) * d]);
            }
            let (start, end) = (starts[group], starts[group + 1]);
            let rows = &blended[start..end];
            let k = rows[0].k as usize;
            let g = ids[k] as usize;
            let s = &packed[g].s;
            let z = packed[g].depth;
            let col = &splats.channels_of(g)[..d];
            let block = |bl: &RowBlend| {
                let at = bl.row as usize * d * LANES;
                &v_image_t[at..at + d * LANES]
            };
            grads.as_mut().fill(0.0);
            let mut sums = [0f32; GEOMETRY];
            // The record's sums per tile column over the Gaussian's rows (top to bottom), all
            // lanes at once; folded into `sums` (and `grads`) column by column from the left
            // after its last row ([`super::record`]).
            let mut part = Aligned([[0f32; LANES]; GEOMETRY]);
            let mut cols: Mask = 0;
            // The rows up to four at a time, for `v_image . c` of their pixels: independent
            // sums (each lane sums its channels in order), two or four at once; a missing last
            // row is taken as the one before.
            for quad in rows.chunks(4) {
                let last = block(&quad[quad.len() - 1]);
                let mut owns = [[0f32; LANES]; 4];
                if quad.len() <= 2 {
                    let two = wd.dots(block(&quad[0]), last, col);
                    owns[..2].copy_from_slice(&two);
                } else {
                    owns = wd.dots4(
                        [block(&quad[0]), block(&quad[1]), block(&quad[2]), last],
                        col,
                    );
                }
                for (bl, own) in quad.iter().zip(&owns) {
                    let r = bl.row as usize;
                    let cy = pixel_centre::<f32>(y0 + bl.row);
                    let (alpha, clamped) = alphas(isa, s.opacity, &bl.falloff);
                    let dy = s.my - cy;
                    let mut w = [0f32; LANES];
                    let mut next = [0f32; LANES];
                    let mut geo = Aligned([[0f32; LANES]; GEOMETRY]);
                    for l in 0..LANES {
                        let (alpha, front) = (alpha[l], bl.trans[l]);
                        let dx = s.mx - cx[l];
                        let own_l = own[l] + v_depth[r][l] * z + v_alpha[r][l];
                        w[l] = alpha * front;
                        geo[DEPTH][l] = w[l] * v_depth[r][l];
                        let v_a = front * (own_l - behind[r][l]);
                        next[l] = alpha * own_l + (1.0 - alpha) * behind[r][l];
                        geo[OPACITY][l] = v_a * bl.falloff[l];
                        let v_sigma = -(v_a * alpha);
                        geo[CONIC_A][l] = v_sigma * 0.5 * dx * dx;
                        geo[CONIC_B][l] = v_sigma * dx * dy;
                        geo[CONIC_C][l] = v_sigma * 0.5 * dy * dy;
                        geo[MEAN_X][l] = v_sigma * (s.a * dx + s.b * dy);
                        geo[MEAN_Y][l] = v_sigma * (s.b * dx + s.c * dy);
                    }
                    behind[r] = isa.select(bl.blend, &next, &behind[r]);
                    cols |= bl.blend;
                    // No gradient flows through a clamped alpha: only the depth term there.
                    let free = bl.blend & !clamped;
                    for j in 0..GEOMETRY {
                        let m = if j == DEPTH { bl.blend } else { free };
                        let sum: [f32; LANES] = std::array::from_fn(|l| part[j][l] + geo[j][l]);
                        part[j] = isa.select(m, &sum, &part[j]);
                    }
                    if by_column {
                        let v = block(bl).as_chunks::<LANES>().0;
                        for (a, v) in columns.as_chunks_mut::<LANES>().0.iter_mut().zip(v) {
                            let sum: [f32; LANES] = std::array::from_fn(|l| a[l] + w[l] * v[l]);
                            *a = isa.select(bl.blend, &sum, a);
                        }
                    } else {
                        // Pixel by pixel in raster order.
                        for_each_bit(bl.blend, |l| {
                            let p = pixel(r, l);
                            let x = &cot.image[p * d..(p + 1) * d];
                            wd.axpy_backward(grads.as_mut(), w[l], x);
                        });
                    }
                }
            }
            for_each_bit(cols, |l| {
                for j in 0..GEOMETRY {
                    sums[j] += part[j][l];
                }
                if by_column {
                    for (c, g) in grads.as_mut().iter_mut().enumerate() {
                        *g += columns[c * LANES + l];
                    }
                }
            });
            columns.fill(0.0);
            // The records start at zero and each Gaussian's sums are complete: storing them
            // equals adding them. Compact records are the blending Gaussians' in list order,
            // which is the order of the groups.
            let slot = if compact { group } else { k };
            let record = &mut rec[slot * stride..(slot + 1) * stride];
            let (geometry, channels) = record.split_at_mut(GEOMETRY);
            for (r, &v) in geometry.iter_mut().zip(&sums) {
                r.write(v);
            }
            for (r, &v) in channels.iter_mut().zip(grads.as_ref()) {
                r.write(v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The Gaussians are those of the distinct `k` of the rows, in their order, each once
        /// per run of equal `k` (what a list that pushes every new `k` gives), for any run
        /// lengths, the list's last position included, and list entries anywhere in `u32`.
        #[test]
        fn blending_ids_list_each_run_of_rows_once(
            list in proptest::collection::vec(any::<u32>(), 1..40),
            runs in proptest::collection::vec((any::<u32>(), 1usize..5), 0..40),
        ) {
            // Distinct positions in ascending order, as the walk takes them.
            let mut positions: Vec<u32> =
                runs.iter().map(|&(k, _)| k % list.len() as u32).collect();
            positions.sort_unstable();
            positions.dedup();
            let rows: Vec<RowRef> = positions
                .iter()
                .zip(&runs)
                .flat_map(|(&k, &(_, n))| {
                    (0..n).map(move |i| RowRef { k, row: i as u16, blend: 1 })
                })
                .collect();
            let mut kept = KeptRows::default();
            for r in &rows {
                kept.push(r.k, r.row as u32, r.blend as u32);
            }
            let mut expected: Vec<u32> = Vec::new();
            let mut last = None;
            for r in &rows {
                if last != Some(r.k) {
                    expected.push(list[r.k as usize]);
                    last = Some(r.k);
                }
            }
            prop_assert_eq!(blending_ids(&kept, &list), expected);
        }

        /// Kept rows read back as pushed, for any steps between positions (those that need an
        /// escape word, up to the whole `u32` range, among them), rows and lanes; and after
        /// `clear`, the buffer holds only what is pushed next.
        #[test]
        fn kept_rows_read_back_as_pushed(
            steps in proptest::collection::vec(
                prop_oneof![0u32..3, 4090u32..4100, any::<u32>()],
                0..60,
            ),
            rows in proptest::collection::vec((0u16..16, any::<u16>()), 60),
            first in proptest::collection::vec((any::<u32>(), 0u16..16, any::<u16>()), 0..3),
        ) {
            let mut kept = KeptRows::default();
            for &(k, row, blend) in &first {
                kept.push(k.min(5), row as u32, blend as u32);
            }
            kept.clear();
            let mut k = 0u32;
            let pushed: Vec<RowRef> = steps
                .iter()
                .zip(&rows)
                .map_while(|(&step, &(row, blend))| {
                    k = k.checked_add(step)?;
                    Some(RowRef { k, row, blend })
                })
                .collect();
            for r in &pushed {
                kept.push(r.k, r.row as u32, r.blend as u32);
            }
            prop_assert!(kept.len_bound() >= pushed.len());
            prop_assert!(kept.bytes() <= 8 * pushed.len());
            prop_assert_eq!(kept.iter().collect::<Vec<_>>(), pushed);
        }
    }

    /// Every falloff and alpha of a row evaluation, in every lane (those that blend and those
    /// that do not), for the portable lanes and each instruction set this machine has.
    fn row_values(s: &Splat<f32>, cy: f32) -> Vec<f32> {
        struct Op<'a>(&'a Splat<f32>, f32);
        impl LaneOp for Op<'_> {
            type Output = Vec<f32>;
            #[inline(always)]
            fn run<I: LaneIsa>(self, isa: I) -> Vec<f32> {
                let cx: [f32; LANES] = std::array::from_fn(|l| pixel_centre::<f32>(l as u32));
                let (mut falloff, mut alpha) = ([0f32; LANES], [0f32; LANES]);
                evaluate_row::<true, I>(
                    isa,
                    self.0,
                    Mask::MAX,
                    &cx,
                    self.1,
                    &mut falloff,
                    &mut alpha,
                );
                falloff.into_iter().chain(alpha).collect()
            }
        }
        super::super::Isa::available()
            .into_iter()
            .filter_map(super::super::Token::new)
            .flat_map(|token| token.run(Op(s, cy)))
            .collect()
    }

    /// Where a Gaussian's cut lies beyond the exponential's range (an opacity of `f32::MAX` or
    /// `+inf`), its rows still make the scalar evaluation's decisions and alphas: far lanes whose
    /// `sigma` is below the cut but whose exponential underflows to 0 are skipped (`sigma` from
    /// 0.08 to 310 along the row).
    #[test]
    fn rows_of_a_cut_beyond_the_exponential_s_range_evaluate_as_the_scalar_loops() {
        for opacity in [f32::MAX, f32::INFINITY] {
            let s = Splat::new([0.25f32, 0.5], [2.67, 0.0, 2.67], opacity);
            assert!(s.sigma_cut > -gaussian::EXP_F32_LOW, "cut {}", s.sigma_cut);
            check_row_against_scalar(&s, pixel_centre::<f32>(0));
        }
    }

    /// [`row_values`]' alphas against the scalar loops' evaluation, lane by lane.
    fn check_row_against_scalar(s: &Splat<f32>, cy: f32) {
        let values = row_values(s, cy);
        for per_isa in values.chunks(2 * LANES) {
            let alpha = &per_isa[LANES..];
            for (l, &a) in alpha.iter().enumerate() {
                let scalar = crate::blend::evaluate(s, pixel_centre::<f32>(l as u32), cy);
                if let Some(hit) = scalar {
                    assert_eq!(a.to_bits(), hit.alpha.to_bits(), "lane {l}");
                } else {
                    // Not blended: the lane's alpha stays below the skip threshold (or NaN).
                    assert!(a < ALPHA_MIN as f32 || a.is_nan(), "lane {l}: alpha {a}");
                }
            }
        }
    }

    proptest! {
        /// No row evaluation leaves a subnormal value in any lane: far from a Gaussian's centre
        /// `exp(-sigma)` is subnormal, and arithmetic on subnormals is many times slower on some
        /// processors, so the lanes the Gaussian does not reach must not compute it.
        #[test]
        fn row_evaluations_leave_no_subnormal_lane(
            mx in -8f32..24.0,
            my in -8f32..24.0,
            radius in 0.3f32..6.0,
            skew in -0.9f32..0.9,
            opacity in 0.01f32..1.0,
            row in 0u32..16,
        ) {
            let a = 1.0 / (radius * radius);
            let s = Splat::new([mx, my], [a, skew * a, a], opacity);
            let values = row_values(&s, pixel_centre::<f32>(row));
            prop_assert!(values.iter().all(|v| !v.is_subnormal()), "{values:?}");
        }
    }
}
