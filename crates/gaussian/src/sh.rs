//! View-dependent colour from real spherical harmonics up to degree 3, forward and backward.
//!
//! Convention: gsplat's `_spherical_harmonics` with the basis of `_eval_sh_bases_fast` (Sloan,
//! "Efficient Spherical Harmonic Evaluation", JCGT 2013), as pinned by the oracle:
//!
//! * the view direction is `d = mean - camera_centre`, normalised as `d / max(|d|, 1e-12)`;
//! * `raw = sum_k basis_k(d) sh_k` over the first `(degree + 1)^2` coefficients (the others are
//!   ignored, so a scene stored at degree 3 can render at a lower active degree);
//! * `colour = max(raw + 0.5, 0)`; the backward passes the gradient where `raw + 0.5 >= 0`
//!   (PyTorch's `clamp_min` backward).
//!
//! The basis polynomials are differentiated as polynomials in `(x, y, z)` and the result is
//! chained through the normalisation, exactly as automatic differentiation of the reference does.
//! SH coefficients are Gaussian-major: `sh[n * coeffs_per_gaussian + k]` is an RGB triple.
//!
//! Gaussians are processed in parallel in fixed chunks. In `f32` the forward runs as vector code
//! (lane arrays of 16 Gaussians, compiled for the instruction set `pulp` picks at run time) with
//! the scalar operations in the same order per lane, so every path and thread count gives the
//! same bits.

use base::memory::filled;
use rayon::prelude::*;
use std::mem::MaybeUninit;

use crate::Real;

