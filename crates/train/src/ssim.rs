//! Structural similarity (SSIM), forward and exact backward, as the 3DGS trainer computes it.
//!
//! Convention (the `ssim` of the 3DGS code, after Wang et al. 2004): an 11x11 Gaussian window
//! with sigma 1.5, normalised to sum 1, applied per channel as a "same"-size correlation with zero
//! padding (`conv2d(..., padding=5, groups=C)`); `C1 = 0.01^2`, `C2 = 0.03^2` (data range 1); the
//! SSIM map
//!
//! ```text
//! S = (2 mu_x mu_y + C1) (2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1) (s_xx + s_yy + C2))
//! s_xx = G*(x x) - mu_x^2,  s_yy = G*(y y) - mu_y^2,  s_xy = G*(x y) - mu_x mu_y
//! ```
//!
//! is averaged over all channels and pixels. The window is the outer product of a 1-D Gaussian,
//! so the 2-D zero-padded correlation is computed exactly as two 1-D zero-padded passes.
//!
//! Images are row-major, channel-interleaved (`HWC`): value `(y, x, c)` is at `(y * W + x) * C + c`.
//! Rows are processed in parallel; every sum runs in a fixed order, so results are bit-identical
//! for any thread count (and any instruction set of the vectorised blur).

use gaussian::Real;
use rayon::prelude::*;

use crate::error::TrainError;

/// Window side length.
pub const WINDOW_SIZE: usize = 11;
/// Standard deviation of the Gaussian window, in pixels.
pub const WINDOW_SIGMA: f64 = 1.5;
/// Stabiliser of the luminance term, `(0.01 * data_range)^2` with data range 1.
pub const C1: f64 = 0.01 * 0.01;
/// Stabiliser of the contrast-structure term, `(0.03 * data_range)^2`.
pub const C2: f64 = 0.03 * 0.03;

const HALF: usize = WINDOW_SIZE / 2;

/// Width, height and channel count of an interleaved image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageShape {
    /// Pixels per row.
    pub width: usize,
    /// Number of rows.
    pub height: usize,
    /// Values per pixel (3 for RGB).
    pub channels: usize,
}

impl ImageShape {
    /// A shape.
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        ImageShape {
            width,
            height,
            channels,
        }
    }

    /// Number of values, `width * height * channels`.
    pub fn len(&self) -> usize {
        self.width * self.height * self.channels
    }

    /// Whether the image holds no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub(crate) fn check(&self, what: &str, values: usize) -> Result<(), TrainError> {
        if self.is_empty() || values != self.len() {
            return Err(TrainError::Shape(format!(
                "{what} has {values} values, expected a non-empty {}x{}x{} image",
                self.width, self.height, self.channels
            )));
        }
        Ok(())
    }
}

