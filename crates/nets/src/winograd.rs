//! Winograd F(2x2, 3x3): the fast algorithm of the valid 3x3 cross-correlation and of its
//! weight gradient, used by the convolution engine ([`crate::conv`]) for `f32` layers that are
//! wide enough (see [`crate::conv::ConvAlgorithm`]).
//!
//! Convention (Lavin and Gray, "Fast Algorithms for Convolutional Neural Networks", 2016,
//! interpolation points 0, 1, -1 and infinity): the 2x2 block of outputs
//! `y[r][x] = sum_{i,j} g[i][j] d[r+i][x+j]` of a 4x4 input patch `d` and a 3x3 kernel `g` is
//!
//! ```text
//! Y = Aᵀ [ (G g Gᵀ) ⊙ (Bᵀ d B) ] A,
//!      ⎡1  0 -1  0⎤       ⎡1    0    0 ⎤
//! Bᵀ = ⎢0  1  1  0⎥   G = ⎢1/2  1/2  1/2⎥   Aᵀ = ⎡1  1  1  0⎤
//!      ⎢0 -1  1  0⎥       ⎢1/2 -1/2  1/2⎥        ⎣0  1 -1 -1⎦
//!      ⎣0  1  0 -1⎦       ⎣0    0    1 ⎦
//! ```
//!
//! Over channels the elementwise product becomes, for each of the 16 positions `e` of the
//! transformed patch, one matrix product `M[e] (O x tiles) = U[e] (O x C) * V[e] (C x tiles)`,
//! where `U` holds the transformed kernels and `V` the transformed input patches of a run of
//! tiles: 16 multiply-adds per channel pair and 4 outputs, against 36 for the direct correlation,
//! in exchange for the transforms, which are additions linear in the channel counts.
//!
//! # Exactness
//! The algebra is exact (the module's tests check it in `f64`); only the rounding differs from
//! the direct correlation. The transforms only add and subtract, and the kernel transform
//! (halves of sums, computed in `f64` and rounded once) is exact up to that one rounding, so an
//! output carries the rounding of a few more additions than the direct sum. F(4x4, 3x3), with
//! a ninth of the direct arithmetic, was measured too: its larger coefficients (up to 8 and
//! 1/24) raised the worst relative error of the fullres decoder's `f32` gradients against the
//! oracle from about 1e-6 to 1e-4, the project's `f32` tolerance, so it is not used.
//!
//! # ReLU decisions
//! A ReLU decision is the sign of a pre-activation, and a gradient jumps where one changes. The
//! forward passes that record a tape for a backward pass (the guard of `conv3x3_valid`)
//! decide as the exact sum of their `f32` inputs would. Each pre-activation `y` of output
//! channel `o` in tile `t` is `Aᵀ M A` plus the bias, with `M[e] = sum_c U[e][o][c] V[e][c][t]`,
//! and its rounding error is at most `(C + 16) u |U_o| |V_t|`, where `u` is the unit roundoff,
//! `|U_o|` the Euclidean norm of the rounded transformed kernels of `o` over all positions and
//! input channels, and `|V_t|` that of the computed transformed patches of `t`:
//! - the products over channels, in any order and with or without fused multiply-adds, err by
//!   at most `γ_C sum_{e,c} |U||V| <= γ_C |U_o| |V_t|` (Cauchy-Schwarz over `(e, c)`), with
//!   `γ_C = C u / (1 - C u)`;
//! - the kernel transform, rounded once, adds `u |U_o| |V_t|`;
//! - the input transform (two additions per value) errs by at most `u (|V| + |t_a| + |t_b|)`
//!   per value, where `t_a` and `t_b` are the values of its first stage; over a patch
//!   `|t| <= |(Bᵀ)⁻¹|₂ |V| <= √3 |V|` and each first-stage value enters at most three second-stage
//!   ones, so the error norm is at most `(1 + √6 √3) u |V_t| < 5.25 u |V_t|`;
//! - the output transform (two additions, then two, of at most 9 values with coefficients ±1)
//!   adds at most `4 u sum_e |M[e]| <= 4 u |U_o| |V_t|` to first order;
//! - adding the bias and rounding never changes the sign of a sum.
//!
//! `C + 11.25` plus second-order terms is below `(C + 16)(1 + 2^-6)`, the factor used (divided
//! by `sqrt(1 - γ_16C)`, because `|V_t|²` is summed in `f32`, as a vector loop, and may fall
//! short by that relative amount; summed in `f64` as a scalar loop, it cost as much as the
//! products saved). A
//! pre-activation whose computed magnitude exceeds the bound has the sign of the exact one; the
//! others are recomputed as the direct sum in `f64` (products of `f32` values are exact in
//! `f64`, so only the `f64` additions round, about 2^29 times finer), with the bias, rounded once
//! and passed through the ReLU. In the taped passes of the README's demo, 0.9 to 5.7 in 10,000
//! pre-activations of a layer fell within the bound. The recomputation depends only on
//! the output position, so results stay bitwise identical for any thread count and for a region
//! computed alone. The module's test `guarded_relu_decisions_are_those_of_the_exact_sum` builds
//! inputs whose pre-activations are all small differences of large partial sums: the unguarded
//! pass flips about 6 % of the decisions, the guarded one none.
//!
//! # Tiling, memory, vectors and determinism
//! The output of one image is cut into 2x2 tiles, numbered row by row; a job is a contiguous run
//! of at most [`tiles_per_job`] of them. A job transforms its input patches into `V`
//! (`16 x C x tiles`), multiplies into `M` (`16 x O x tiles`) through [`crate::matmul`]
//! (single-threaded), and transforms `M` back into its output tiles, adding the bias and applying
//! the ReLU. The products always have [`tiles_per_job`] columns (a job with fewer tiles leaves
//! the rest unused): the GEMM library chooses its blocking by the shapes, and with one shape
//! each output's sum runs in the same order whichever job and column its tile falls in, so a
//! region computed alone (`crate::tiled`) equals the same region of the whole image bit for bit
//! (with fewer columns for a last, shorter job, a compressed relu4_1 encoder level differed in
//! the last bits). The transforms run a tile row's run of tiles at a time as loops over the tiles,
//! which the compiler vectorises for the instruction set chosen at run time (`pulp`: AVX-512,
//! AVX2+FMA, NEON or the baseline); they only add and subtract, so every instruction set
//! gives the same bits. Jobs run in parallel with rayon and write disjoint output tiles; their
//! extent depends only on the shapes, so results are bitwise identical for any thread count.
//! Scratch memory is at most [`JOB_BUDGET_BYTES`] per running job (more only when 32 tiles
//! exceed it), and the transformed kernels take `16 x O x C` elements.
//!
//! # Weight gradient
//! The adjoint of the same algebra (`conv3x3_valid_weight_grad`): the transformed output
//! gradients `A dY Aᵀ` of a job's tiles times its transformed input patches, summed over the
//! tiles into `dU` (`16 x O x C`), then `dw = Gᵀ dU G`. The jobs are shorter runs of tiles than
//! the forward pass's, run in fixed contiguous groups, each with its own `dU`, summed in group
//! order, so the result is bitwise identical for any thread count as well.