/// Number of basis functions of a degree: `(degree + 1)^2`.
pub const fn num_bases(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

// Basis constants, named after their role in the reference.
const C0: f64 = 0.2820947917738781;
const C1: f64 = 0.48860251190292;
const C2_ZX: f64 = 1.092548430592079;
const C2_XY: f64 = 0.5462742152960395;
const C2_Z2: f64 = 0.9461746957575601;
const C2_Z0: f64 = 0.3153915652525201;
const C3_C: f64 = 2.285228997322329;
const C3_C0: f64 = 0.4570457994644658;
const C3_B: f64 = 1.445305721320277;
const C3_A: f64 = 0.5900435899266435;
const C3_Z3: f64 = 1.865881662950577;
const C3_Z1: f64 = 1.119528997770346;

/// The first `nb` (1, 4, 9 or 16) basis functions at the direction `(x, y, z)`; the rest are 0.
#[inline(always)]
pub fn eval_bases<T: Real>(nb: usize, [x, y, z]: [T; 3]) -> [T; 16] {
    let l = T::lit;
    let mut r = [T::zero(); 16];
    r[0] = l(C0);
    if nb <= 1 {
        return r;
    }
    r[1] = -l(C1) * y;
    r[2] = l(C1) * z;
    r[3] = -l(C1) * x;
    if nb <= 4 {
        return r;
    }
    let z2 = z * z;
    let fc1 = x * x - y * y;
    let fs1 = l(2.0) * x * y;
    let tmp_b = -l(C2_ZX) * z;
    r[4] = l(C2_XY) * fs1;
    r[5] = tmp_b * y;
    r[6] = l(C2_Z2) * z2 - l(C2_Z0);
    r[7] = tmp_b * x;
    r[8] = l(C2_XY) * fc1;
    if nb <= 9 {
        return r;
    }
    let tmp_c = -l(C3_C) * z2 + l(C3_C0);
    let tmp_b = l(C3_B) * z;
    let fc2 = x * fc1 - y * fs1;
    let fs2 = x * fs1 + y * fc1;
    r[9] = -l(C3_A) * fs2;
    r[10] = tmp_b * fs1;
    r[11] = tmp_c * y;
    r[12] = z * (l(C3_Z3) * z2 - l(C3_Z1));
    r[13] = tmp_c * x;
    r[14] = tmp_b * fc1;
    r[15] = -l(C3_A) * fc2;
    r
}

/// `sum_k g[k] * grad basis_k(x, y, z)` over the first `nb` basis functions, with each basis
/// function differentiated as a polynomial in `(x, y, z)`.
#[inline(always)]
pub fn bases_vjp<T: Real>(nb: usize, [x, y, z]: [T; 3], g: &[T; 16]) -> [T; 3] {
    let l = T::lit;
    let two = l(2.0);
    let (mut gx, mut gy, mut gz) = (T::zero(), T::zero(), T::zero());
    if nb <= 1 {
        return [gx, gy, gz];
    }
    // r1 = -C1 y, r2 = C1 z, r3 = -C1 x.
    gy -= l(C1) * g[1];
    gz += l(C1) * g[2];
    gx -= l(C1) * g[3];
    if nb <= 4 {
        return [gx, gy, gz];
    }
    // r4 = C2_XY 2xy.
    gx += l(C2_XY) * two * y * g[4];
    gy += l(C2_XY) * two * x * g[4];
    // r5 = -C2_ZX z y.
    gy -= l(C2_ZX) * z * g[5];
    gz -= l(C2_ZX) * y * g[5];
    // r6 = C2_Z2 z^2 - C2_Z0.
    gz += l(C2_Z2) * two * z * g[6];
    // r7 = -C2_ZX z x.
    gx -= l(C2_ZX) * z * g[7];
    gz -= l(C2_ZX) * x * g[7];
    // r8 = C2_XY (x^2 - y^2).
    gx += l(C2_XY) * two * x * g[8];
    gy -= l(C2_XY) * two * y * g[8];
    if nb <= 9 {
        return [gx, gy, gz];
    }
    let three = l(3.0);
    let z2 = z * z;
    let fc1 = x * x - y * y;
    let fs1 = two * x * y;
    let tmp_c = -l(C3_C) * z2 + l(C3_C0);
    let d_tmp_c_dz = -two * l(C3_C) * z;
    let tmp_b = l(C3_B) * z;
    // fc2 = x^3 - 3 x y^2, fs2 = 3 x^2 y - y^3.
    let d_fc2 = [three * fc1, -three * fs1];
    let d_fs2 = [three * fs1, three * fc1];
    // r9 = -C3_A fs2.
    gx -= l(C3_A) * d_fs2[0] * g[9];
    gy -= l(C3_A) * d_fs2[1] * g[9];
    // r10 = C3_B z 2xy.
    gx += tmp_b * two * y * g[10];
    gy += tmp_b * two * x * g[10];
    gz += l(C3_B) * fs1 * g[10];
    // r11 = tmp_c y.
    gy += tmp_c * g[11];
    gz += d_tmp_c_dz * y * g[11];
    // r12 = C3_Z3 z^3 - C3_Z1 z.
    gz += (three * l(C3_Z3) * z2 - l(C3_Z1)) * g[12];
    // r13 = tmp_c x.
    gx += tmp_c * g[13];
    gz += d_tmp_c_dz * x * g[13];
    // r14 = C3_B z (x^2 - y^2).
    gx += tmp_b * two * x * g[14];
    gy -= tmp_b * two * y * g[14];
    gz += l(C3_B) * fc1 * g[14];
    // r15 = -C3_A fc2.
    gx -= l(C3_A) * d_fc2[0] * g[15];
    gy -= l(C3_A) * d_fc2[1] * g[15];
    [gx, gy, gz]
}

/// `[f(0), f(1), f(2)]`, spelled out so that it always inlines (`array::map` may not).
#[inline(always)]
fn v3<T>(f: impl Fn(usize) -> T) -> [T; 3] {
    [f(0), f(1), f(2)]
}

/// `d / max(|d|, 1e-12)`, the divisor, and whether the norm was clamped.
#[inline(always)]
fn normalize_dir<T: Real>(d: [T; 3]) -> ([T; 3], T, bool) {
    let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let eps = T::lit(1e-12);
    let clamped = norm < eps;
    let denom = if clamped { eps } else { norm };
    (v3(|a| d[a] / denom), denom, clamped)
}

fn check_args(degree: usize, coeffs_per_gaussian: usize, sh_len: usize, n: usize) -> usize {
    assert!(degree <= 3, "SH degree {degree} is not supported (0..=3)");
    let nb = num_bases(degree);
    assert!(
        nb <= coeffs_per_gaussian,
        "SH degree {degree} needs {nb} coefficients per Gaussian, the scene stores {coeffs_per_gaussian}"
    );
    assert_eq!(
        sh_len,
        n * coeffs_per_gaussian,
        "{sh_len} SH coefficients for {n} Gaussians with {coeffs_per_gaussian} each"
    );
    nb
}

/// Gaussians per parallel work item (a fixed chunking: results never depend on the threads).
const MIN_CHUNK: usize = 1024;

/// The colour of one Gaussian (the reference: the vector code does the same per lane).
#[inline(always)]
fn color_one<T: Real>(nb: usize, coeffs: &[[T; 3]], m: &[T; 3], camera_center: [T; 3]) -> [T; 3] {
    let dir = v3(|a| m[a] - camera_center[a]);
    let (u, _, _) = normalize_dir(dir);
    let b = eval_bases(nb, u);
    v3(|c| {
        let raw = (0..nb).fold(T::zero(), |acc, k| acc + b[k] * coeffs[k][c]);
        (raw + T::lit(0.5)).max(T::zero())
    })
}

/// The gradients of one Gaussian, given a colour cotangent `vc` that is not all zero: writes
/// the first `nb` entries of `d_coeffs` and returns the gradient of the mean.
#[inline(always)]
fn backward_one<T: Real>(
    nb: usize,
    coeffs: &[[T; 3]],
    m: &[T; 3],
    camera_center: [T; 3],
    vc: [T; 3],
    d_coeffs: &mut [[T; 3]],
) -> [T; 3] {
    let zero = T::zero();
    let dir = v3(|a| m[a] - camera_center[a]);
    let (u, denom, clamped) = normalize_dir(dir);
    let b = eval_bases(nb, u);
    // The colour cotangent where the clamp at 0 passes it.
    let v = v3(|c| {
        let raw = (0..nb).fold(zero, |acc, k| acc + b[k] * coeffs[k][c]);
        if raw + T::lit(0.5) >= zero {
            vc[c]
        } else {
            zero
        }
    });
    let mut g_basis = [zero; 16];
    for k in 0..nb {
        d_coeffs[k] = v3(|c| b[k] * v[c]);
        g_basis[k] = coeffs[k][0] * v[0] + coeffs[k][1] * v[1] + coeffs[k][2] * v[2];
    }
    let g_u = bases_vjp(nb, u, &g_basis);
    // u = d / max(|d|, eps): (I - u u^T) / |d| unless the norm was clamped.
    if clamped {
        v3(|a| g_u[a] / denom)
    } else {
        let dot = u[0] * g_u[0] + u[1] * g_u[1] + u[2] * g_u[2];
        v3(|a| (g_u[a] - u[a] * dot) / denom)
    }
}

/// Colours of Gaussians seen from `camera_center`, with SH evaluated to `degree`.
///
/// In `f32` this runs as vector code (16 Gaussians per step, compiled for the instruction set
/// `pulp` picks at run time) that performs the scalar operations per lane, so it returns the
/// same bits as the generic code.
///
/// # Panics
/// If `degree > 3`, `(degree + 1)^2 > coeffs_per_gaussian`, or
/// `sh.len() != means.len() * coeffs_per_gaussian`.
pub fn sh_colors<T: Real>(
    degree: usize,
    coeffs_per_gaussian: usize,
    sh: &[[T; 3]],
    means: &[[T; 3]],
    camera_center: [T; 3],
) -> Vec<[T; 3]> {
    let nb = check_args(degree, coeffs_per_gaussian, sh.len(), means.len());
    let k = coeffs_per_gaussian;
    let mut out = vec![[T::zero(); 3]; means.len()];
    out.par_chunks_mut(MIN_CHUNK)
        .zip(means.par_chunks(MIN_CHUNK))
        .zip(sh.par_chunks(MIN_CHUNK * k.max(1)))
        .for_each(|((out, means), sh)| {
            if fast::colors(nb, k, sh, means, camera_center, out) {
                return;
            }
            for ((o, m), coeffs) in out.iter_mut().zip(means).zip(sh.chunks_exact(k)) {
                *o = color_one(nb, coeffs, m, camera_center);
            }
        });
    out
}

/// The backward of [`sh_colors`]: given the cotangent of the colours, the gradients with
/// respect to the SH coefficients (zero beyond the active degree) and to the means (through
/// the view direction). A Gaussian whose colour cotangent is zero gets zero gradients without
/// evaluating its bases (the image does not depend on it).
///
/// In `f32` this runs as vector code, as [`sh_colors`] does, with the scalar operations in the
/// same order per lane, so every path and thread count gives the same bits.
///
/// # Panics
/// As [`sh_colors`], and if `v_colors.len() != means.len()`.
pub fn sh_colors_backward<T: Real>(
    degree: usize,
    coeffs_per_gaussian: usize,
    sh: &[[T; 3]],
    means: &[[T; 3]],
    camera_center: [T; 3],
    v_colors: &[[T; 3]],
) -> (Vec<[T; 3]>, Vec<[T; 3]>) {
    let n = means.len();
    let nb = check_args(degree, coeffs_per_gaussian, sh.len(), n);
    assert_eq!(
        v_colors.len(),
        n,
        "{} colour cotangents for {n} Gaussians",
        v_colors.len()
    );
    let zero = T::zero();
    let k = coeffs_per_gaussian;
    if k == 0 {
        return (Vec::new(), filled(n, [zero; 3]));
    }
    // Every element is written once, by the loop below, instead of zeroed first and then
    // overwritten: the coefficient gradients are the largest array of an iteration
    // (`docs/performance.md`, "The SH gradients written once").
    let mut d_sh: Vec<[T; 3]> = Vec::with_capacity(sh.len());
    let mut d_means: Vec<[T; 3]> = Vec::with_capacity(n);
    d_sh.spare_capacity_mut()[..sh.len()]
        .par_chunks_mut(MIN_CHUNK * k)
        .zip(d_means.spare_capacity_mut()[..n].par_chunks_mut(MIN_CHUNK))
        .zip(sh.par_chunks(MIN_CHUNK * k))
        .zip(
            means
                .par_chunks(MIN_CHUNK)
                .zip(v_colors.par_chunks(MIN_CHUNK)),
        )
        .for_each(|(((d_sh, d_means), sh), (means, v_colors))| {
            backward_rows(nb, k, sh, means, camera_center, v_colors, d_sh, d_means);
        });
    // SAFETY: the chunks above cover the first `sh.len()` and `n` slots of the two buffers
    // (the same chunking of both, `MIN_CHUNK` Gaussians and their `k` coefficients each), and
    // every iteration writes Gaussian `i`'s mean gradient and all `k` of its coefficient slots;
    // `for_each` returns only after every chunk is done.
    unsafe {
        d_sh.set_len(sh.len());
        d_means.set_len(n);
    }
    (d_sh, d_means)
}

/// [`sh_colors_backward`] of a run of Gaussians, one after the other on the calling thread,
/// into buffers the caller owns: `d_sh` (laid out like `sh`) and `d_means` are overwritten,
/// with the same bits [`sh_colors_backward`] gives those Gaussians. For callers that consume
/// the gradients chunk by chunk while they are in cache (the geometry trainer applies Adam to
/// each chunk's coefficients as soon as their gradients exist).
///
/// # Panics
/// As [`sh_colors_backward`], and if `d_sh` or `d_means` do not match `sh` and `means`.
#[allow(clippy::too_many_arguments)]
pub fn sh_colors_backward_rows<T: Real>(
    degree: usize,
    coeffs_per_gaussian: usize,
    sh: &[[T; 3]],
    means: &[[T; 3]],
    camera_center: [T; 3],
    v_colors: &[[T; 3]],
    d_sh: &mut [[T; 3]],
    d_means: &mut [[T; 3]],
) {
    let n = means.len();
    let nb = check_args(degree, coeffs_per_gaussian, sh.len(), n);
    assert!(
        v_colors.len() == n && d_means.len() == n && d_sh.len() == sh.len(),
        "{} colour cotangents, {} mean and {} coefficient gradient slots for {n} Gaussians \
         and {} coefficients",
        v_colors.len(),
        d_means.len(),
        d_sh.len(),
        sh.len()
    );
    if coeffs_per_gaussian == 0 {
        d_means.fill([T::zero(); 3]);
        return;
    }
    // SAFETY: `[T; 3]` and `MaybeUninit<[T; 3]>` have the same layout, and `backward_rows`
    // only ever stores initialised values, so the slices stay initialised.
    let (d_sh, d_means) = unsafe {
        (
            &mut *(d_sh as *mut [[T; 3]] as *mut [MaybeUninit<[T; 3]>]),
            &mut *(d_means as *mut [[T; 3]] as *mut [MaybeUninit<[T; 3]>]),
        )
    };
    backward_rows(
        nb,
        coeffs_per_gaussian,
        sh,
        means,
        camera_center,
        v_colors,
        d_sh,
        d_means,
    );
}

/// The backward of the Gaussians of one chunk (`k > 0` coefficients each): writes every
/// Gaussian's mean gradient and all `k` of its coefficient slots.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn backward_rows<T: Real>(
    nb: usize,
    k: usize,
    sh: &[[T; 3]],
    means: &[[T; 3]],
    camera_center: [T; 3],
    v_colors: &[[T; 3]],
    d_sh: &mut [MaybeUninit<[T; 3]>],
    d_means: &mut [MaybeUninit<[T; 3]>],
) {
    let zero = T::zero();
    let done = fast::backward(nb, k, sh, means, camera_center, v_colors, d_sh, d_means);
    let mut own = [[zero; 3]; 16];
    for i in done..means.len() {
        // A Gaussian the image does not depend on (culled, or blended nowhere) has a zero
        // cotangent and so zero gradients: skip its bases.
        let (d_mean, active) = if v_colors[i].iter().all(|&v| v == zero) {
            ([zero; 3], 0)
        } else {
            let d_mean = backward_one(
                nb,
                &sh[i * k..(i + 1) * k],
                &means[i],
                camera_center,
                v_colors[i],
                &mut own[..nb],
            );
            (d_mean, nb)
        };
        d_means[i].write(d_mean);
        for (j, slot) in d_sh[i * k..(i + 1) * k].iter_mut().enumerate() {
            slot.write(if j < active { own[j] } else { [zero; 3] });
        }
    }
}