/// The normalised 1-D Gaussian window: `exp(-(i - 5)^2 / (2 sigma^2))` over its sum.
pub fn gaussian_window() -> [f64; WINDOW_SIZE] {
    let mut w = [0.0; WINDOW_SIZE];
    for (i, wi) in w.iter_mut().enumerate() {
        let d = i as f64 - HALF as f64;
        *wi = (-(d * d) / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// SSIM value and its gradient with respect to the first image.
#[derive(Clone, Debug)]
pub struct SsimGrad<T> {
    /// Mean SSIM over all channels and pixels.
    pub value: f64,
    /// `d value / d x`, laid out like `x`.
    pub grad_x: Vec<T>,
}

/// Mean SSIM of `x` against `y`.
pub fn ssim<T: Real>(x: &[T], y: &[T], shape: ImageShape) -> Result<f64, TrainError> {
    shape.check("ssim: first image", x.len())?;
    shape.check("ssim: second image", y.len())?;
    Ok(forward(x, y, shape, false).value)
}

/// Mean SSIM of `x` against `y` and its gradient with respect to `x` (`y` is the constant target).
pub fn ssim_with_grad<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
) -> Result<SsimGrad<T>, TrainError> {
    let (value, grad_x) = ssim_with_grad_map(x, y, shape, |_, _, g| g)?;
    Ok(SsimGrad { value, grad_x })
}

/// Mean SSIM of `x` against `y`, and `f(x_i, y_i, g_i)` for every value `i` (laid out like `x`),
/// where `g = d SSIM / d x`: a caller that combines the gradient with other per-value terms does
/// so in the same pass, without another image-sized buffer.
pub(crate) fn ssim_with_grad_map<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
    f: impl Fn(T, T, T) -> T + Sync,
) -> Result<(f64, Vec<T>), TrainError> {
    shape.check("ssim: first image", x.len())?;
    shape.check("ssim: second image", y.len())?;
    let fwd = forward(x, y, shape, true);
    let (c, w, h) = (shape.channels, shape.width, shape.height);
    let taps = taps::<T>();

    // The zero-padded correlation with a symmetric window is its own transpose: the three
    // partials are blurred like the forward maps, then
    //   dS/dx = G*(dS/dmu_x) + 2 x G*(dS/dE_xx) + y G*(dS/dE_xy).
    let horiz = horizontal_passes::<T, 3>(c * h, w, &taps, |r, m, row| {
        row.copy_from_slice(&fwd.partials[(r * 3 + m) * w..(r * 3 + m + 1) * w]);
    });
    let mut grad = vec![T::zero(); x.len()];
    grad.par_chunks_mut(w * c).enumerate().for_each_init(
        || vec![T::zero(); 3 * w],
        |blurred, (yy, out)| {
            for p in 0..c {
                vertical_passes::<T, 3>(&horiz, w, h, p * h + yy, &taps, blurred);
                base::isa::dispatch(GradientRow {
                    blurred,
                    x: &x[yy * w * c..(yy + 1) * w * c],
                    y: &y[yy * w * c..(yy + 1) * w * c],
                    channel: p,
                    out,
                    f: &f,
                });
            }
        },
    );
    Ok((fwd.value, grad))
}

/// The forward pass of SSIM: its mean and, when asked, the partials of the mean with respect to
/// the three blurred maps that depend on `x`, laid out by planar row `r = channel * H + y` as
/// `[r][map][W]` with maps `dS/dmu_x`, `dS/dE_xx`, `dS/dE_xy` (each divided by the value count).
struct Forward<T> {
    value: f64,
    partials: Vec<T>,
}

/// The five blurred maps `mu_x`, `mu_y`, `E_xx`, `E_yy`, `E_xy` row by row, then per pixel the SSIM
/// map and (with `grads`) its partials. Two passes over the image, each parallel over rows; every
/// value is computed by the same operations in the same order as the textbook sequence of
/// separate blurs (see the tests), so the bits do not depend on the thread count.
fn forward<T: Real>(x: &[T], y: &[T], shape: ImageShape, grads: bool) -> Forward<T> {
    let (c, w, h) = (shape.channels, shape.width, shape.height);
    let n = x.len();
    let rows = c * h;
    let taps = taps::<T>();
    // The planar rows of x, y, x x, y y and x y, each horizontally blurred.
    let horiz = horizontal_passes::<T, 5>(rows, w, &taps, |r, m, row| {
        let (p, yy) = (r / h, r % h);
        let at = |i: usize| (yy * w + i) * c + p;
        match m {
            0 => row.iter_mut().enumerate().for_each(|(i, o)| *o = x[at(i)]),
            1 => row.iter_mut().enumerate().for_each(|(i, o)| *o = y[at(i)]),
            2 => row.iter_mut().enumerate().for_each(|(i, o)| {
                let v = x[at(i)];
                *o = v * v
            }),
            3 => row.iter_mut().enumerate().for_each(|(i, o)| {
                let v = y[at(i)];
                *o = v * v
            }),
            _ => row
                .iter_mut()
                .enumerate()
                .for_each(|(i, o)| *o = x[at(i)] * y[at(i)]),
        }
    });

    let inv_m = T::lit(1.0 / n as f64);
    let mut map = vec![T::zero(); n];
    let mut partials = vec![T::zero(); if grads { 3 * n } else { 0 }];
    let mut partial_rows: Vec<&mut [T]> = if grads {
        partials.chunks_mut(3 * w).collect()
    } else {
        (0..rows).map(|_| &mut [][..]).collect()
    };
    map.par_chunks_mut(w)
        .zip(partial_rows.par_iter_mut())
        .enumerate()
        .for_each_init(
            || vec![T::zero(); 5 * w],
            |blurred, (r, (s_row, g_row))| {
                vertical_passes::<T, 5>(&horiz, w, h, r, &taps, blurred);
                base::isa::dispatch(MapRow {
                    blurred,
                    map: s_row,
                    partials: g_row,
                    inv_m,
                });
            },
        );
    drop(partial_rows);
    Forward {
        value: mean_f64(&map),
        partials,
    }
}

fn taps<T: Real>() -> [T; WINDOW_SIZE] {
    gaussian_window().map(T::lit)
}

/// Mean of a buffer, accumulated in `f64` per fixed-size chunk, then over chunks in order.
pub(crate) fn mean_f64<T: Real>(v: &[T]) -> f64 {
    sum_f64(v) / v.len() as f64
}

/// The chunk of [`sum_f64`] and [`sum_f64_of`]: the order of their sums.
const SUM_CHUNK: usize = 4096;

/// Sum of a buffer in `f64`, in a fixed order independent of the thread count.
pub(crate) fn sum_f64<T: Real>(v: &[T]) -> f64 {
    sum_f64_of(v, v, |a, _| a.to_f64_exact())
}

/// The sum of `f(a_i, b_i)` in the order of [`sum_f64`] (per chunk of [`SUM_CHUNK`] values, then
/// over the chunks), without a buffer of the terms.
pub(crate) fn sum_f64_of<T: Real>(a: &[T], b: &[T], f: impl Fn(T, T) -> f64 + Sync) -> f64 {
    debug_assert_eq!(a.len(), b.len());
    let partial: Vec<f64> = a
        .par_chunks(SUM_CHUNK)
        .zip(b.par_chunks(SUM_CHUNK))
        .map(|(a, b)| a.iter().zip(b).map(|(&x, &y)| f(x, y)).sum::<f64>())
        .collect();
    partial.iter().sum()
}

/// The SSIM map of one planar row from its five blurred maps (`blurred`: `[map][W]`), and with
/// `partials` (`[map][W]`, empty without) the partials of the mean.
struct MapRow<'a, T> {
    blurred: &'a [T],
    map: &'a mut [T],
    partials: &'a mut [T],
    inv_m: T,
}