use std::sync::Mutex;

use base::Real;
use ndarray::Array4;
use rayon::prelude::*;

use crate::conv_parts::{bias_relu, in_fixed_groups, sum_in_order, SyncPtr};
use crate::matmul::{matmul, GemmBackend};

/// Outputs per tile side (`m` of F(m x m, 3 x 3)).
const M: usize = 2;
/// Inputs per patch side (`m + 2`).
const A: usize = 4;
/// Positions of a transformed patch.
const E: usize = A * A;

/// Upper bound on the scratch of one job (`V` and `M`), in bytes: small enough that a job's
/// operands stay in the shared L3 cache of the development machine with two jobs running, large
/// enough that each of its 16 products is a wide GEMM.
pub const JOB_BUDGET_BYTES: usize = 8 << 20;

/// Upper bound on the scratch of one weight-gradient job (`V` and the transformed output
/// gradients): smaller than [`JOB_BUDGET_BYTES`], because there the 16 products accumulate into
/// one `O x C` block per position over the job's tiles, and shorter products whose operands stay
/// in the core's own L2 cache ran faster. Measured at 256x256 (`NETS_CONV_TABLE=algorithms cargo
/// bench -p dsgs-nets --bench conv`, two threads, Winograd over direct time): with 8 MiB the
/// weight gradient took 0.58 to 0.70 of the direct time from 64->128 up but 0.86 at 128->128 and
/// 1.33 at 64->64; with 2 MiB 0.56 to 0.63, and 0.76 at 64->64; with 16 MiB or more, up to 1.07.
const DW_JOB_BUDGET_BYTES: usize = 2 << 20;

/// Fewest tiles of a weight-gradient job, whatever [`DW_JOB_BUDGET_BYTES`] allows: the length of
/// its products' sums. With the 32 tiles that 2 MiB leave for 256->512 and 512->256, the weight
/// gradient took 0.69 to 0.74 of the direct time, against 0.60 to 0.62 with 160 tiles (8 MiB).
const DW_MIN_TILES: usize = 128;

/// Tiles per job for `c` input and `o` output channels of `T`: as many as fit
/// [`JOB_BUDGET_BYTES`], between 32 and 4096, a multiple of 32.
pub fn tiles_per_job<T>(c: usize, o: usize) -> usize {
    tiles_within::<T>(c, o, JOB_BUDGET_BYTES, 32)
}

/// Tiles per job for `c` input and `o` output channels of `T`: as many as fit `budget` bytes,
/// between `min` and 4096, a multiple of 32 (`min` is one too).
fn tiles_within<T>(c: usize, o: usize, budget: usize, min: usize) -> usize {
    let per_tile = E * (c + o) * std::mem::size_of::<T>();
    (budget / per_tile.max(1)).clamp(min, 4096) / 32 * 32
}

/// `G g` for one column `g` of a kernel (3 values to 4), in `f64`.
#[inline(always)]
fn kernel_1d(g: [f64; 3]) -> [f64; A] {
    [
        g[0],
        (g[0] + g[1] + g[2]) / 2.0,
        (g[0] - g[1] + g[2]) / 2.0,
        g[2],
    ]
}

/// The transformed kernels `U[e][o][c] = (G w[o][c] Gᵀ)[e]` of weights `w [O,C,3,3]` (flat),
/// computed in `f64` and rounded once.
fn transform_kernels<T: Real>(ws: &[T], o: usize, c: usize) -> Vec<T> {
    let mut u = vec![T::zero(); E * o * c];
    let ptr = SyncPtr(u.as_mut_ptr());
    (0..o).into_par_iter().for_each(|oc| {
        for ci in 0..c {
            let g = &ws[(oc * c + ci) * 9..(oc * c + ci + 1) * 9];
            let g = |i: usize, j: usize| g[i * 3 + j].to_f64_exact();
            // Columns of G g (4x3), then the rows of (G g) Gᵀ.
            let cols: [[f64; A]; 3] =
                std::array::from_fn(|j| kernel_1d([g(0, j), g(1, j), g(2, j)]));
            let [c0, c1, c2] = cols;
            for (i, ((&a, &b), &d)) in c0.iter().zip(&c1).zip(&c2).enumerate() {
                let row = kernel_1d([a, b, d]);
                for (j, &v) in row.iter().enumerate() {
                    // SAFETY: (i*A + j, oc, ci) indexes inside `u`, and the task of `oc` is the
                    // only writer of the elements with that `oc`.
                    unsafe { *ptr.get().add(((i * A + j) * o + oc) * c + ci) = T::lit(v) };
                }
            }
        }
    });
    u
}

/// The scratch of one job: transformed inputs, transformed outputs, the rows of one run, and
/// the guard's.
type Scratch<T> = (Vec<T>, Vec<T>, Vec<T>, GuardScratch<T>);

/// A run of tiles within one tile row: tile row `ty`, tile columns `tx0..tx0 + len`, the first
/// of which is tile `off` of its job.
#[derive(Clone, Copy)]
struct Run {
    ty: usize,
    tx0: usize,
    len: usize,
    off: usize,
}

/// The jobs of `n` images of `tiles` tiles each: `(image, first tile, end tile)`, at most
/// `per_job` tiles each, in image and tile order.
fn jobs(n: usize, tiles: usize, per_job: usize) -> Vec<(usize, usize, usize)> {
    (0..n)
        .flat_map(|img| {
            (0..tiles)
                .step_by(per_job)
                .map(move |t0| (img, t0, (t0 + per_job).min(tiles)))
        })
        .collect()
}

/// The runs of tiles `t0..t1` of an image `tw` tiles wide.
fn runs(t0: usize, t1: usize, tw: usize) -> Vec<Run> {
    let mut v = Vec::new();
    let mut t = t0;
    while t < t1 {
        let (ty, tx0) = (t / tw, t % tw);
        let len = (tw - tx0).min(t1 - t);
        v.push(Run {
            ty,
            tx0,
            len,
            off: t - t0,
        });
        t += len;
    }
    v
}