/// The `f32` vector code of [`sh_colors`]: blocks of [`fast::LANES`] Gaussians whose
/// per-Gaussian scalar operations (those of [`color_one`]) run stage by stage across lane
/// arrays; the last partial block runs Gaussian by Gaussian. Compiled for the instruction set
/// `pulp` picks at run time.
mod fast {
    use std::mem::MaybeUninit;

    use super::{bases_vjp, color_one, eval_bases, normalize_dir, v3};
    use crate::Real;

    pub(super) const LANES: usize = 16;

    /// The stages of [`color_one`] for the block of [`LANES`] Gaussians starting at `i0`, each
    /// stage on lane arrays: the view directions `u`, the `NB` bases `b`, the
    /// gathered coefficients `coef[basis][channel]` and the colours before the offset and clamp.
    struct Block<const NB: usize> {
        u: [[f32; LANES]; 3],
        b: [[f32; LANES]; NB],
        coef: [[[f32; LANES]; 3]; NB],
        raw: [[f32; LANES]; 3],
    }

    impl<const NB: usize> Block<NB> {
        /// A block of zeros, filled by [`Block::fill`].
        #[inline(always)]
        fn zeros() -> Self {
            Block {
                u: [[0.0; LANES]; 3],
                b: [[0.0; LANES]; NB],
                coef: [[[0.0; LANES]; 3]; NB],
                raw: [[0.0; LANES]; 3],
            }
        }

