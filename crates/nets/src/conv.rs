//! Convolution engine: 3x3 convolution with reflection padding and 1x1 convolution, forward and
//! backward, NCHW, on top of a single-threaded GEMM ([`crate::matmul`]: the `gemm` crate by
//! default, `matrixmultiply` as the alternative).
//!
//! Convention (PyTorch `Conv2d`, cross-correlation): weights are `[O, C, K, K]`, biases `[O]`, and
//! `y[n,o,r,x] = b[o] + sum_{c,i,j} w[o,c,i,j] * xp[n,c,r+i,x+j]`, where `xp` is the input padded
//! by one pixel with reflection (`F.pad(x, (1,1,1,1), mode="reflect")`, which mirrors about the edge
//! pixel without repeating it) for 3x3 kernels and the input itself for 1x1 kernels.
//!
//! # How it is computed
//! Every convolution, including the backward ones, is reduced to a *valid* cross-correlation of an
//! already padded tensor (`conv_valid`):
//! * forward 3x3: reflection-pad by 1, then valid 3x3;
//! * input gradient 3x3: zero-pad the output gradient by 2 and correlate with the flipped,
//!   transposed kernel (`wt[c,o,i,j] = w[o,c,2-i,2-j]`), which yields the gradient of the padded
//!   input; then fold the reflected border back onto the pixels it was copied from;
//! * 1x1 convolutions need no padding: the input rows themselves are the GEMM operand.
//!
//! A valid 3x3 correlation is an *implicit GEMM*: output rows are computed on the padded grid
//! (each row `Wp` wide, of which the last two columns are discarded), where the window of tap
//! `(i, j)` is just the padded plane shifted by `i*Wp + j`, a strided matrix the GEMM packs
//! directly. A tile of output rows accumulates the nine products
//! `w[:, :, i, j] (O x C) * shifted input (C x tile)` into an `O x tile` accumulator and then
//! copies the valid columns out with bias and ReLU. No im2col matrix is formed.
//!
//! The weight gradient is the same implicit GEMM transposed: with the output gradient widened to
//! the padded width by zero columns, `dW[:, :, i, j] += dY_tile (O x tile) * shifted input^T
//! (tile x C)` for each tap, tile by tile.
//!
//! For `f32` layers wide enough ([`ConvAlgorithm::default_for`]), the valid 3x3
//! correlation of the forward pass and of the input gradient, and the weight gradient, run as
//! Winograd F(2x2, 3x3) instead ([`crate::winograd`]: 16 multiply-adds for 36, bounded extra
//! rounding; the weight gradient's final transform is computed in `f64`); `f64`, the
//! precision of the oracle and gradient tests, always runs the implicit GEMM above, the reference.
//! A forward pass that records a tape for a backward pass ([`conv3x3_reflect_exact_relu`]) makes
//! its ReLU decisions, the masks of the gradient, as the exact sum would: under Winograd, the
//! pre-activations within the algorithm's rounding-error bound of zero are recomputed by the
//! direct sum in `f64` ("ReLU decisions" in [`crate::winograd`]). [`with_algorithm`] forces
//! either algorithm for the convolutions started on the calling thread, taped or not.
//!
//! # Memory bound
//! Forward (and input-gradient) tiles are whole output rows of one image, with an accumulator of
//! at most [`ACC_BUDGET_BYTES`] (256 KiB) unless one padded row alone is larger
//! (`O*Wp*size_of::<T>()`; then a tile is one row). Each running task owns one accumulator, so
//! forward scratch memory is at most `threads * max(256 KiB, O*Wp*size_of::<T>())`, independent
//! of the image height and batch size: a 256x256 fullres relu4_1 forward in `f32` uses at most
//! 2 x 528 KiB, where a whole-image im2col of its 512-channel layer would take 2.4 GB. A weight
//! gradient holds `DW_GROUPS` (4) accumulators of `9*O*C` elements (4 x 4.7 MB for 256->512 in
//! `f32`) and, for 3x3, one copy of the output gradient widened by two columns (the Winograd
//! weight gradient instead holds `16*O*C` elements per group and one job's scratch per running
//! group, see [`crate::winograd`]). Besides scratch,
//! a convolution allocates its output and one padded copy of its input (or output gradient).
//!
//! # Parallelism and determinism
//! Forward and input-gradient tiles run in parallel with rayon, each with single-threaded GEMMs
//! writing a disjoint block of the output. Weight-gradient tiles are split into `DW_GROUPS` fixed
//! contiguous groups that run in parallel, each accumulating its tiles in order into its own
//! buffer; the buffers are then summed in group order. The tiling and grouping depend only on the
//! shapes, never on the number of threads, and every output element is computed by one task
//! through the same sequence of GEMM calls (taps in a fixed order), so results are bitwise
//! identical for any thread count.

use std::mem::MaybeUninit;
use std::sync::Mutex;