/// Valid 3x3 cross-correlation of a padded input `xs [N,C,Hp,Wp]` (flat, standard layout) with
/// `ws [O,C,3,3]` (flat), plus an optional bias, optionally followed by ReLU; the same result as
/// the direct implicit GEMM of [`crate::conv`] up to rounding. Output `[N, O, Hp-2, Wp-2]`.
///
/// With `relu` and `guard`, every pre-activation within the error bound of zero
/// ([`band_factor`]) is recomputed by the direct sum in `f64`, so that each ReLU decision is
/// the one of the exact sum (see "ReLU decisions" in the module documentation).
#[allow(clippy::too_many_arguments)]
pub(crate) fn conv3x3_valid<T: Real>(
    xs: &[T],
    dims: [usize; 4],
    ws: &[T],
    o: usize,
    bias: Option<&[T]>,
    relu: bool,
    guard: bool,
    backend: GemmBackend,
) -> Array4<T> {
    let [n, c, hp, wp] = dims;
    let (h_out, w_out) = (hp - 2, wp - 2);
    let (th, tw) = (h_out.div_ceil(M), w_out.div_ceil(M));
    let tiles = th * tw;
    let per_job = tiles_per_job::<T>(c, o);
    let jobs = jobs(n, tiles, per_job);
    let u = transform_kernels(ws, o, c);
    let guard = guard && relu;
    // The guard's per-output-channel factor `band_factor(c) * |U[.][o][.]|`.
    let u_norms: Vec<f64> = if guard {
        let f = band_factor::<T>(c);
        (0..o)
            .map(|oc| f * norm_f64((0..E).flat_map(|e| &u[(e * o + oc) * c..(e * o + oc + 1) * c])))
            .collect()
    } else {
        Vec::new()
    };
    // The pre-activations the guard flags, as `[image, output channel, row, column]`, in any
    // order (`recompute` sorts them).
    let flagged: Mutex<Vec<[u32; 4]>> = Mutex::new(Vec::new());
    // Not zeroed first: the jobs' runs partition the tiles, and the output stage writes every
    // output element of each run's tiles (see `assume_init` below).
    let mut out = Array4::<T>::uninit((n, o, h_out, w_out));
    let out_ptr = SyncPtr(out.as_mut_ptr().cast::<T>());
    let plane_in = hp * wp;
    // Scratch buffers are recycled through a pool, so at most one set per running job exists.
    let pool: Mutex<Vec<Scratch<T>>> = Mutex::new(Vec::new());
    jobs.par_iter().for_each(|&(img, t0, t1)| {
        // The products always run on `per_job` columns, however many tiles the job has (the
        // spare columns hold stale finite values and are never read back): the GEMM library
        // picks its blocking and kernels by the shapes, so with one shape for every job, and
        // whole panels (a multiple of 32 columns), each output is summed in the same order
        // wherever its tile falls: in a whole image, in a region of it (`crate::tiled`), first
        // or last in a job.
        let nt = per_job;
        let (mut v, mut m, mut rows, mut guard_scratch) = pool
            .lock()
            .ok()
            .and_then(|mut p| p.pop())
            .unwrap_or_default();
        v.resize(E * c * nt, T::zero());
        m.resize(E * o * nt, T::zero());
        rows.resize(4 * A * (tw + 1), T::zero());
        let runs = runs(t0, t1, tw);
        base::isa::dispatch(InputStage {
            x_img: &xs[img * c * plane_in..(img + 1) * c * plane_in],
            dims: [c, hp, wp],
            nt,
            runs: &runs,
            scratch: &mut rows,
            v: &mut v,
        });
        if guard {
            let len = t1 - t0;
            guard_scratch.sums.resize(len, T::zero());
            base::isa::dispatch(NormStage {
                v: &v,
                nt,
                sums: &mut guard_scratch.sums,
            });
            guard_scratch.norms.clear();
            let norms = guard_scratch.sums.iter().map(|s| s.to_f64_exact().sqrt());
            guard_scratch.norms.extend(norms);
            guard_scratch.suspects.clear();
        }
        for e in 0..E {
            // SAFETY: U[e] is O x C, V[e] is C x nt and M[e] is O x nt, all row-major inside
            // their buffers, and M does not alias U or V.
            unsafe {
                matmul(
                    backend,
                    o,
                    c,
                    nt,
                    (u.as_ptr().add(e * o * c), c as isize, 1),
                    (v.as_ptr().add(e * c * nt), nt as isize, 1),
                    false,
                    (m.as_mut_ptr().add(e * o * nt), nt as isize, 1),
                );
            }
        }
        base::isa::dispatch(OutputStage {
            m: &m,
            o,
            nt,
            runs: &runs,
            bias,
            relu,
            guard: guard.then_some(Guard {
                u_norms: &u_norms,
                tile_norms: &guard_scratch.norms,
                bounds: &mut guard_scratch.bounds,
                suspects: &mut guard_scratch.suspects,
            }),
            scratch: &mut rows,
            out: out_ptr,
            img,
            out_dims: [h_out, w_out],
        });
        if !guard_scratch.suspects.is_empty() {
            // A poisoned lock still holds every flag pushed before the panic that poisoned it
            // (which rayon passes on to the caller anyway).
            let mut f = flagged.lock().unwrap_or_else(|e| e.into_inner());
            let of_image = guard_scratch.suspects.iter();
            f.extend(of_image.map(|&(oc, r, x)| [img as u32, oc, r, x]));
        }
        if let Ok(mut p) = pool.lock() {
            p.push((v, m, rows, guard_scratch));
        }
    });
    // SAFETY: the jobs' runs cover every tile of every image (`jobs` and `runs` partition
    // them), and `OutputStage` writes all the output rows and columns of each run's tiles that
    // lie inside the output, so every element has been written.
    let mut out = unsafe { out.assume_init() };
    let mut flagged = flagged.into_inner().unwrap_or_else(|e| e.into_inner());
    if !flagged.is_empty() {
        recompute(xs, dims, ws, bias, &mut flagged, &mut out);
    }
    out
}

/// `(C + 16) u (1 + 2^-6) / sqrt(1 - γ_16C)`, with `u` the unit roundoff of `T` and
/// `γ_n = n u / (1 - n u)`: times `|U_o|` (the Euclidean norm of output channel `o`'s
/// transformed kernels over all 16 positions and input channels, in `f64`) and `|V_t|~` (that of
/// tile `t`'s transformed input patches, its square summed in `T`, which errs by at most
/// `γ_16C`), a bound on the rounding error of every pre-activation of output channel `o` in tile
/// `t`. See "ReLU decisions" in the module documentation.
pub(crate) fn band_factor<T: Real>(c: usize) -> f64 {
    let unit_roundoff = T::epsilon().to_f64_exact() / 2.0;
    let n = (E * c) as f64 * unit_roundoff;
    let gamma = n / (1.0 - n);
    if !(0.0..1.0).contains(&gamma) {
        // Too many channels for the bound: recompute every pre-activation.
        return f64::INFINITY;
    }
    (c as f64 + 16.0) * unit_roundoff * (1.0 + 1.0 / 64.0) / (1.0 - gamma).sqrt()
}

/// The Euclidean norm of `values`, summed in `f64` in their order.
fn norm_f64<'a, T: Real + 'a>(values: impl IntoIterator<Item = &'a T>) -> f64 {
    values
        .into_iter()
        .map(|v| {
            let v = v.to_f64_exact();
            v * v
        })
        .sum::<f64>()
        .sqrt()
}