        /// Computes the stages of the block of Gaussians starting at `i0` in place (one block
        /// reused by a loop: returning a new one per step copies kilobytes, and the loads of
        /// the copy wait for it).
        #[inline(always)]
        fn fill(
            &mut self,
            k: usize,
            sh: &[[f32; 3]],
            means: &[[f32; 3]],
            center: [f32; 3],
            i0: usize,
        ) {
            let Block { u, b, coef, raw } = self;
            for l in 0..LANES {
                let m = &means[i0 + l];
                let (ul, _, _) = normalize_dir(v3(|a| m[a] - center[a]));
                for a in 0..3 {
                    u[a][l] = ul[a];
                }
            }
            for l in 0..LANES {
                let bl = eval_bases(NB, [u[0][l], u[1][l], u[2][l]]);
                for kk in 0..NB {
                    b[kk][l] = bl[kk];
                }
            }
            if !transpose_full(k, sh, i0, coef.as_flattened_mut()) {
                for l in 0..LANES {
                    let row = &sh[(i0 + l) * k..(i0 + l) * k + NB];
                    for kk in 0..NB {
                        for c in 0..3 {
                            coef[kk][c][l] = row[kk][c];
                        }
                    }
                }
            }
            *raw = [[0.0f32; LANES]; 3];
            for kk in 0..NB {
                for c in 0..3 {
                    for l in 0..LANES {
                        raw[c][l] += b[kk][l] * coef[kk][c][l];
                    }
                }
            }
        }
    }