use base::Real;
use ndarray::{Array1, Array4, ArrayView1, ArrayView4, ArrayViewMut2, Axis};
use rayon::prelude::*;

use crate::conv_parts::{bias_relu, in_fixed_groups, sum_in_order, SyncPtr};
use crate::matmul::{backend_for, matmul, GemmBackend, Pass};

/// Target number of output pixels per tile (a good GEMM width).
pub const TILE_PIXELS: usize = 2048;

/// Upper bound on one forward accumulator (`O` channels by tile pixels), in bytes, unless one
/// padded row is larger. 256 KiB keeps it in a core's L2 cache while the nine taps accumulate
/// into it; measured on the 2-core development machine, larger tiles were slower.
pub const ACC_BUDGET_BYTES: usize = 256 << 10;

/// Fixed number of tile groups of the 3x3 weight gradient, run in parallel, each with its own
/// `[K*K, O, C]` accumulator (see `weight_grad_implicit`).
const DW_GROUPS: usize = 4;

/// How a 3x3 convolution (forward or input gradient) is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvAlgorithm {
    /// The implicit GEMM of nine taps described above: the reference, in any precision.
    Direct,
    /// Winograd F(2x2, 3x3) ([`crate::winograd`]): 16 multiply-adds for 36, a slightly larger
    /// rounding error in the forward pass and the input gradient.
    Winograd,
}

/// Smallest input and output channel count for which [`ConvAlgorithm::Winograd`] is the default:
/// below it the transforms cost more than the products they save (the first and last layers of
/// the networks, with 3 channels on one side).
pub const WINOGRAD_MIN_CHANNELS: usize = 16;

/// Smallest sum of the input and output channel counts for which [`ConvAlgorithm::Winograd`] is
/// the default, in the forward pass, the input gradient and the weight gradient. Measured at
/// 256x256 on two threads of an otherwise idle machine (`NETS_CONV_TABLE=algorithms cargo bench
/// -p dsgs-nets --bench conv`, see `docs/performance.md`): Winograd takes 0.50 to 0.77 of the
/// direct time on every layer from 64->64 up, in all three passes (the highest at 64->64); on the
/// layers with 3 channels on one side it is slower.
pub const WINOGRAD_MIN_CHANNEL_SUM: usize = 128;

thread_local! {
    static ALGORITHM: std::cell::Cell<Option<ConvAlgorithm>> = const { std::cell::Cell::new(None) };
}

impl ConvAlgorithm {
    /// The default for a 3x3 convolution of `c` input and `o` output channels in precision `T`:
    /// Winograd for `f32` when both counts reach [`WINOGRAD_MIN_CHANNELS`] and their sum reaches
    /// [`WINOGRAD_MIN_CHANNEL_SUM`], direct otherwise.
    /// `f64`, the reference precision of the oracle and gradient tests, always runs direct.
    pub fn default_for<T: Real>(c: usize, o: usize) -> ConvAlgorithm {
        let is_f32 = T::as_f32_slice(&[]).is_some();
        if is_f32 && c.min(o) >= WINOGRAD_MIN_CHANNELS && c + o >= WINOGRAD_MIN_CHANNEL_SUM {
            ConvAlgorithm::Winograd
        } else {
            ConvAlgorithm::Direct
        }
    }
}

/// Runs `f` with every 3x3 convolution it starts on this thread (forward, input gradient and
/// weight gradient) computed by `algorithm`, whatever the precision and channel counts
/// (restoring the previous choice afterwards, also on panic). Convolutions started on other
/// threads keep their own.
pub fn with_algorithm<R>(algorithm: ConvAlgorithm, f: impl FnOnce() -> R) -> R {
    struct Restore(Option<ConvAlgorithm>);
    impl Drop for Restore {
        fn drop(&mut self) {
            ALGORITHM.with(|a| a.set(self.0));
        }
    }
    let _restore = Restore(ALGORITHM.with(|a| a.replace(Some(algorithm))));
    f()
}

/// The algorithm a 3x3 convolution of `c` to `o` channels started on this thread uses.
pub fn algorithm_for<T: Real>(c: usize, o: usize) -> ConvAlgorithm {
    ALGORITHM
        .with(|a| a.get())
        .unwrap_or_else(|| ConvAlgorithm::default_for::<T>(c, o))
}

/// The tiles `(image, first row, last row + 1)` of an output of `n` images of `h_out` rows.
fn tiles(n: usize, h_out: usize, rows: usize) -> Vec<(usize, usize, usize)> {
    let mut v = Vec::new();
    for img in 0..n {
        let mut r0 = 0;
        while r0 < h_out {
            let r1 = (r0 + rows).min(h_out);
            v.push((img, r0, r1));
            r0 = r1;
        }
    }
    v
}