impl<T: Real> pulp::WithSimd for MapRow<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let w = self.map.len();
        let c1 = T::lit(C1);
        let c2 = T::lit(C2);
        let two = T::lit(2.0);
        let [mu_x, mu_y, e_xx, e_yy, e_xy] =
            [0, 1, 2, 3, 4].map(|k| &self.blurred[k * w..(k + 1) * w]);
        let terms = |i: usize| {
            let (mx, my) = (mu_x[i], mu_y[i]);
            let sxx = e_xx[i] - mx * mx;
            let syy = e_yy[i] - my * my;
            let sxy = e_xy[i] - mx * my;
            let a = two * mx * my + c1;
            let b = two * sxy + c2;
            let c = mx * mx + my * my + c1;
            let d = sxx + syy + c2;
            (mx, my, a, b, c, d)
        };
        if self.partials.is_empty() {
            for (i, s) in self.map.iter_mut().enumerate() {
                let (_, _, a, b, c, d) = terms(i);
                *s = (a * b) / (c * d);
            }
            return;
        }
        // Per pixel, with A = 2 mu_x mu_y + C1, B = 2 s_xy + C2, C = mu_x^2 + mu_y^2 + C1,
        // D = s_xx + s_yy + C2 and S = AB / (CD), the partials of S with respect to the three
        // blurred maps that depend on x (mu_x, E_xx = G*(xx), E_xy = G*(xy)) are
        //   dS/dmu_x = 2 mu_y (dS/dA - dS/dB) + 2 mu_x (dS/dC - dS/dD)
        //   dS/dE_xx = dS/dD,   dS/dE_xy = 2 dS/dB.
        let inv_m = self.inv_m;
        let (g_mu, rest) = self.partials.split_at_mut(w);
        let (g_xx, g_xy) = rest.split_at_mut(w);
        for i in 0..w {
            let (mx, my, a, b, c, d) = terms(i);
            self.map[i] = (a * b) / (c * d);
            let cd = c * d;
            let ds_da = b / cd;
            let ds_db = a / cd;
            let s = a * b / cd;
            let ds_dc = -s / c;
            let ds_dd = -s / d;
            g_mu[i] = inv_m * (two * my * (ds_da - ds_db) + two * mx * (ds_dc - ds_dd));
            g_xx[i] = inv_m * ds_dd;
            g_xy[i] = inv_m * two * ds_db;
        }
    }
}