/// The guard's scratch of one job: the norms of its tiles' transformed patches (and their
/// squares), one output channel's bounds over a run of tiles, and the pre-activations to
/// recompute, as `(output channel, row, column)`.
#[derive(Default)]
struct GuardScratch<T> {
    sums: Vec<T>,
    bounds: Vec<T>,
    norms: Vec<f64>,
    suspects: Vec<(u32, u32, u32)>,
}

/// The sums of squares of the transformed patches of a job's tiles (`|V_t|²`, over all 16
/// positions and input channels), in `T`, row by row of `v` (`16 x C x nt`), run with the
/// instruction set `pulp` chose (separate multiplications and additions, so the same bits with
/// any of them).
struct NormStage<'a, T> {
    v: &'a [T],
    nt: usize,
    sums: &'a mut [T],
}

impl<T: Real> pulp::WithSimd for NormStage<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let len = self.sums.len();
        self.sums.fill(T::zero());
        for row in self.v.chunks_exact(self.nt) {
            for (s, &x) in self.sums.iter_mut().zip(&row[..len]) {
                *s += x * x;
            }
        }
    }
}

/// What [`OutputStage`] needs to flag pre-activations near zero.
struct Guard<'a, T> {
    /// `band_factor(C) |U_o|` per output channel.
    u_norms: &'a [f64],
    /// `|V_t|` per tile of the job.
    tile_norms: &'a [f64],
    /// The bounds of one output channel's run of tiles, rounded up into `T`.
    bounds: &'a mut Vec<T>,
    suspects: &'a mut Vec<(u32, u32, u32)>,
}

/// A value of `T` at least `x` (for `x >= 0`; NaN stays NaN): `x` widened by `2^-20` of itself
/// and by `f32`'s smallest normal value, then rounded to nearest. The widened value is a normal
/// number, so rounding takes at most `2^-24` of it (`2^-53` in `f64`): less than was added. An
/// element `|v| > upper_bound(x)` therefore has `|v| > x`; an element at or below it is compared
/// with `x` itself, so the comparison's outcome is that of `|v| <= x` in `f64`.
#[inline(always)]
fn upper_bound<T: Real>(x: f64) -> T {
    T::lit(x * (1.0 + 1.0 / 1_048_576.0) + f64::from(f32::MIN_POSITIVE))
}

/// Flagged pre-activations per parallel work item of [`recompute`].
const RECOMPUTE_CHUNK: usize = 512;

/// Input channels per block of [`recompute`]'s sums.
const RECOMPUTE_CHANNELS: usize = 8;

/// Recomputes the flagged pre-activations `[image, output channel, row, column]` by the direct
/// sum in `f64`, adds the bias, rounds once to `T` and applies the ReLU, writing into `out`.
///
/// Each sum runs as nine partial sums, one per kernel tap, each over the input channels in
/// ascending order, then added in tap order (row by row): it depends on the position alone, so
/// the result is the same for any thread count and any split into jobs or regions. The work runs
/// input channel block by block over chunks of the flagged positions sorted by image and row,
/// so that a block's weights and the few input rows of a chunk are read while they are in cache.
fn recompute<T: Real>(
    xs: &[T],
    [_, c, hp, wp]: [usize; 4],
    ws: &[T],
    bias: Option<&[T]>,
    flagged: &mut [[u32; 4]],
    out: &mut Array4<T>,
) {
    let (_, o, h_out, w_out) = out.dim();
    let plane = hp * wp;
    flagged.sort_unstable_by_key(|&[img, oc, r, x]| (img, r, x, oc));
    // The weights by input channel, `[C][O][3][3]`, in `f64`.
    let mut w64 = vec![0.0; ws.len()];
    for (oc, wo) in ws.chunks_exact(9 * c).enumerate() {
        for (ci, wk) in wo.chunks_exact(9).enumerate() {
            let dst = &mut w64[(ci * o + oc) * 9..(ci * o + oc + 1) * 9];
            for (d, w) in dst.iter_mut().zip(wk) {
                *d = w.to_f64_exact();
            }
        }
    }
    let sums: Vec<f64> = flagged
        .par_chunks(RECOMPUTE_CHUNK)
        .flat_map_iter(|chunk| {
            let mut taps = vec![[0.0f64; 9]; chunk.len()];
            for c0 in (0..c).step_by(RECOMPUTE_CHANNELS) {
                let c1 = (c0 + RECOMPUTE_CHANNELS).min(c);
                for (t, &[img, oc, r, x]) in taps.iter_mut().zip(chunk) {
                    let (img, oc, r, x) = (img as usize, oc as usize, r as usize, x as usize);
                    let mut acc = *t;
                    for ci in c0..c1 {
                        let w = &w64[(ci * o + oc) * 9..][..9];
                        let xc = &xs[(img * c + ci) * plane..][..plane];
                        for a in 0..3 {
                            let row = &xc[(r + a) * wp + x..][..3];
                            for b in 0..3 {
                                acc[3 * a + b] += w[3 * a + b] * row[b].to_f64_exact();
                            }
                        }
                    }
                    *t = acc;
                }
            }
            taps.into_iter().map(|t| t.iter().sum::<f64>())
        })
        .collect();
    let out = out.as_slice_mut().expect("fresh output");
    for (&s, &[img, oc, r, x]) in sums.iter().zip(flagged.iter()) {
        let (img, oc, r, x) = (img as usize, oc as usize, r as usize, x as usize);
        let b = bias.map_or(0.0, |b| b[oc].to_f64_exact());
        let v = T::lit(s + b);
        out[((img * o + oc) * h_out + r) * w_out + x] = if v > T::zero() { v } else { T::zero() };
    }
}