/// Rows per tile of the implicit GEMM: at most [`TILE_PIXELS`] pixels on the padded grid and an
/// accumulator of at most [`ACC_BUDGET_BYTES`] (at least one row).
fn rows_per_implicit_tile<T>(o: usize, wp: usize, h_out: usize) -> usize {
    let by_pixels = TILE_PIXELS / wp.max(1);
    let by_memory = ACC_BUDGET_BYTES / (o * wp * std::mem::size_of::<T>()).max(1);
    by_pixels.min(by_memory).clamp(1, h_out.max(1))
}

/// Valid cross-correlation of a padded input `xp [N,C,Hp,Wp]` with `w [O,C,K,K]`, plus an
/// optional bias, optionally followed by ReLU. Output `[N, O, Hp-K+1, Wp-K+1]`.
///
/// For `K > 1` this is an implicit GEMM: output rows are computed on the padded grid (width
/// `Wp`, the last `K-1` columns of each row being discarded), where the input window of tap
/// `(i, j)` is the padded plane shifted by `i*Wp + j`, a plain strided matrix. Each tile then
/// accumulates `K*K` products `w[:, :, i, j] (O x C) * shifted input (C x tile)` into an
/// `O x tile` accumulator in a fixed tap order, and copies the valid columns out, adding the bias
/// and applying the ReLU. No im2col buffer is formed.
pub(crate) fn conv_valid<T: Real>(
    xp: ArrayView4<T>,
    w: ArrayView4<T>,
    bias: Option<ArrayView1<T>>,
    relu: bool,
    guard: bool,
    backend: GemmBackend,
) -> Array4<T> {
    let (n, c, hp, wp) = xp.dim();
    let (o, wc, k, k2) = w.dim();
    assert_eq!(wc, c, "conv: weight has {wc} input channels, input has {c}");
    assert_eq!(k, k2, "conv: kernel must be square");
    assert!(
        hp >= k && wp >= k,
        "conv: input {hp}x{wp} smaller than kernel {k}"
    );
    let (h_out, w_out) = (hp - k + 1, wp - k + 1);
    let xp = xp.as_standard_layout();
    let w = w.as_standard_layout();
    let xs = xp.as_slice().expect("standard layout");
    let ws = w.as_slice().expect("standard layout");
    let bias: Option<Vec<T>> = bias.map(|b| b.to_vec());
    if let Some(b) = &bias {
        assert_eq!(
            b.len(),
            o,
            "conv: bias has {} entries for {o} outputs",
            b.len()
        );
    }
    if k == 3 && algorithm_for::<T>(c, o) == ConvAlgorithm::Winograd {
        return crate::winograd::conv3x3_valid(
            xs,
            [n, c, hp, wp],
            ws,
            o,
            bias.as_deref(),
            relu,
            guard,
            backend,
        );
    }
    let ckk = c * k * k;
    let mut out = zeroed::<T>((n, o, h_out, w_out));
    let out_ptr = SyncPtr(out.as_mut_ptr());
    let rows = rows_per_implicit_tile::<T>(o, wp, h_out);
    let jobs = tiles(n, h_out, rows);
    let plane_in = hp * wp;
    let plane_out = h_out * w_out;
    // Accumulators are recycled through a pool, so at most one per running task exists.
    let pool: Mutex<Vec<Vec<T>>> = Mutex::new(Vec::new());
    jobs.par_iter().for_each(|&(img, r0, r1)| {
        let x_img = &xs[img * c * plane_in..(img + 1) * c * plane_in];
        // SAFETY (whole block): the tile writes rows r0..r1 of every output channel of image
        // `img`, which no other tile touches. Tap (i, j) reads padded-plane elements
        // (r0+i)*wp + j + p for p < np = (r1-r0)*wp - (k-1), whose largest index is
        // (r1-1+i)*wp + j + wp - k <= hp*wp - 1 since r1 <= hp-k+1, i, j <= k-1: inside the plane.
        unsafe {
            let c_out = out_ptr.get().add(img * o * plane_out + r0 * w_out);
            if k == 1 {
                // The input rows are the GEMM operand and the output rows its result.
                let px = (r1 - r0) * w_out;
                matmul(
                    backend,
                    o,
                    c,
                    px,
                    (ws.as_ptr(), c as isize, 1),
                    (x_img[r0 * wp..].as_ptr(), plane_in as isize, 1),
                    false,
                    (c_out, plane_out as isize, 1),
                );
                for oc in 0..o {
                    let row = std::slice::from_raw_parts_mut(c_out.add(oc * plane_out), px);
                    let b = bias.as_ref().map_or(T::zero(), |b| b[oc]);
                    for v in row.iter_mut() {
                        *v = bias_relu(*v, b, relu);
                    }
                }
            } else {
                let np = (r1 - r0) * wp - (k - 1);
                let mut acc = pool
                    .lock()
                    .ok()
                    .and_then(|mut p| p.pop())
                    .unwrap_or_default();
                acc.resize(o * np, T::zero());
                for i in 0..k {
                    for j in 0..k {
                        let tap = i * k + j;
                        matmul(
                            backend,
                            o,
                            c,
                            np,
                            (ws.as_ptr().add(tap), ckk as isize, (k * k) as isize),
                            (x_img.as_ptr().add((r0 + i) * wp + j), plane_in as isize, 1),
                            tap != 0,
                            (acc.as_mut_ptr(), np as isize, 1),
                        );
                    }
                }
                for oc in 0..o {
                    let b = bias.as_ref().map_or(T::zero(), |b| b[oc]);
                    for r in 0..r1 - r0 {
                        let dst = std::slice::from_raw_parts_mut(
                            c_out.add(oc * plane_out + r * w_out),
                            w_out,
                        );
                        let src = &acc[oc * np + r * wp..oc * np + r * wp + w_out];
                        for (d, &v) in dst.iter_mut().zip(src) {
                            *d = bias_relu(v, b, relu);
                        }
                    }
                }
                if let Ok(mut p) = pool.lock() {
                    p.push(acc);
                }
            }
        }
    });
    out
}