    /// Gaussians ahead of the current block whose coefficients are prefetched: the loads of a
    /// block's 48 cache lines of coefficients otherwise wait for memory one after the other
    /// (`docs/performance.md`, "SSIM blocks and SH prefetch").
    const AHEAD: usize = 2 * LANES;

    /// Asks for the coefficients of the block [`AHEAD`] Gaussians after `i0` (a hint: no effect
    /// on any result).
    #[inline(always)]
    fn prefetch_ahead(k: usize, sh: &[[f32; 3]], i0: usize) {
        let start = ((i0 + AHEAD) * k).min(sh.len());
        let end = ((i0 + AHEAD + LANES) * k).min(sh.len());
        base::memory::prefetch(&sh[start..end]);
    }

    /// The coefficients of all 16 bases of the Gaussians `i0..i0 + LANES` as lane arrays,
    /// `coef[3 * basis + channel][lane]`, moved by three 16 x 16 transposes in AVX-512
    /// registers. The same values as the element-by-element copy, which the compiler turns
    /// into scalar stores read back as vectors (each vector load then waits for its sixteen
    /// stores). Returns `false`, doing nothing, unless `coef` holds all 16 bases and the
    /// processor has AVX-512.
    #[inline(always)]
    fn transpose_full(k: usize, sh: &[[f32; 3]], i0: usize, coef: &mut [[f32; LANES]]) -> bool {
        #[cfg(target_arch = "x86_64")]
        if coef.len() == 48 {
            if let Some(simd) = pulp::x86::V4::try_new() {
                let rows: [&[f32]; LANES] =
                    std::array::from_fn(|l| sh[(i0 + l) * k..(i0 + l) * k + 16].as_flattened());
                simd.vectorize(|| {
                    for q in 0..3 {
                        let block: [[f32; LANES]; LANES] = std::array::from_fn(|l| {
                            rows[l][q * LANES..(q + 1) * LANES]
                                .try_into()
                                .expect("16 coefficients")
                        });
                        let t = transpose16(simd, block);
                        coef[q * LANES..(q + 1) * LANES].copy_from_slice(&t);
                    }
                });
                return true;
            }
        }
        let _ = (k, sh, i0, coef);
        false
    }

    /// `out[j][l] = m[l][j]` for a 16 x 16 block: pairs of rows interleaved, then pairs of
    /// pairs, then 128-bit quarters exchanged twice.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // the index picks the rows each step combines
    fn transpose16(simd: pulp::x86::V4, m: [[f32; LANES]; LANES]) -> [[f32; LANES]; LANES] {
        use std::arch::x86_64::__m512;
        let f = simd.avx512f;
        // Plain loops, not `array::from_fn`: a closure the compiler leaves out of line is
        // compiled without AVX-512 and calls each intrinsic as a function.
        let mut r: [__m512; LANES] = [f._mm512_setzero_ps(); LANES];
        for i in 0..LANES {
            r[i] = pulp::cast(m[i]);
        }
        // Per 128-bit quarter: (a0 b0 a1 b1) and (a2 b2 a3 b3) of rows a, b.
        let mut t = r;
        for i in 0..LANES {
            let (a, b) = (r[i & !1], r[i | 1]);
            t[i] = if i % 2 == 0 {
                f._mm512_unpacklo_ps(a, b)
            } else {
                f._mm512_unpackhi_ps(a, b)
            };
        }
        // u[4g + j], quarter q: rows 4g..4g + 4 at column 4q + j.
        let mut u = t;
        for i in 0..LANES {
            let (g, j) = (i / 4, i % 4);
            let (a, b) = (t[4 * g + j / 2], t[4 * g + 2 + j / 2]);
            u[i] = if j % 2 == 0 {
                f._mm512_shuffle_ps::<0x44>(a, b)
            } else {
                f._mm512_shuffle_ps::<0xEE>(a, b)
            };
        }
        let mut out = [[0f32; LANES]; LANES];
        for j in 0..4 {
            // Quarters 0 and 2 (`_0`) or 1 and 3 (`_1`) of rows 0..8 and of rows 8..16.
            let v_0 = f._mm512_shuffle_f32x4::<0x88>(u[j], u[4 + j]);
            let v_1 = f._mm512_shuffle_f32x4::<0xDD>(u[j], u[4 + j]);
            let w_0 = f._mm512_shuffle_f32x4::<0x88>(u[8 + j], u[12 + j]);
            let w_1 = f._mm512_shuffle_f32x4::<0xDD>(u[8 + j], u[12 + j]);
            out[j] = pulp::cast(f._mm512_shuffle_f32x4::<0x88>(v_0, w_0));
            out[4 + j] = pulp::cast(f._mm512_shuffle_f32x4::<0x88>(v_1, w_1));
            out[8 + j] = pulp::cast(f._mm512_shuffle_f32x4::<0xDD>(v_0, w_0));
            out[12 + j] = pulp::cast(f._mm512_shuffle_f32x4::<0xDD>(v_1, w_1));
        }
        out
    }