/// The weight gradient `[O, C, 3, 3]` (flat) of [`conv3x3_valid`] given its padded input
/// `xs [N,C,Hp,Wp]` and the output gradient `dys [N,O,Hp-2,Wp-2]` (flat, standard layout): the
/// same result as the direct implicit GEMM of [`crate::conv`] up to rounding.
///
/// Differentiating `Y = Aᵀ [U ⊙ V] A`: the gradient of the transformed kernel is
/// `dU[e] (O x C) = sum over tiles of (A dY Aᵀ)[e] (O x tiles) * V[e]ᵀ (tiles x C)`, 16 products
/// with the transformed input patches `V` of the forward pass, and `dw = Gᵀ dU G`, computed in
/// `f64` and rounded once. Jobs are runs of tiles as in the forward pass, of at most
/// [`DW_JOB_BUDGET_BYTES`] of scratch; they are split into `groups` fixed
/// contiguous groups run in parallel, each accumulating its jobs in order into its own `dU`; the
/// groups' sums are added in group order. Neither depends on the thread count, and every product
/// has the same number of columns (the spare ones zero), so results are bitwise identical for any
/// thread count. Output positions past the image edge (partial tiles) have a zero gradient and
/// input positions past it read as zero, so they add nothing.
pub(crate) fn conv3x3_valid_weight_grad<T: Real>(
    xs: &[T],
    dims: [usize; 4],
    dys: &[T],
    o: usize,
    groups: usize,
    backend: GemmBackend,
) -> Vec<T> {
    let [n, c, hp, wp] = dims;
    let (h_out, w_out) = (hp - 2, wp - 2);
    let (th, tw) = (h_out.div_ceil(M), w_out.div_ceil(M));
    let tiles = th * tw;
    let per_job = tiles_within::<T>(c, o, DW_JOB_BUDGET_BYTES, DW_MIN_TILES);
    let jobs = jobs(n, tiles, per_job);
    let groups = groups.clamp(1, jobs.len().max(1));
    let plane_in = hp * wp;
    let plane_out = h_out * w_out;
    let partials: Vec<Vec<T>> = in_fixed_groups(&jobs, groups, |group| {
        let nt = per_job;
        let mut du = vec![T::zero(); E * o * c];
        let mut v = vec![T::zero(); E * c * nt];
        let mut dm = vec![T::zero(); E * o * nt];
        let mut rows = vec![T::zero(); 4 * A * (tw + 1)];
        for &(img, t0, t1) in group {
            let runs = runs(t0, t1, tw);
            if t1 - t0 < nt {
                // Columns past the job's tiles: zero in both operands, so that they add
                // exactly nothing (not even a NaN from a stale value).
                for row in v.chunks_mut(nt).chain(dm.chunks_mut(nt)) {
                    row[t1 - t0..].fill(T::zero());
                }
            }
            base::isa::dispatch(InputStage {
                x_img: &xs[img * c * plane_in..(img + 1) * c * plane_in],
                dims: [c, hp, wp],
                nt,
                runs: &runs,
                scratch: &mut rows,
                v: &mut v,
            });
            base::isa::dispatch(GradientStage {
                dy_img: &dys[img * o * plane_out..(img + 1) * o * plane_out],
                o,
                nt,
                runs: &runs,
                out_dims: [h_out, w_out],
                scratch: &mut rows,
                dm: &mut dm,
            });
            for e in 0..E {
                // SAFETY: dM[e] is O x nt and V[e] is C x nt, row-major inside their
                // buffers (V[e] read transposed as nt x C); dU[e] is O x C inside this
                // group's own `du`, which aliases neither.
                unsafe {
                    matmul(
                        backend,
                        o,
                        nt,
                        c,
                        (dm.as_ptr().add(e * o * nt), nt as isize, 1),
                        (v.as_ptr().add(e * c * nt), 1, nt as isize),
                        true,
                        (du.as_mut_ptr().add(e * o * c), c as isize, 1),
                    );
                }
            }
        }
        du
    });
    // dw[o][c] = Gᵀ dU[o][c] G, with dU summed over the groups in order.
    let mut dw = vec![T::zero(); o * c * 9];
    dw.par_chunks_mut(c * 9).enumerate().for_each(|(oc, row)| {
        for (ci, cell) in row.chunks_mut(9).enumerate() {
            let du = |e: usize| sum_in_order(&partials, (e * o + oc) * c + ci).to_f64_exact();
            let h: [f64; E] = std::array::from_fn(du);
            // Gᵀ along the rows of dU (4x4 -> 3x4), then along its columns (3x4 -> 3x3).
            let rows: [[f64; A]; 3] = std::array::from_fn(|i| {
                std::array::from_fn(|j| kernel_1d_transposed([0, 1, 2, 3].map(|e| h[e * A + j]))[i])
            });
            for (i, r) in rows.iter().enumerate() {
                let out = kernel_1d_transposed(*r);
                for (j, &v) in out.iter().enumerate() {
                    cell[i * 3 + j] = T::lit(v);
                }
            }
        }
    });
    dw
}

/// `Gᵀ h` for one column `h` of a kernel gradient (4 values to 3), in `f64`: the adjoint of
/// [`kernel_1d`].
#[inline(always)]
fn kernel_1d_transposed(h: [f64; A]) -> [f64; 3] {
    [
        h[0] + (h[1] + h[2]) / 2.0,
        (h[1] - h[2]) / 2.0,
        (h[1] + h[2]) / 2.0 + h[3],
    ]
}

/// The output-gradient transform of one job, run with the instruction set `pulp` chose: for
/// every output channel of image `dy_img` (`out_dims = [H, W]` planes) and every run of tiles,
/// `A dY Aᵀ` of each tile's 2x2 gradient block (zero past the image edge) into `dm`
/// (`16 x O x nt`).
struct GradientStage<'a, T> {
    dy_img: &'a [T],
    o: usize,
    nt: usize,
    runs: &'a [Run],
    out_dims: [usize; 2],
    scratch: &'a mut [T],
    dm: &'a mut [T],
}

impl<T: Real> pulp::WithSimd for GradientStage<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let [h_out, w_out] = self.out_dims;
        let (o, nt) = (self.o, self.nt);
        for oc in 0..o {
            let plane = &self.dy_img[oc * h_out * w_out..(oc + 1) * h_out * w_out];
            for run in self.runs {
                let len = run.len;
                // The block's rows a = 0, 1 as left (even) and right (odd) columns.
                let (d, rest) = self.scratch.split_at_mut(2 * M * len);
                let p = &mut rest[..2 * A * len];
                let x0 = run.tx0 * M;
                for a in 0..M {
                    let (left, right) = d[2 * a * len..(2 * a + 2) * len].split_at_mut(len);
                    let r = run.ty * M + a;
                    if r >= h_out {
                        left.fill(T::zero());
                        right.fill(T::zero());
                        continue;
                    }
                    let row = &plane[r * w_out..(r + 1) * w_out];
                    for k in 0..len {
                        let x = x0 + 2 * k;
                        left[k] = row[x];
                        right[k] = row.get(x + 1).copied().unwrap_or(T::zero());
                    }
                }
                // A dY (4x2), column by column: rows dY0, dY0 + dY1, dY0 - dY1, -dY1.
                for x in 0..M {
                    let (y0, y1) = (&d[x * len..(x + 1) * len], &d[(2 + x) * len..(3 + x) * len]);
                    let q = &mut p[x * A * len..(x + 1) * A * len];
                    let (q0, rest) = q.split_at_mut(len);
                    let (q1, rest) = rest.split_at_mut(len);
                    let (q2, q3) = rest.split_at_mut(len);
                    for k in 0..len {
                        q0[k] = y0[k];
                        q1[k] = y0[k] + y1[k];
                        q2[k] = y0[k] - y1[k];
                        q3[k] = -y1[k];
                    }
                }
                // Then (A dY) Aᵀ along the rows: columns P0, P0 + P1, P0 - P1, -P1.
                for i in 0..A {
                    let (p0, p1) = (
                        &p[i * len..(i + 1) * len],
                        &p[(A + i) * len..(A + i + 1) * len],
                    );
                    let at = |j: usize| ((i * A + j) * o + oc) * nt + run.off;
                    let out = &mut self.dm[at(0)..at(0) + len];
                    out.copy_from_slice(p0);
                    let out = &mut self.dm[at(1)..at(1) + len];
                    for k in 0..len {
                        out[k] = p0[k] + p1[k];
                    }
                    let out = &mut self.dm[at(2)..at(2) + len];
                    for k in 0..len {
                        out[k] = p0[k] - p1[k];
                    }
                    let out = &mut self.dm[at(3)..at(3) + len];
                    for k in 0..len {
                        out[k] = -p1[k];
                    }
                }
            }
        }
    }
}