/// One channel of one image row of the gradient: from the blurred partials (`blurred`:
/// `[map][W]`) and the row's interleaved values of `x` and `y`, `out[k] = f(x, y, dS/dx)` at the
/// channel's values.
struct GradientRow<'a, T, F> {
    blurred: &'a [T],
    x: &'a [T],
    y: &'a [T],
    channel: usize,
    out: &'a mut [T],
    f: &'a F,
}

impl<T: Real, F: Fn(T, T, T) -> T> pulp::WithSimd for GradientRow<'_, T, F> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let w = self.blurred.len() / 3;
        let c = self.x.len() / w.max(1);
        let two = T::lit(2.0);
        let (b_mu, rest) = self.blurred.split_at(w);
        let (b_xx, b_xy) = rest.split_at(w);
        for i in 0..w {
            let k = i * c + self.channel;
            let (xv, yv) = (self.x[k], self.y[k]);
            let g = b_mu[i] + two * xv * b_xx[i] + yv * b_xy[i];
            self.out[k] = (self.f)(xv, yv, g);
        }
    }
}

/// The first half of the zero-padded "same" correlation with the separable window: the
/// horizontal passes over `rows` rows of `M` maps, laid out `[row][map][W]`; `fill(r, m, buf)`
/// writes row `r` of map `m` into `buf`, which is then blurred. [`vertical_passes`] is the second
/// half.
///
/// Each output value of either half starts at zero and adds `tap * input` tap by tap in window
/// order, skipping taps outside the image. The passes keep [`BLOCK`] outputs in registers while
/// they add all their taps (vector code compiled for the instruction set `pulp` picks at run
/// time; the same bits whichever it is). The horizontal pass reads its row from a buffer with
/// [`HALF`] zeros on either side: a tap outside the image then adds `+0` to a sum that started
/// at `+0`, which leaves the sum's bits as they are (in round-to-nearest a sum is `-0` only when
/// both terms are, so a sum started at `+0` never is), so padding and skipping agree.
fn horizontal_passes<T: Real, const M: usize>(
    rows: usize,
    w: usize,
    taps: &[T; WINDOW_SIZE],
    fill: impl Fn(usize, usize, &mut [T]) + Sync,
) -> Vec<T> {
    let mut out = vec![T::zero(); rows * M * w];
    if w == 0 {
        return out;
    }
    out.par_chunks_mut(M * w).enumerate().for_each_init(
        || vec![T::zero(); w + 2 * HALF],
        |padded, (r, maps)| {
            for (m, out) in maps.chunks_mut(w).enumerate() {
                fill(r, m, &mut padded[HALF..HALF + w]);
                base::isa::dispatch(HorizontalPass { out, padded, taps });
            }
        },
    );
    out
}