/// Gradients of a valid cross-correlation with respect to its weights and bias, given the padded
/// input `xp [N,C,Hp,Wp]`, the output gradient `dy [N,O,Hp-K+1,Wp-K+1]` and the kernel size.
pub(crate) fn conv_valid_param_grads<T: Real>(
    xp: ArrayView4<T>,
    dy: ArrayView4<T>,
    k: usize,
    backend: GemmBackend,
) -> (Array4<T>, Array1<T>) {
    let (n, c, hp, wp) = xp.dim();
    let (dn, o, h_out, w_out) = dy.dim();
    assert_eq!(dn, n, "conv grads: batch sizes differ");
    assert_eq!(
        (h_out, w_out),
        (hp - k + 1, wp - k + 1),
        "conv grads: output gradient has the wrong size"
    );
    let xp = xp.as_standard_layout();
    let dy = dy.as_standard_layout();
    let xs = xp.as_slice().expect("standard layout");
    let dys = dy.as_slice().expect("standard layout");
    let db = bias_grad(dys, n, o, h_out * w_out);
    let dw = if k == 3 && algorithm_for::<T>(c, o) == ConvAlgorithm::Winograd {
        crate::winograd::conv3x3_valid_weight_grad(xs, [n, c, hp, wp], dys, o, DW_GROUPS, backend)
    } else {
        weight_grad_implicit(xs, [n, c, hp, wp], dys, o, k, backend)
    };
    (Array4::from_shape_vec((o, c, k, k), dw).expect("shape"), db)
}

/// The bias gradient: the sum of `dy [N,O,H,W]` (as a slice) over images and pixels, per channel.
fn bias_grad<T: Real>(dys: &[T], n: usize, o: usize, plane_out: usize) -> Array1<T> {
    let db: Vec<T> = (0..o)
        .into_par_iter()
        .map(|oc| {
            let mut acc = T::zero();
            for img in 0..n {
                let start = (img * o + oc) * plane_out;
                acc += dys[start..start + plane_out].iter().copied().sum::<T>();
            }
            acc
        })
        .collect();
    Array1::from_vec(db)
}