/// `Bᵀ d B` of the patches of one run of tiles of one channel `plane` (`hp x wp`), written as
/// `run.len` values from `v[at(e)]` for each position `e`. `scratch` holds at least
/// `4 * A * (run.len + 1)` values.
#[inline(always)]
fn transform_input_run<T: Real>(
    plane: &[T],
    hp: usize,
    wp: usize,
    run: Run,
    scratch: &mut [T],
    v: &mut [T],
    at: impl Fn(usize) -> usize,
) {
    let (len, k1) = (run.len, run.len + 1);
    let (even, rest) = scratch.split_at_mut(A * k1);
    let (odd, rest) = rest.split_at_mut(A * k1);
    let (ce, co) = rest.split_at_mut(A * k1);
    let co = &mut co[..A * k1];
    // The even and odd columns 2(tx0 + k) and 2(tx0 + k) + 1 of the patch rows, zero outside
    // the plane.
    let x0 = run.tx0 * M;
    for i in 0..A {
        let (ev, od) = (
            &mut even[i * k1..(i + 1) * k1],
            &mut odd[i * k1..(i + 1) * k1],
        );
        let r = run.ty * M + i;
        if r >= hp {
            ev.fill(T::zero());
            od.fill(T::zero());
            continue;
        }
        let row = &plane[r * wp..(r + 1) * wp];
        if x0 + 2 * k1 <= wp {
            let src = &row[x0..x0 + 2 * k1];
            for ((e, o), pair) in ev.iter_mut().zip(od.iter_mut()).zip(src.chunks_exact(2)) {
                *e = pair[0];
                *o = pair[1];
            }
        } else {
            for k in 0..k1 {
                let x = x0 + 2 * k;
                ev[k] = row.get(x).copied().unwrap_or(T::zero());
                od[k] = row.get(x + 1).copied().unwrap_or(T::zero());
            }
        }
    }
    // Bᵀ along the patch rows, for the even and the odd columns.
    for (src, out) in [(&*even, &mut *ce), (&*odd, &mut *co)] {
        let (d0, d1, d2, d3) = (
            &src[..k1],
            &src[k1..2 * k1],
            &src[2 * k1..3 * k1],
            &src[3 * k1..4 * k1],
        );
        let (o0, rest) = out.split_at_mut(k1);
        let (o1, rest) = rest.split_at_mut(k1);
        let (o2, o3) = rest.split_at_mut(k1);
        for k in 0..k1 {
            o0[k] = d0[k] - d2[k];
            o1[k] = d1[k] + d2[k];
            o2[k] = d2[k] - d1[k];
            o3[k] = d1[k] - d3[k];
        }
    }
    // Then B along the columns: column j of tile k is even[k], odd[k], even[k+1], odd[k+1].
    for i in 0..A {
        let (e, od) = (&ce[i * k1..(i + 1) * k1], &co[i * k1..(i + 1) * k1]);
        let (e0, e1, o0, o1) = (&e[..len], &e[1..=len], &od[..len], &od[1..=len]);
        let rows: [usize; A] = std::array::from_fn(|j| at(i * A + j));
        let out = &mut v[rows[0]..rows[0] + len];
        for k in 0..len {
            out[k] = e0[k] - e1[k];
        }
        let out = &mut v[rows[1]..rows[1] + len];
        for k in 0..len {
            out[k] = o0[k] + e1[k];
        }
        let out = &mut v[rows[2]..rows[2] + len];
        for k in 0..len {
            out[k] = e1[k] - o0[k];
        }
        let out = &mut v[rows[3]..rows[3] + len];
        for k in 0..len {
            out[k] = o0[k] - o1[k];
        }
    }
}

/// The input transform of one job, run with the instruction set `pulp` chose: every channel
/// of image `x_img` (`dims = [C, Hp, Wp]`) over every run of tiles, into `v` (`16 x C x nt`).
struct InputStage<'a, T> {
    x_img: &'a [T],
    dims: [usize; 3],
    nt: usize,
    runs: &'a [Run],
    scratch: &'a mut [T],
    v: &'a mut [T],
}

impl<T: Real> pulp::WithSimd for InputStage<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let [c, hp, wp] = self.dims;
        let plane_in = hp * wp;
        for ci in 0..c {
            let plane = &self.x_img[ci * plane_in..(ci + 1) * plane_in];
            for run in self.runs {
                transform_input_run(plane, hp, wp, *run, self.scratch, self.v, |e| {
                    (e * c + ci) * self.nt + run.off
                });
            }
        }
    }
}

/// The output transform of one job, run with the instruction set `pulp` chose: every output
/// channel over every run of tiles, from `m` (`16 x O x nt`) into the output tensor of
/// `out_dims = [H, W]` planes, adding the bias and applying the ReLU.
struct OutputStage<'a, T> {
    m: &'a [T],
    o: usize,
    nt: usize,
    runs: &'a [Run],
    bias: Option<&'a [T]>,
    relu: bool,
    /// With a guard, the ReLU is applied here, after each pre-activation within the band of
    /// zero has been flagged for recomputation.
    guard: Option<Guard<'a, T>>,
    scratch: &'a mut [T],
    out: SyncPtr<T>,
    img: usize,
    out_dims: [usize; 2],
}