    /// The colours of one work item when `T` is `f32` (returns `false`, doing nothing,
    /// otherwise).
    pub(super) fn colors<T: Real>(
        nb: usize,
        k: usize,
        sh: &[[T; 3]],
        means: &[[T; 3]],
        center: [T; 3],
        out: &mut [[T; 3]],
    ) -> bool {
        let (Some(sh), Some(means), Some(center), Some(out)) = (
            T::as_f32_slice(sh.as_flattened()),
            T::as_f32_slice(means.as_flattened()),
            T::as_f32_slice(&center),
            T::as_f32_slice_mut(out.as_flattened_mut()),
        ) else {
            return false;
        };
        let op = Colors {
            k,
            sh: sh.as_chunks::<3>().0,
            means: means.as_chunks::<3>().0,
            center: [center[0], center[1], center[2]],
            out: out.as_chunks_mut::<3>().0,
        };
        match nb {
            1 => base::isa::dispatch(ColorsNb::<1>(op)),
            4 => base::isa::dispatch(ColorsNb::<4>(op)),
            9 => base::isa::dispatch(ColorsNb::<9>(op)),
            _ => base::isa::dispatch(ColorsNb::<16>(op)),
        }
        true
    }

    struct Colors<'a> {
        k: usize,
        sh: &'a [[f32; 3]],
        means: &'a [[f32; 3]],
        center: [f32; 3],
        out: &'a mut [[f32; 3]],
    }

    struct ColorsNb<'a, const NB: usize>(Colors<'a>);

    impl<const NB: usize> pulp::WithSimd for ColorsNb<'_, NB> {
        type Output = ();

        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) {
            let Colors {
                k,
                sh,
                means,
                center,
                out,
            } = self.0;
            let blocks = means.len() / LANES;
            let mut block = Block::<NB>::zeros();
            for blk in 0..blocks {
                let i0 = blk * LANES;
                // color_one across lanes, stage by stage on lane arrays
                let half = 0.5f32;
                prefetch_ahead(k, sh, i0);
                block.fill(k, sh, means, center, i0);
                let raw = &block.raw;
                for l in 0..LANES {
                    out[i0 + l] = v3(|c| (raw[c][l] + half).max(0.0));
                }
            }
            for i in blocks * LANES..means.len() {
                out[i] = color_one(NB, &sh[i * k..i * k + NB], &means[i], center);
            }
        }
    }

    /// The mean and coefficient gradients of the whole blocks of [`LANES`] Gaussians of one
    /// chunk when `T` is `f32` (the stages of [`super::backward_one`] on lane arrays, each lane
    /// with the scalar operations in their order, and zeros for a Gaussian whose colour
    /// cotangent is zero, as the scalar loop writes); returns how many Gaussians it did (0 in
    /// `f64`), the caller doing the rest.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn backward<T: Real>(
        nb: usize,
        k: usize,
        sh: &[[T; 3]],
        means: &[[T; 3]],
        center: [T; 3],
        v_colors: &[[T; 3]],
        d_sh: &mut [MaybeUninit<[T; 3]>],
        d_means: &mut [MaybeUninit<[T; 3]>],
    ) -> usize {
        let (Some(sh), Some(means), Some(center), Some(v_colors)) = (
            T::as_f32_slice(sh.as_flattened()),
            T::as_f32_slice(means.as_flattened()),
            T::as_f32_slice(&center),
            T::as_f32_slice(v_colors.as_flattened()),
        ) else {
            return 0;
        };
        // SAFETY: `Real` is sealed and only `f32` returns `Some` from `as_f32_slice` (just
        // checked), so `T` is `f32` and the slices keep their layout.
        let (d_sh, d_means) = unsafe {
            (
                &mut *(d_sh as *mut [MaybeUninit<[T; 3]>] as *mut [MaybeUninit<[f32; 3]>]),
                &mut *(d_means as *mut [MaybeUninit<[T; 3]>] as *mut [MaybeUninit<[f32; 3]>]),
            )
        };
        let op = Backward {
            k,
            sh: sh.as_chunks::<3>().0,
            means: means.as_chunks::<3>().0,
            center: [center[0], center[1], center[2]],
            v_colors: v_colors.as_chunks::<3>().0,
            d_sh,
            d_means,
        };
        match nb {
            1 => base::isa::dispatch(BackwardNb::<1>(op)),
            4 => base::isa::dispatch(BackwardNb::<4>(op)),
            9 => base::isa::dispatch(BackwardNb::<9>(op)),
            _ => base::isa::dispatch(BackwardNb::<16>(op)),
        }
    }

    struct Backward<'a> {
        k: usize,
        sh: &'a [[f32; 3]],
        means: &'a [[f32; 3]],
        center: [f32; 3],
        v_colors: &'a [[f32; 3]],
        d_sh: &'a mut [MaybeUninit<[f32; 3]>],
        d_means: &'a mut [MaybeUninit<[f32; 3]>],
    }

    struct BackwardNb<'a, const NB: usize>(Backward<'a>);

    impl<const NB: usize> pulp::WithSimd for BackwardNb<'_, NB> {
        type Output = usize;

        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> usize {
            let Backward {
                k,
                sh,
                means,
                center,
                v_colors,
                d_sh,
                d_means,
            } = self.0;
            let blocks = means.len() / LANES;
            let mut block = Block::<NB>::zeros();
            // Coefficient gradients `dc[3 * basis + channel][lane]` (zero beyond `NB`).
            let mut dc = [[0.0f32; LANES]; 48];
            for blk in 0..blocks {
                let i0 = blk * LANES;
                prefetch_ahead(k, sh, i0);
                block.fill(k, sh, means, center, i0);
                let Block { u, b, coef, raw } = &block;
                // The colour cotangent where the clamp at 0 passes it.
                let mut v = [[0.0f32; LANES]; 3];
                let mut active = [false; LANES];
                for l in 0..LANES {
                    let vc = v_colors[i0 + l];
                    active[l] = !vc.iter().all(|&x| x == 0.0);
                    for c in 0..3 {
                        v[c][l] = if raw[c][l] + 0.5 >= 0.0 { vc[c] } else { 0.0 };
                    }
                }
                let mut g_basis = [[0.0f32; LANES]; 16];
                for kk in 0..NB {
                    for l in 0..LANES {
                        for c in 0..3 {
                            dc[3 * kk + c][l] = b[kk][l] * v[c][l];
                        }
                        g_basis[kk][l] = coef[kk][0][l] * v[0][l]
                            + coef[kk][1][l] * v[1][l]
                            + coef[kk][2][l] * v[2][l];
                    }
                }
                let mut g_mean = [[0.0f32; LANES]; 3];
                for l in 0..LANES {
                    let mut gb = [0.0f32; 16];
                    for kk in 0..NB {
                        gb[kk] = g_basis[kk][l];
                    }
                    let ul = [u[0][l], u[1][l], u[2][l]];
                    let g_u = bases_vjp(NB, ul, &gb);
                    let m = &means[i0 + l];
                    let (_, denom, clamped) = normalize_dir(v3(|a| m[a] - center[a]));
                    let d = if clamped {
                        v3(|a| g_u[a] / denom)
                    } else {
                        let dot = ul[0] * g_u[0] + ul[1] * g_u[1] + ul[2] * g_u[2];
                        v3(|a| (g_u[a] - ul[a] * dot) / denom)
                    };
                    for a in 0..3 {
                        g_mean[a][l] = d[a];
                    }
                }
                for l in 0..LANES {
                    let i = i0 + l;
                    d_means[i].write(if active[l] {
                        v3(|a| g_mean[a][l])
                    } else {
                        [0.0; 3]
                    });
                }
                store_rows::<NB>(k, &dc, &active, i0, d_sh);
            }
            blocks * LANES
        }
    }

    /// Writes the `k` coefficient gradient slots of the Gaussians `i0..i0 + LANES` from the
    /// lane arrays `dc` (the first `NB` bases; zeros after them, and everywhere for an inactive
    /// lane): three 16 x 16 transposes in AVX-512 registers when all 16 bases are there.
    #[inline(always)]
    fn store_rows<const NB: usize>(
        k: usize,
        dc: &[[f32; LANES]; 48],
        active: &[bool; LANES],
        i0: usize,
        d_sh: &mut [MaybeUninit<[f32; 3]>],
    ) {
        #[cfg(target_arch = "x86_64")]
        if NB == 16 {
            if let Some(simd) = pulp::x86::V4::try_new() {
                simd.vectorize(|| {
                    for q in 0..3 {
                        let mut block = [[0.0f32; LANES]; LANES];
                        block.copy_from_slice(&dc[q * LANES..(q + 1) * LANES]);
                        let t = transpose16(simd, block);
                        for l in 0..LANES {
                            // Floats `16 q .. 16 (q + 1)` of the 48 of the first 16 slots.
                            let row = &mut d_sh[(i0 + l) * k..(i0 + l) * k + 16];
                            let vals = if active[l] { t[l] } else { [0.0; LANES] };
                            // SAFETY: `row` is 16 slots of three floats each
                            // (`MaybeUninit<[f32; 3]>` has the layout of `[f32; 3]`), so floats
                            // `16 q .. 16 q + 16` with `q < 3` lie inside it.
                            unsafe {
                                let flat = row.as_mut_ptr().cast::<f32>();
                                std::ptr::copy_nonoverlapping(
                                    vals.as_ptr(),
                                    flat.add(q * LANES),
                                    LANES,
                                );
                            }
                        }
                    }
                });
                for l in 0..LANES {
                    let row = &mut d_sh[(i0 + l) * k..(i0 + l + 1) * k];
                    for slot in &mut row[16..] {
                        slot.write([0.0; 3]);
                    }
                }
                return;
            }
        }
        for l in 0..LANES {
            let row = &mut d_sh[(i0 + l) * k..(i0 + l + 1) * k];
            for (j, slot) in row.iter_mut().enumerate() {
                slot.write(if active[l] && j < NB {
                    v3(|c| dc[3 * j + c][l])
                } else {
                    [0.0; 3]
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random value in [-1, 1).
    fn noise(i: usize) -> f32 {
        let x = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        ((x >> 40) as f32 / (1u64 << 23) as f32) - 1.0
    }

    fn bits(v: &[[f32; 3]]) -> Vec<u32> {
        v.as_flattened().iter().map(|x| x.to_bits()).collect()
    }

    /// Means (one exactly at the camera centre: the clamped normalisation), SH coefficients
    /// large enough that some colours clamp at 0, and cotangents with some zero rows.
    type Case = (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<[f32; 3]>, [f32; 3]);

    fn case(n: usize, k: usize) -> Case {
        let center = [0.1f32, -0.2, 0.3];
        let mut means: Vec<[f32; 3]> = (0..n)
            .map(|i| v3(|a| center[a] + 2.0 * noise(3 * i + a)))
            .collect();
        means[n / 2] = center;
        let sh = (0..n * k).map(|i| v3(|a| noise(7 * i + a + 11))).collect();
        let v_colors = (0..n)
            .map(|i| {
                if i % 5 == 0 {
                    [0.0; 3]
                } else {
                    v3(|a| noise(5 * i + a + 3))
                }
            })
            .collect();
        (means, sh, v_colors, center)
    }

    #[test]
    fn chunked_and_vector_paths_give_the_bits_of_the_gaussian_by_gaussian_reference() {
        // sizes with partial lane blocks and several parallel work items
        for n in [1, 17, 2 * MIN_CHUNK + 37] {
            for (degree, k) in (0..=3).flat_map(|d| [(d, 16), (d, num_bases(d))]) {
                let nb = num_bases(degree);
                let (means, sh, v_colors, center) = case(n, k);
                let colors = sh_colors(degree, k, &sh, &means, center);
                let reference: Vec<[f32; 3]> = (0..n)
                    .map(|i| color_one(nb, &sh[i * k..(i + 1) * k], &means[i], center))
                    .collect();
                assert_eq!(
                    bits(&colors),
                    bits(&reference),
                    "colours, n {n} degree {degree}"
                );
                assert!(colors.iter().flatten().any(|&c| c == 0.0) || n < 17 || degree == 0);

                let (d_sh, d_means) = sh_colors_backward(degree, k, &sh, &means, center, &v_colors);
                let mut ref_sh = vec![[0.0f32; 3]; n * k];
                let mut ref_means = vec![[0.0f32; 3]; n];
                for i in 0..n {
                    if v_colors[i] != [0.0; 3] {
                        ref_means[i] = backward_one(
                            nb,
                            &sh[i * k..(i + 1) * k],
                            &means[i],
                            center,
                            v_colors[i],
                            &mut ref_sh[i * k..(i + 1) * k],
                        );
                    }
                }
                assert_eq!(bits(&d_sh), bits(&ref_sh), "d_sh, n {n} degree {degree}");
                assert_eq!(
                    bits(&d_means),
                    bits(&ref_means),
                    "d_means, n {n} degree {degree}"
                );

                // The same bits from the calling thread into buffers of earlier values, in two
                // runs split off a lane block.
                let split = n.min(21);
                let mut rows_sh = vec![[f32::NAN; 3]; n * k];
                let mut rows_means = vec![[-7.0f32; 3]; n];
                let (sh_a, sh_b) = rows_sh.split_at_mut(split * k);
                let (m_a, m_b) = rows_means.split_at_mut(split);
                let (v_a, v_b) = v_colors.split_at(split);
                let (s_a, s_b) = sh.split_at(split * k);
                let (p_a, p_b) = means.split_at(split);
                sh_colors_backward_rows(degree, k, s_a, p_a, center, v_a, sh_a, m_a);
                sh_colors_backward_rows(degree, k, s_b, p_b, center, v_b, sh_b, m_b);
                assert_eq!(
                    bits(&rows_sh),
                    bits(&ref_sh),
                    "rows d_sh, n {n} degree {degree}"
                );
                assert_eq!(
                    bits(&rows_means),
                    bits(&ref_means),
                    "rows d_means, n {n} degree {degree}"
                );
            }
        }
    }
}