/// Weight gradient `[O, C, K, K]` (flat) of a valid `K x K` cross-correlation, by implicit GEMM:
/// with `dY` widened to the padded width (`K-1` zero columns per row, `dyp`; `dY` itself for `K = 1`),
/// tap `(i, j)` is `dW[:, :, i, j] += dyp_tile (O x np) * X_ij^T (np x C)`, where `X_ij` is the
/// padded input plane shifted by `i*Wp + j` (as in [`conv_valid`]); the zero columns cancel the
/// products with the wrapped-around pixels. Tiles are split into [`DW_GROUPS`] fixed contiguous
/// groups run in parallel, each accumulating its tiles in order into its own `[K*K, O, C]`
/// buffer; the group buffers are then summed in group order. Neither depends on the thread count.
fn weight_grad_implicit<T: Real>(
    xs: &[T],
    dims: [usize; 4],
    dys: &[T],
    o: usize,
    k: usize,
    backend: GemmBackend,
) -> Vec<T> {
    let [n, c, hp, wp] = dims;
    let (h_out, w_out) = (hp - k + 1, wp - k + 1);
    let plane_in = hp * wp;
    let plane_dyp = h_out * wp;
    let widened: Vec<T>;
    let dyp = if k == 1 {
        dys
    } else {
        let mut d = vec![T::zero(); n * o * plane_dyp];
        d.par_chunks_mut(plane_dyp)
            .zip(dys.par_chunks(h_out * w_out))
            .for_each(|(d, s)| {
                for (dr, sr) in d.chunks_mut(wp).zip(s.chunks(w_out)) {
                    dr[..w_out].copy_from_slice(sr);
                }
            });
        widened = d;
        &widened
    };
    let rows = (TILE_PIXELS / wp).clamp(1, h_out.max(1));
    let jobs = tiles(n, h_out, rows);
    let groups = DW_GROUPS.min(jobs.len());
    let taps = k * k;
    let partials: Vec<Vec<T>> = in_fixed_groups(&jobs, groups, |group| {
        let mut acc = vec![T::zero(); taps * o * c];
        for &(img, r0, r1) in group {
            let np = (r1 - r0) * wp - (k - 1);
            let x_img = &xs[img * c * plane_in..(img + 1) * c * plane_in];
            let dy_tile = &dyp[img * o * plane_dyp + r0 * wp..];
            for i in 0..k {
                for j in 0..k {
                    // SAFETY: `dy_tile` holds rows r0..r1 of all O channels of image `img`
                    // (largest index (o-1)*plane_dyp + np - 1 < its length); the shifted
                    // input reads stay inside the padded plane as shown in `conv_valid`;
                    // `acc` is this group's own buffer, of O x C per tap.
                    unsafe {
                        matmul(
                            backend,
                            o,
                            np,
                            c,
                            (dy_tile.as_ptr(), plane_dyp as isize, 1),
                            (x_img.as_ptr().add((r0 + i) * wp + j), 1, plane_in as isize),
                            true,
                            (acc.as_mut_ptr().add((i * k + j) * o * c), c as isize, 1),
                        );
                    }
                }
            }
        }
        acc
    });
    // dw[o][c][tap] = sum over groups, in order, of partial[tap][o][c].
    let mut dw = vec![T::zero(); o * c * taps];
    dw.par_chunks_mut(c * taps)
        .enumerate()
        .for_each(|(oc, row)| {
            for (ci, cell) in row.chunks_mut(taps).enumerate() {
                for (tap, v) in cell.iter_mut().enumerate() {
                    *v = sum_in_order(&partials, (tap * o + oc) * c + ci);
                }
            }
        });
    dw
}

/// Reflection padding by one pixel on both spatial axes (`F.pad(x, (1,1,1,1), mode="reflect")`).
///
/// # Panics
/// If the height or width is below 2 (reflection needs a neighbour to mirror).
pub fn pad_reflect1<T: Real>(x: ArrayView4<T>) -> Array4<T> {
    let (n, c, h, w) = x.dim();
    assert!(
        h >= 2 && w >= 2,
        "reflection padding needs at least 2x2 pixels, got {h}x{w}"
    );
    let x = x.as_standard_layout();
    let xs = x.as_slice().expect("standard layout");
    // Padded row `r` copies input row `1` (r = 0), `r - 1` or `h - 2` (r = h + 1); within it,
    // column 0 copies input column 1 and column w + 1 input column w - 2.
    by_planes((n, c, h + 2, w + 2), |i, j, mut o| {
        let xc = &xs[(i * c + j) * h * w..][..h * w];
        let o = o.as_slice_mut().expect("a fresh plane is contiguous");
        for (r, row) in o.chunks_exact_mut(w + 2).enumerate() {
            let y = match r {
                0 => 1,
                r if r == h + 1 => h - 2,
                r => r - 1,
            };
            let src = &xc[y * w..][..w];
            row[0].write(src[1]);
            row[w + 1].write(src[w - 2]);
            for (d, &v) in row[1..w + 1].iter_mut().zip(src) {
                d.write(v);
            }
        }
    })
}

/// Zero padding by `p` pixels on both spatial axes.
fn pad_zero<T: Real>(x: ArrayView4<T>, p: usize) -> Array4<T> {
    let (n, c, h, w) = x.dim();
    let x = x.as_standard_layout();
    let xs = x.as_slice().expect("standard layout");
    let wp = w + 2 * p;
    by_planes((n, c, h + 2 * p, wp), |i, j, mut o| {
        let xc = &xs[(i * c + j) * h * w..][..h * w];
        let o = o.as_slice_mut().expect("a fresh plane is contiguous");
        for (r, row) in o.chunks_exact_mut(wp).enumerate() {
            if r < p || r >= p + h {
                row.fill(MaybeUninit::new(T::zero()));
                continue;
            }
            row[..p].fill(MaybeUninit::new(T::zero()));
            row[p + w..].fill(MaybeUninit::new(T::zero()));
            for (d, &v) in row[p..p + w].iter_mut().zip(&xc[(r - p) * w..][..w]) {
                d.write(v);
            }
        }
    })
}