impl<T: Real> pulp::WithSimd for OutputStage<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(mut self, _simd: S) {
        let [h_out, w_out] = self.out_dims;
        let (o, nt) = (self.o, self.nt);
        for oc in 0..o {
            let b = self.bias.map_or(T::zero(), |b| b[oc]);
            for run in self.runs {
                let len = run.len;
                untransform_run(
                    self.m,
                    |e| (e * o + oc) * nt + run.off,
                    len,
                    b,
                    self.relu && self.guard.is_none(),
                    self.scratch,
                );
                if let Some(g) = &mut self.guard {
                    // Pre-activations within the band of zero are flagged, then all go
                    // through the ReLU. A column is first compared with the band's bounds
                    // rounded up into `T` (`upper_bound`), all of it at once; only a column
                    // with an element at or below one of them is compared exactly.
                    let y = &mut self.scratch[2 * A * len..2 * A * len + 2 * M * len];
                    let un = g.u_norms[oc];
                    let norms = &g.tile_norms[run.off..run.off + len];
                    g.bounds.clear();
                    g.bounds
                        .extend(norms.iter().map(|&n| upper_bound::<T>(un * n)));
                    for (q, col) in y.chunks_exact_mut(len).enumerate() {
                        let mut near = false;
                        for (v, &b) in col.iter().zip(g.bounds.iter()) {
                            near |= v.abs() <= b;
                        }
                        if near {
                            let (x, a) = (q / M, q % M);
                            for (k, v) in col.iter().enumerate() {
                                if v.to_f64_exact().abs() <= un * norms[k] {
                                    let (r, xx) = (run.ty * M + a, (run.tx0 + k) * M + x);
                                    if r < h_out && xx < w_out {
                                        g.suspects.push((oc as u32, r as u32, xx as u32));
                                    }
                                }
                            }
                        }
                        for v in col.iter_mut() {
                            *v = bias_relu(*v, T::zero(), true);
                        }
                    }
                }
                let y = &self.scratch[2 * A * len..2 * A * len + 2 * M * len];
                let (x0, x1) = (run.tx0 * M, ((run.tx0 + len) * M).min(w_out));
                for a in 0..M {
                    let r = run.ty * M + a;
                    if r >= h_out {
                        break;
                    }
                    // SAFETY: columns x0..x1 of row r of channel oc of image img lie inside the
                    // output tensor and belong to this run's tiles, which only this job writes.
                    let dst = unsafe {
                        std::slice::from_raw_parts_mut(
                            self.out
                                .get()
                                .add(((self.img * o + oc) * h_out + r) * w_out + x0),
                            x1 - x0,
                        )
                    };
                    let (left, right) = (
                        &y[a * len..(a + 1) * len],
                        &y[(M + a) * len..(M + a + 1) * len],
                    );
                    let mut pairs = dst.chunks_exact_mut(2);
                    for ((pair, &l), &r) in (&mut pairs).zip(left).zip(right) {
                        pair[0] = l;
                        pair[1] = r;
                    }
                    if let [last] = pairs.into_remainder() {
                        *last = left[len - 1];
                    }
                }
            }
        }
    }
}