/// The vertical passes for planar row `r` (plane `r / h`, row `r % h`) of the `M` maps of
/// `horiz` (laid out by [`horizontal_passes`]) into `out` (`[map][W]`), within each plane.
fn vertical_passes<T: Real, const M: usize>(
    horiz: &[T],
    w: usize,
    h: usize,
    r: usize,
    taps: &[T; WINDOW_SIZE],
    out: &mut [T],
) {
    let (plane, y) = (r / h, r % h);
    let plane_rows = &horiz[plane * h * M * w..(plane + 1) * h * M * w];
    // The taps whose source row lies inside the plane.
    let first = HALF.saturating_sub(y);
    let end = WINDOW_SIZE.min(h + HALF - y);
    for (m, out) in out.chunks_mut(w.max(1)).enumerate() {
        let rows: [&[T]; WINDOW_SIZE] = std::array::from_fn(|k| {
            if (first..end).contains(&k) {
                let at = (y + k - HALF) * M * w + m * w;
                &plane_rows[at..at + w]
            } else {
                &[][..]
            }
        });
        base::isa::dispatch(VerticalPass {
            out,
            rows: &rows[first..end],
            taps: &taps[first..end],
        });
    }
}

/// Zero-padded "same" correlation of `planes` stacked `H x W` planes (`rows = planes * H` rows)
/// with the separable window, one map at a time through [`horizontal_passes`] and
/// [`vertical_passes`] (for the tests of the passes).
#[cfg(test)]
fn blur<T: Real>(src: &[T], w: usize, h: usize, rows: usize, taps: &[T; WINDOW_SIZE]) -> Vec<T> {
    debug_assert_eq!(src.len(), w * rows);
    let horiz = horizontal_passes::<T, 1>(rows, w, taps, |r, _, row| {
        row.copy_from_slice(&src[r * w..(r + 1) * w])
    });
    let mut out = vec![T::zero(); src.len()];
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(r, orow)| {
            vertical_passes::<T, 1>(&horiz, w, h, r, taps, orow);
        });
    out
}

/// Outputs per block of the passes (one AVX-512 register of `f32`).
const BLOCK: usize = 16;

/// The horizontal pass over one row: `out[x] = sum over k of taps[k] * padded[x + k]`, from
/// zero in tap order, with `padded` the row with [`HALF`] zeros on either side.
struct HorizontalPass<'a, T> {
    out: &'a mut [T],
    padded: &'a [T],
    taps: &'a [T; WINDOW_SIZE],
}

impl<T: Real> pulp::WithSimd for HorizontalPass<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let HorizontalPass { out, padded, taps } = self;
        for x0 in block_starts(out.len()) {
            let mut acc = [T::zero(); BLOCK];
            for (k, &t) in taps.iter().enumerate() {
                let src = &padded[x0 + k..x0 + k + BLOCK];
                for l in 0..BLOCK {
                    acc[l] += t * src[l];
                }
            }
            out[x0..x0 + BLOCK].copy_from_slice(&acc);
        }
        if out.len() < BLOCK {
            for (x, o) in out.iter_mut().enumerate() {
                let mut acc = T::zero();
                for (k, &t) in taps.iter().enumerate() {
                    acc += t * padded[x + k];
                }
                *o = acc;
            }
        }
    }
}

/// The vertical pass for one row: `out[x] = sum over k of taps[k] * rows[k][x]`, from zero in
/// tap order (`rows` and `taps` cut to the taps whose source row is inside the plane).
struct VerticalPass<'a, T> {
    out: &'a mut [T],
    rows: &'a [&'a [T]],
    taps: &'a [T],
}

impl<T: Real> pulp::WithSimd for VerticalPass<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let VerticalPass { out, rows, taps } = self;
        for x0 in block_starts(out.len()) {
            let mut acc = [T::zero(); BLOCK];
            for (row, &t) in rows.iter().zip(taps) {
                let src = &row[x0..x0 + BLOCK];
                for l in 0..BLOCK {
                    acc[l] += t * src[l];
                }
            }
            out[x0..x0 + BLOCK].copy_from_slice(&acc);
        }
        if out.len() < BLOCK {
            for (x, o) in out.iter_mut().enumerate() {
                let mut acc = T::zero();
                for (row, &t) in rows.iter().zip(taps) {
                    acc += t * row[x];
                }
                *o = acc;
            }
        }
    }
}