/// The adjoint of [`pad_reflect1`]: folds the gradient of a reflection-padded tensor
/// `[N,C,H+2,W+2]` back onto the `[N,C,H,W]` pixels the border was copied from.
fn fold_reflect1<T: Real>(gp: Array4<T>) -> Array4<T> {
    let (n, c, hp, wp) = gp.dim();
    let (h, w) = (hp - 2, wp - 2);
    let gp = gp.as_standard_layout();
    let gs = gp.as_slice().expect("standard layout");
    by_planes((n, c, h, w), |i, j, mut out| {
        let g = &gs[(i * c + j) * hp * wp..][..hp * wp];
        let out = out.as_slice_mut().expect("a fresh plane is contiguous");
        // Rows first on padded columns: padded row 0 mirrors input row 1, row h+1 mirrors
        // input row h-2 (added after row 0 when both are row 1); `summed` holds such a row.
        let mut summed = vec![T::zero(); wp];
        for (r, dst) in out.chunks_exact_mut(w).enumerate() {
            let mut src = &g[(r + 1) * wp..(r + 2) * wp];
            if r == 1 || r == h - 2 {
                summed.copy_from_slice(src);
                if r == 1 {
                    for (s, &t) in summed.iter_mut().zip(&g[..wp]) {
                        *s += t;
                    }
                }
                if r == h - 2 {
                    for (s, &b) in summed.iter_mut().zip(&g[(h + 1) * wp..]) {
                        *s += b;
                    }
                }
                src = &summed;
            }
            // Then the columns: column q takes padded column q + 1, column 1 adds padded
            // column 0 and column w - 2 padded column w + 1, in that order (both when w = 3).
            for (d, &v) in dst.iter_mut().zip(&src[1..w + 1]) {
                d.write(v);
            }
            let mut first = src[2] + src[0];
            if w == 3 {
                first += src[w + 1];
            } else {
                dst[w - 2].write(src[w - 1] + src[w + 1]);
            }
            dst[1].write(first);
        }
    })
}

/// A zeroed `[N,C,H,W]` array, its planes zeroed in parallel (`Array4::zeros` clears the whole
/// block on the calling thread; a convolution's output is tens of megabytes).
pub(crate) fn zeroed<T: Real>(dim: (usize, usize, usize, usize)) -> Array4<T> {
    by_planes(dim, |_, _, mut plane| {
        plane.fill(MaybeUninit::new(T::zero()))
    })
}

/// A `[N,C,H,W]` array whose `[H,W]` planes are written by `fill(n, c, plane)`, the planes in
/// parallel. `fill` must write every element of the plane it is given: the array is returned
/// as initialised without being zeroed first (padding, folding and upsampling overwrite every
/// element, and zeroing a large tensor first costs a pass over its memory on one thread).
pub(crate) fn by_planes<T: Real>(
    dim: (usize, usize, usize, usize),
    fill: impl Fn(usize, usize, ArrayViewMut2<MaybeUninit<T>>) + Sync,
) -> Array4<T> {
    let (n, c, h, w) = dim;
    let mut out = Array4::<T>::uninit(dim);
    out.view_mut()
        .into_shape_with_order((n * c, h, w))
        .expect("a fresh array is contiguous")
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(p, plane)| fill(p / c, p % c, plane));
    // SAFETY: every caller's `fill` writes each element of its plane (the planes partition the
    // array), so every element is initialised here.
    unsafe { out.assume_init() }
}

/// The kernel of the input gradient: `wt[c,o,i,j] = w[o,c,K-1-i,K-1-j]`.
/// Flipping both kernel axes reverses each `K x K` block of taps: tap `(K-1-i, K-1-j)` is
/// `K*K - 1 - (i K + j)` in the block.
fn flip_transpose<T: Real>(w: ArrayView4<T>) -> Array4<T> {
    let (o, c, k, _) = w.dim();
    let kk = k * k;
    let w = w.as_standard_layout();
    let src = w.as_slice().expect("a standard-layout array is contiguous");
    let mut out = Vec::with_capacity(c * o * kk);
    for ci in 0..c {
        for oi in 0..o {
            out.extend(src[(oi * c + ci) * kk..][..kk].iter().rev());
        }
    }
    Array4::from_shape_vec((c, o, k, k), out).expect("length is c*o*k*k")
}

fn check_3x3(w: &ArrayView4<impl Real>) {
    let (_, _, kh, kw) = w.dim();
    assert!(kh == 3 && kw == 3, "expected a 3x3 kernel, got {kh}x{kw}");
}

fn check_1x1(w: &ArrayView4<impl Real>) {
    let (_, _, kh, kw) = w.dim();
    assert!(kh == 1 && kw == 1, "expected a 1x1 kernel, got {kh}x{kw}");
}

/// 3x3 convolution with reflection padding 1: `x [N,C,H,W]`, `w [O,C,3,3]`, `b [O]` to
/// `[N,O,H,W]`, optionally followed by ReLU.
///
/// # Panics
/// On inconsistent shapes or `H < 2` or `W < 2`.
pub fn conv3x3_reflect<T: Real>(
    x: ArrayView4<T>,
    w: ArrayView4<T>,
    b: ArrayView1<T>,
    relu: bool,
) -> Array4<T> {
    conv3x3_reflect_with(x, w, b, relu, false)
}