/// `Aᵀ m A` of one run of `len` tiles, whose 16 transformed positions `e` are the rows
/// `m[at(e)..at(e) + len]`, plus the bias `b` and the ReLU. Returns the outputs as four rows of
/// `len` values in `scratch` (at least `12 len` long): output row `a` and column `x` of tile `k`
/// is element `(x * 2 + a) * len + k`.
#[inline(always)]
fn untransform_run<'s, T: Real>(
    m: &[T],
    at: impl Fn(usize) -> usize,
    len: usize,
    b: T,
    relu: bool,
    scratch: &'s mut [T],
) -> &'s [T] {
    let (p, rest) = scratch.split_at_mut(2 * A * len);
    let y = &mut rest[..2 * M * len];
    // m A, row by row of the patch: p[i][0] = m[i][0] + m[i][1] + m[i][2] and
    // p[i][1] = m[i][1] - m[i][2] - m[i][3].
    for i in 0..A {
        let row = |j: usize| {
            let s = at(i * A + j);
            &m[s..s + len]
        };
        let (m0, m1, m2, m3) = (row(0), row(1), row(2), row(3));
        let (p0, p1) = p[2 * i * len..(2 * i + 2) * len].split_at_mut(len);
        for k in 0..len {
            p0[k] = m0[k] + m1[k] + m2[k];
            p1[k] = m1[k] - m2[k] - m3[k];
        }
    }
    // Then Aᵀ (m A), column by column, with the bias and the ReLU.
    for x in 0..M {
        let col = |i: usize| &p[(2 * i + x) * len..(2 * i + x + 1) * len];
        let (q0, q1, q2, q3) = (col(0), col(1), col(2), col(3));
        let (y0, y1) = y[2 * x * len..(2 * x + 2) * len].split_at_mut(len);
        for k in 0..len {
            y0[k] = bias_relu(q0[k] + q1[k] + q2[k], b, relu);
            y1[k] = bias_relu(q1[k] - q2[k] - q3[k], b, relu);
        }
    }
    y
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (SplitMix64) for test data.
    pub(super) fn values(seed: u64, len: usize) -> Vec<f64> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = s;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                (z >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
            })
            .collect()
    }

    pub(super) fn direct(xs: &[f64], [n, c, hp, wp]: [usize; 4], ws: &[f64], o: usize) -> Vec<f64> {
        let (h, w) = (hp - 2, wp - 2);
        let mut y = vec![0.0; n * o * h * w];
        for img in 0..n {
            for oc in 0..o {
                for r in 0..h {
                    for x in 0..w {
                        let mut s = 0.0;
                        for ci in 0..c {
                            for i in 0..3 {
                                for j in 0..3 {
                                    s += ws[((oc * c + ci) * 3 + i) * 3 + j]
                                        * xs[((img * c + ci) * hp + r + i) * wp + x + j];
                                }
                            }
                        }
                        y[((img * o + oc) * h + r) * w + x] = s;
                    }
                }
            }
        }
        y
    }

    /// The direct weight gradient `[O, C, 3, 3]` of a valid correlation.
    fn direct_weight_grad(
        xs: &[f64],
        [n, c, hp, wp]: [usize; 4],
        dys: &[f64],
        o: usize,
    ) -> Vec<f64> {
        let (h, w) = (hp - 2, wp - 2);
        let mut dw = vec![0.0; o * c * 9];
        for img in 0..n {
            for oc in 0..o {
                for ci in 0..c {
                    for i in 0..3 {
                        for j in 0..3 {
                            let mut s = 0.0;
                            for r in 0..h {
                                for x in 0..w {
                                    s += dys[((img * o + oc) * h + r) * w + x]
                                        * xs[((img * c + ci) * hp + r + i) * wp + x + j];
                                }
                            }
                            dw[((oc * c + ci) * 3 + i) * 3 + j] += s;
                        }
                    }
                }
            }
        }
        dw
    }

    /// The weight gradient's algebra, as for the forward pass: in `f64` it returns the direct
    /// sum to within the accumulated rounding, with partial edge tiles, several images and
    /// group counts from one to more than the jobs (the groups change only the order of the
    /// sums).
    #[test]
    fn winograd_weight_gradient_equals_the_direct_one_in_f64() {
        for (n, c, o, hp, wp, seed) in [
            (1, 3, 2, 7, 9, 1),
            (2, 5, 4, 11, 6, 2),
            (1, 8, 3, 13, 17, 3),
        ] {
            let xs = values(seed, n * c * hp * wp);
            let dys = values(seed + 100, n * o * (hp - 2) * (wp - 2));
            let want = direct_weight_grad(&xs, [n, c, hp, wp], &dys, o);
            // Each weight's gradient sums one product per output pixel and image.
            let scale = (n * (hp - 2) * (wp - 2)) as f64;
            for groups in [1, 2, 7] {
                let got = conv3x3_valid_weight_grad(
                    &xs,
                    [n, c, hp, wp],
                    &dys,
                    o,
                    groups,
                    GemmBackend::Gemm,
                );
                assert_eq!(got.len(), want.len());
                for (g, w) in got.iter().zip(&want) {
                    assert!((g - w).abs() <= 1e-13 * scale, "{g} vs {w}");
                }
            }
        }
    }

    /// The algebra: in `f64` the transform returns the direct correlation to within the
    /// accumulated rounding of both (a few hundred ulps of the largest partial sum), on sizes
    /// that are not multiples of the tile, so the edge tiles are partial.
    #[test]
    fn winograd_equals_the_direct_correlation_in_f64() {
        for (n, c, o, hp, wp, seed) in [
            (1, 3, 2, 7, 9, 1),
            (2, 5, 4, 11, 6, 2),
            (1, 8, 3, 13, 17, 3),
        ] {
            let xs = values(seed, n * c * hp * wp);
            let ws = values(seed + 100, o * c * 9);
            let want = direct(&xs, [n, c, hp, wp], &ws, o);
            let got = conv3x3_valid(
                &xs,
                [n, c, hp, wp],
                &ws,
                o,
                None,
                false,
                false,
                GemmBackend::Gemm,
            );
            let scale = (9 * c) as f64;
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() <= 1e-13 * scale, "{g} vs {w}");
            }
        }
    }

    /// Guarded ReLU decisions (`conv3x3_valid` with `relu` and `guard`) are those of the exact
    /// sum, also where cancellation puts the pre-activations within rounding of zero: the input
    /// channels come in equal pairs whose weights nearly cancel, the second of each pair in the
    /// second half, so every pre-activation is a small difference of large partial sums. The unguarded pass, on the same inputs, flips some
    /// decisions, which shows that the inputs reach the rounding; and on inputs without
    /// cancellation the guarded values are those of the unguarded pass wherever it decided
    /// outside the band.
    #[test]
    fn guarded_relu_decisions_are_those_of_the_exact_sum() {
        let relu64 = |v: f64| v.max(0.0);
        // The second case has two images, so that recomputed values land in the right one.
        for (n, c, o, hp, wp, seed) in [(1, 32, 8, 18, 18, 11), (2, 48, 5, 17, 20, 12)] {
            let dims = [n, c, hp, wp];
            let xs: Vec<f32> = (0..n as u64)
                .flat_map(|img| {
                    let half: Vec<f32> = values(seed + 100 * img, c / 2 * hp * wp)
                        .into_iter()
                        .map(|v| v as f32)
                        .collect();
                    [half.clone(), half].concat()
                })
                .collect();
            let base = values(seed + 1, o * c / 2 * 9);
            let tiny = values(seed + 2, o * c / 2 * 9);
            // Channel k + C/2 repeats channel k's input with the opposite weight plus 1e-6 of
            // it, so the partial sums over the channels grow, then cancel.
            let mut ws = vec![0f32; o * c * 9];
            for oc in 0..o {
                for k in 0..c / 2 {
                    for t in 0..9 {
                        let i = (oc * c / 2 + k) * 9 + t;
                        ws[(oc * c + k) * 9 + t] = base[i] as f32;
                        ws[(oc * c + k + c / 2) * 9 + t] = (-base[i] + 1e-6 * tiny[i]) as f32;
                    }
                }
            }
            let bias = vec![0f32; o];
            let x64: Vec<f64> = xs.iter().map(|&v| v as f64).collect();
            let w64: Vec<f64> = ws.iter().map(|&v| v as f64).collect();
            let exact = direct(&x64, dims, &w64, o);
            let run = |guard: bool| {
                let y = conv3x3_valid(
                    &xs,
                    dims,
                    &ws,
                    o,
                    Some(&bias),
                    true,
                    guard,
                    GemmBackend::Gemm,
                );
                y.iter().map(|&v| v as f64).collect::<Vec<_>>()
            };
            let (guarded, plain) = (run(true), run(false));
            let decided = |y: &[f64]| y.iter().map(|&v| v > 0.0).collect::<Vec<_>>();
            let want = exact.iter().map(|&v| v > 0.0).collect::<Vec<_>>();
            assert_eq!(decided(&guarded), want, "C={c}");
            let flips = decided(&plain)
                .iter()
                .zip(&want)
                .filter(|(a, b)| a != b)
                .count();
            assert!(
                flips > 0,
                "C={c}: the unguarded pass made no wrong decision"
            );
            // Every guarded value the guard changed is the exact sum rounded once to `f32`. The
            // recomputation and `direct` each sum in `f64`, within `γ_{9C} A` of the real sum,
            // where `A = sum |w x|` over the terms (`γ_n = n 2^-53 / (1 - n 2^-53)`); rounding to
            // `f32` adds at most `2^-24` of the value. So the bound is `2^-23 |e| + 3 γ_{9C} A`.
            let abs64 = |v: &[f64]| v.iter().map(|a| a.abs()).collect::<Vec<_>>();
            let magnitudes = direct(&abs64(&x64), dims, &abs64(&w64), o);
            let n_terms = (9 * c) as f64 * f64::EPSILON / 2.0;
            let gamma = n_terms / (1.0 - n_terms);
            for (((g, p), e), a) in guarded.iter().zip(&plain).zip(&exact).zip(&magnitudes) {
                if g == p {
                    continue;
                }
                let tol = e.abs() / 8_388_608.0 + 3.0 * gamma * a;
                assert!((g - relu64(*e)).abs() <= tol, "{g} vs {e} (within {tol})");
            }
        }
        // Without cancellation: values outside the band are the unguarded pass's.
        let (c, o, hp, wp) = (24, 6, 15, 14);
        let dims = [1, c, hp, wp];
        let xs: Vec<f32> = values(21, c * hp * wp)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        let ws: Vec<f32> = values(22, o * c * 9)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        let bias: Vec<f32> = values(23, o).into_iter().map(|v| v as f32).collect();
        let run = |guard: bool| {
            conv3x3_valid(
                &xs,
                dims,
                &ws,
                o,
                Some(&bias),
                true,
                guard,
                GemmBackend::Gemm,
            )
        };
        let (guarded, plain) = (run(true), run(false));
        let x64: Vec<f64> = xs.iter().map(|&v| v as f64).collect();
        let w64: Vec<f64> = ws.iter().map(|&v| v as f64).collect();
        let exact = direct(&x64, dims, &w64, o);
        let (h, w) = (hp - 2, wp - 2);
        let mut same = 0;
        for (i, ((g, p), e)) in guarded.iter().zip(&plain).zip(&exact).enumerate() {
            let e = e + bias[i / (h * w)] as f64;
            assert_eq!(*g > 0.0, e > 0.0);
            same += usize::from(g == p);
        }
        // Only pre-activations within (C + 16) u |U| |V| of zero are recomputed: none of the
        // 936 here, when written; the bound allows one in a hundred.
        assert!(
            same * 100 >= 99 * guarded.len(),
            "{same} of {}",
            guarded.len()
        );
    }
}