/// The starts of blocks `x0..x0 + BLOCK` covering `0..n` (none when `n < BLOCK`): every
/// multiple of [`BLOCK`] that fits, then `n - BLOCK` if a tail is left (that last block overlaps
/// the one before and computes their shared outputs again, with the same operations and bits).
#[inline(always)]
fn block_starts(n: usize) -> impl Iterator<Item = usize> {
    let full = if n < BLOCK { 0 } else { n / BLOCK };
    let last = (n >= BLOCK && !n.is_multiple_of(BLOCK)).then(|| n - BLOCK);
    (0..full).map(|b| b * BLOCK).chain(last)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_is_normalised_and_symmetric() {
        let w = gaussian_window();
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for i in 0..WINDOW_SIZE {
            assert_eq!(w[i], w[WINDOW_SIZE - 1 - i]);
        }
        // ratio of neighbouring taps is exp(-(2d+1)/(2 sigma^2))
        assert!((w[6] / w[5] - (-1.0f64 / 4.5).exp()).abs() < 1e-15);
    }

    /// The two passes pixel by pixel, each output value summing its taps in window order.
    fn blur_pixel_by_pixel<T: Real>(
        src: &[T],
        w: usize,
        h: usize,
        taps: &[T; WINDOW_SIZE],
    ) -> Vec<T> {
        let pass = |src: &[T], stride: usize, len: usize, at: &dyn Fn(usize) -> (usize, usize)| {
            let mut out = vec![T::zero(); src.len()];
            for (i, o) in out.iter_mut().enumerate() {
                let (base, pos) = at(i);
                let mut acc = T::zero();
                for (k, &t) in taps.iter().enumerate() {
                    let sp = pos as isize + k as isize - HALF as isize;
                    if sp >= 0 && (sp as usize) < len {
                        acc += t * src[base + sp as usize * stride];
                    }
                }
                *o = acc;
            }
            out
        };
        let horiz = pass(src, 1, w, &|i| (i - i % w, i % w));
        pass(&horiz, w, h, &|i| {
            let (plane, y, x) = (i / (w * h), i / w % h, i % w);
            (plane * w * h + x, y)
        })
    }

    /// SSIM and its gradient the textbook way: planar copies, the five maps blurred pixel by
    /// pixel, the map and the partials per pixel, the partials blurred, the gradient per value.
    fn ssim_reference<T: Real>(x: &[T], y: &[T], shape: ImageShape) -> (f64, Vec<T>) {
        let (c, w, h) = (shape.channels, shape.width, shape.height);
        let n = x.len();
        let planar =
            |v: &[T]| -> Vec<T> { (0..n).map(|k| v[(k % (w * h)) * c + k / (w * h)]).collect() };
        let (xp, yp) = (planar(x), planar(y));
        let taps = taps::<T>();
        let blur = |v: &[T]| blur_pixel_by_pixel(v, w, h, &taps);
        let mu_x = blur(&xp);
        let mu_y = blur(&yp);
        let e_xx = blur(&xp.iter().map(|&v| v * v).collect::<Vec<_>>());
        let e_yy = blur(&yp.iter().map(|&v| v * v).collect::<Vec<_>>());
        let e_xy = blur(&xp.iter().zip(&yp).map(|(&a, &b)| a * b).collect::<Vec<_>>());
        let (c1, c2, two) = (T::lit(C1), T::lit(C2), T::lit(2.0));
        let inv_m = T::lit(1.0 / n as f64);
        let mut map = vec![T::zero(); n];
        let (mut g_mu, mut g_xx, mut g_xy) = (map.clone(), map.clone(), map.clone());
        for k in 0..n {
            let (mx, my) = (mu_x[k], mu_y[k]);
            let sxx = e_xx[k] - mx * mx;
            let syy = e_yy[k] - my * my;
            let sxy = e_xy[k] - mx * my;
            let a = two * mx * my + c1;
            let b = two * sxy + c2;
            let cc = mx * mx + my * my + c1;
            let d = sxx + syy + c2;
            map[k] = (a * b) / (cc * d);
            let s = map[k];
            g_mu[k] =
                inv_m * (two * my * (b / (cc * d) - a / (cc * d)) + two * mx * (-s / cc - -s / d));
            g_xx[k] = inv_m * (-s / d);
            g_xy[k] = inv_m * two * (a / (cc * d));
        }
        let value = map
            .chunks(4096)
            .map(|ch| ch.iter().map(|v| v.to_f64_exact()).sum::<f64>())
            .sum::<f64>()
            / n as f64;
        let (b_mu, b_xx, b_xy) = (blur(&g_mu), blur(&g_xx), blur(&g_xy));
        let mut grad = vec![T::zero(); n];
        for k in 0..n {
            let g = b_mu[k] + two * xp[k] * b_xx[k] + yp[k] * b_xy[k];
            grad[(k % (w * h)) * c + k / (w * h)] = g;
        }
        (value, grad)
    }

    fn check_against_reference<T: Real>() {
        // narrower and wider than the window, one to four channels, more values than one chunk
        // of the f64 sum
        for (w, h, c) in [(1, 1, 1), (3, 14, 2), (13, 9, 3), (40, 23, 3), (70, 31, 4)] {
            let shape = ImageShape::new(w, h, c);
            let n = shape.len();
            let x: Vec<T> = (0..n)
                .map(|i| T::lit(((i * 7919 % 1013) as f64) / 1013.0))
                .collect();
            let y: Vec<T> = (0..n)
                .map(|i| T::lit(((i * 104729 % 997) as f64) / 997.0))
                .collect();
            let (value, grad) = ssim_reference(&x, &y, shape);
            let fast = ssim_with_grad(&x, &y, shape).unwrap();
            let bits = |v: &[T]| {
                v.iter()
                    .map(|a| a.to_f64_exact().to_bits())
                    .collect::<Vec<_>>()
            };
            assert_eq!(fast.value.to_bits(), value.to_bits(), "{w}x{h}x{c}");
            assert_eq!(ssim(&x, &y, shape).unwrap().to_bits(), value.to_bits());
            assert_eq!(bits(&fast.grad_x), bits(&grad), "{w}x{h}x{c}");
        }
    }

    #[test]
    fn fused_passes_give_the_bits_of_the_textbook_sequence_of_blurs() {
        check_against_reference::<f32>();
        check_against_reference::<f64>();
    }

    #[test]
    fn vector_blur_gives_the_bits_of_the_pixel_by_pixel_sums() {
        let taps = taps::<f32>();
        // narrower and wider than the window and the vector block, rows of whole blocks and
        // with a tail, several planes; negative values and negative zeros (a tap outside the
        // image must leave a sum's sign of zero as skipping it would)
        for (w, h, planes) in [
            (1, 1, 1),
            (3, 14, 2),
            (13, 9, 3),
            (16, 5, 1),
            (40, 23, 3),
            (57, 7, 2),
        ] {
            let src: Vec<f32> = (0..w * h * planes)
                .map(|i| match i % 5 {
                    0 => -0.0,
                    _ => ((i * 7919 % 1013) as f32) / 1013.0 - 0.4,
                })
                .collect();
            let fast = blur(&src, w, h, h * planes, &taps);
            let slow = blur_pixel_by_pixel(&src, w, h, &taps);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&slow), "{w}x{h}x{planes}");
        }
    }

    #[test]
    fn separable_blur_equals_the_direct_2d_zero_padded_correlation() {
        let (w, h) = (13, 9);
        let src: Vec<f64> = (0..w * h)
            .map(|i| ((i * 37 % 11) as f64) * 0.1 - 0.3)
            .collect();
        let taps = taps::<f64>();
        let fast = blur(&src, w, h, h, &taps);
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for dy in 0..WINDOW_SIZE {
                    for dx in 0..WINDOW_SIZE {
                        let sy = y as isize + dy as isize - 5;
                        let sx = x as isize + dx as isize - 5;
                        if sy >= 0 && sx >= 0 && (sy as usize) < h && (sx as usize) < w {
                            acc += taps[dy] * taps[dx] * src[sy as usize * w + sx as usize];
                        }
                    }
                }
                assert!((fast[y * w + x] - acc).abs() < 1e-14);
            }
        }
    }
}