/// [`conv3x3_reflect`] followed by a ReLU that decides as the exact sum would: under
/// [`ConvAlgorithm::Winograd`], every pre-activation within the algorithm's rounding-error bound
/// of zero is recomputed by the direct sum in `f64` (see "ReLU decisions" in
/// [`crate::winograd`]). The direct algorithm decides on its own rounded sum. Forward passes
/// that record a tape for a backward pass use it: their ReLU decisions are the gradient's masks.
pub fn conv3x3_reflect_exact_relu<T: Real>(
    x: ArrayView4<T>,
    w: ArrayView4<T>,
    b: ArrayView1<T>,
) -> Array4<T> {
    conv3x3_reflect_with(x, w, b, true, true)
}

/// [`conv3x3_reflect`], with the guard of [`conv3x3_reflect_exact_relu`] when `guard`.
pub(crate) fn conv3x3_reflect_with<T: Real>(
    x: ArrayView4<T>,
    w: ArrayView4<T>,
    b: ArrayView1<T>,
    relu: bool,
    guard: bool,
) -> Array4<T> {
    conv3x3_reflect_padded(x, w, b, relu, guard).0
}

/// [`conv3x3_reflect_with`], also returning the reflection-padded input it convolved, which
/// [`conv3x3_padded_backward_params`] takes.
pub(crate) fn conv3x3_reflect_padded<T: Real>(
    x: ArrayView4<T>,
    w: ArrayView4<T>,
    b: ArrayView1<T>,
    relu: bool,
    guard: bool,
) -> (Array4<T>, Array4<T>) {
    check_3x3(&w);
    let xp = pad_reflect1(x);
    let y = conv_valid(
        xp.view(),
        w,
        Some(b),
        relu,
        guard,
        backend_for(Pass::Forward),
    );
    (y, xp)
}

/// Input gradient of [`conv3x3_reflect`] (without ReLU) given the output gradient `dy [N,O,H,W]`.
pub fn conv3x3_reflect_backward_input<T: Real>(dy: ArrayView4<T>, w: ArrayView4<T>) -> Array4<T> {
    check_3x3(&w);
    let (_, _, h, wd) = dy.dim();
    assert!(
        h >= 2 && wd >= 2,
        "reflection padding needs at least 2x2 pixels, got {h}x{wd}"
    );
    let dxp = conv_valid(
        pad_zero(dy, 2).view(),
        flip_transpose(w).view(),
        None,
        false,
        false,
        backend_for(Pass::InputGrad),
    );
    fold_reflect1(dxp)
}

/// Weight and bias gradients of [`conv3x3_reflect`] (without ReLU) given its input `x` and the
/// output gradient `dy`. Returns `([O,C,3,3], [O])`.
pub fn conv3x3_reflect_backward_params<T: Real>(
    x: ArrayView4<T>,
    dy: ArrayView4<T>,
) -> (Array4<T>, Array1<T>) {
    conv3x3_padded_backward_params(pad_reflect1(x).view(), dy)
}

/// [`conv3x3_reflect_backward_params`] given the reflection-padded input `xp [N,C,H+2,W+2]`
/// (as [`conv3x3_reflect_padded`] returns it) instead of the input.
pub(crate) fn conv3x3_padded_backward_params<T: Real>(
    xp: ArrayView4<T>,
    dy: ArrayView4<T>,
) -> (Array4<T>, Array1<T>) {
    conv_valid_param_grads(xp, dy, 3, backend_for(Pass::WeightGrad))
}

/// 1x1 convolution: `x [N,C,H,W]`, `w [O,C,1,1]`, `b [O]` to `[N,O,H,W]`, optionally followed by
/// ReLU.
pub fn conv1x1<T: Real>(
    x: ArrayView4<T>,
    w: ArrayView4<T>,
    b: ArrayView1<T>,
    relu: bool,
) -> Array4<T> {
    check_1x1(&w);
    conv_valid(x, w, Some(b), relu, false, backend_for(Pass::Forward))
}

/// Input gradient of [`conv1x1`] (without ReLU).
pub fn conv1x1_backward_input<T: Real>(dy: ArrayView4<T>, w: ArrayView4<T>) -> Array4<T> {
    check_1x1(&w);
    conv_valid(
        dy,
        flip_transpose(w).view(),
        None,
        false,
        false,
        backend_for(Pass::InputGrad),
    )
}

/// Weight and bias gradients of [`conv1x1`] (without ReLU). Returns `([O,C,1,1], [O])`.
pub fn conv1x1_backward_params<T: Real>(
    x: ArrayView4<T>,
    dy: ArrayView4<T>,
) -> (Array4<T>, Array1<T>) {
    conv_valid_param_grads(x, dy, 1, backend_for(Pass::WeightGrad))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flip_transpose_follows_its_index_rule_for_any_layout() {
        for (o, c, k) in [(3, 2, 3), (1, 4, 1), (2, 5, 3)] {
            let w = Array4::from_shape_fn((o, c, k, k), |(a, b, i, j)| {
                (((a * 7 + b) * 5 + i) * 3 + j) as f64
            });
            // The same values through a transposed (non-standard) view.
            let wt = w.clone().permuted_axes([1, 0, 2, 3]);
            let swapped = wt.view().permuted_axes([1, 0, 2, 3]);
            for view in [w.view(), swapped] {
                let f = flip_transpose(view);
                assert_eq!(f.dim(), (c, o, k, k));
                for ((ci, oi, i, j), &v) in f.indexed_iter() {
                    assert_eq!(v, w[[oi, ci, k - 1 - i, k - 1 - j]]);
                }
            }
        }
    }

    /// Reflection about the edge pixel without repeating it, as `F.pad(.., mode="reflect")`:
    /// padded index `-1` reads `1`, padded index `len` reads `len - 2`.
    fn reflect(i: isize, len: usize) -> usize {
        match i {
            -1 => 1,
            i if i == len as isize => len - 2,
            i => i as usize,
        }
    }

    /// Inputs of several batch and channel counts, down to 2x2, in standard and transposed
    /// layouts, with distinct integer values.
    fn inputs() -> Vec<Array4<f64>> {
        let mut out = Vec::new();
        for (n, c, h, w) in [
            (1, 1, 2, 2),
            (2, 3, 2, 5),
            (1, 4, 6, 3),
            (3, 2, 7, 9),
            (1, 2, 3, 3),
        ] {
            let x = Array4::from_shape_fn((n, c, h, w), |(a, b, i, j)| {
                (((a * 7 + b) * 11 + i) * 13 + j) as f64
            });
            out.push(x.clone());
            // The same values through a non-standard layout.
            let t = x
                .permuted_axes([1, 0, 3, 2])
                .as_standard_layout()
                .to_owned();
            out.push(t.permuted_axes([1, 0, 3, 2]));
        }
        out
    }

    #[test]
    fn padding_follows_its_index_rule_for_any_shape_and_layout() {
        for x in inputs() {
            let (n, c, h, w) = x.dim();
            let r = pad_reflect1(x.view());
            assert_eq!(r.dim(), (n, c, h + 2, w + 2));
            for ((a, b, i, j), &v) in r.indexed_iter() {
                let (si, sj) = (reflect(i as isize - 1, h), reflect(j as isize - 1, w));
                assert_eq!(v, x[[a, b, si, sj]], "reflect at {:?}", (a, b, i, j));
            }
            for p in [1, 2] {
                let z = pad_zero(x.view(), p);
                assert_eq!(z.dim(), (n, c, h + 2 * p, w + 2 * p));
                for ((a, b, i, j), &v) in z.indexed_iter() {
                    let inside = (p..p + h).contains(&i) && (p..p + w).contains(&j);
                    let want = if inside { x[[a, b, i - p, j - p]] } else { 0.0 };
                    assert_eq!(v, want, "zero pad {p} at {:?}", (a, b, i, j));
                }
            }
        }
    }

    /// `fold_reflect1` is the adjoint of `pad_reflect1`: `<pad(x), g> = <x, fold(g)>` for every
    /// `x` and `g`; with integer values both sides are exact sums.
    #[test]
    fn folding_is_the_adjoint_of_reflection_padding() {
        for x in inputs() {
            let (n, c, h, w) = x.dim();
            let g = Array4::from_shape_fn((n, c, h + 2, w + 2), |(a, b, i, j)| {
                ((a * 3 + b * 5 + i * 7 + j * 11) % 17) as f64 - 8.0
            });
            let lhs = (&pad_reflect1(x.view()) * &g).sum();
            let folded = fold_reflect1(g.clone());
            assert_eq!(folded.dim(), x.dim());
            assert_eq!(lhs, (&x * &folded).sum());
        }
    }

    /// Element by element: `fold(g)` at a pixel is `<pad(e), g>` for the one-hot input `e` of
    /// that pixel (integer values, so exact), at every size of `inputs`, the smallest included.
    #[test]
    fn folding_gathers_every_padded_copy_of_each_pixel() {
        for x in inputs() {
            let (n, c, h, w) = x.dim();
            let g = Array4::from_shape_fn((n, c, h + 2, w + 2), |(a, b, i, j)| {
                ((a * 5 + b * 3 + i * 11 + j * 7) % 19) as f64 - 9.0
            });
            let folded = fold_reflect1(g.clone());
            for ((a, b, i, j), &v) in folded.indexed_iter() {
                let mut e = Array4::<f64>::zeros((n, c, h, w));
                e[[a, b, i, j]] = 1.0;
                assert_eq!(
                    v,
                    (&pad_reflect1(e.view()) * &g).sum(),
                    "{:?}",
                    (a, b, i, j)
                );
            }
        }
    }
}
