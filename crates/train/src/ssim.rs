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
    let stats = Stats::new(x, y, shape);
    Ok(mean_f64(&stats.ssim_map()))
}

/// Mean SSIM of `x` against `y` and its gradient with respect to `x` (`y` is the constant target).
pub fn ssim_with_grad<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
) -> Result<SsimGrad<T>, TrainError> {
    shape.check("ssim: first image", x.len())?;
    shape.check("ssim: second image", y.len())?;
    let stats = Stats::new(x, y, shape);
    let map = stats.ssim_map();
    let value = mean_f64(&map);

    // Per pixel, with A = 2 mu_x mu_y + C1, B = 2 s_xy + C2, C = mu_x^2 + mu_y^2 + C1,
    // D = s_xx + s_yy + C2 and S = AB / (CD), the partials of S with respect to the three blurred
    // maps that depend on x (mu_x, E_xx = G*(xx), E_xy = G*(xy)) are
    //   dS/dmu_x = 2 mu_y (dS/dA - dS/dB) + 2 mu_x (dS/dC - dS/dD)
    //   dS/dE_xx = dS/dD,   dS/dE_xy = 2 dS/dB.
    let n = stats.mu_x.len();
    let inv_m = T::lit(1.0 / n as f64);
    let c1 = T::lit(C1);
    let c2 = T::lit(C2);
    let two = T::lit(2.0);
    let mut g_mu = vec![T::zero(); n];
    let mut g_exx = vec![T::zero(); n];
    let mut g_exy = vec![T::zero(); n];
    let w = shape.width;
    g_mu.par_chunks_mut(w)
        .zip(g_exx.par_chunks_mut(w))
        .zip(g_exy.par_chunks_mut(w))
        .enumerate()
        .for_each(|(row, ((gm, gxx), gxy))| {
            for i in 0..w {
                let k = row * w + i;
                let (mx, my) = (stats.mu_x[k], stats.mu_y[k]);
                let sxx = stats.e_xx[k] - mx * mx;
                let syy = stats.e_yy[k] - my * my;
                let sxy = stats.e_xy[k] - mx * my;
                let a = two * mx * my + c1;
                let b = two * sxy + c2;
                let c = mx * mx + my * my + c1;
                let d = sxx + syy + c2;
                let cd = c * d;
                let ds_da = b / cd;
                let ds_db = a / cd;
                let s = a * b / cd;
                let ds_dc = -s / c;
                let ds_dd = -s / d;
                gm[i] = inv_m * (two * my * (ds_da - ds_db) + two * mx * (ds_dc - ds_dd));
                gxx[i] = inv_m * ds_dd;
                gxy[i] = inv_m * two * ds_db;
            }
        });

    // The zero-padded correlation with a symmetric window is its own transpose.
    let taps = taps::<T>();
    let planes_h = shape.channels * shape.height;
    let b_mu = blur(&g_mu, w, shape.height, planes_h, &taps);
    let b_xx = blur(&g_exx, w, shape.height, planes_h, &taps);
    let b_xy = blur(&g_exy, w, shape.height, planes_h, &taps);

    let xp = &stats.x;
    let yp = &stats.y;
    let grad_planar: Vec<T> = (0..n)
        .into_par_iter()
        .map(|k| b_mu[k] + two * xp[k] * b_xx[k] + yp[k] * b_xy[k])
        .collect();
    Ok(SsimGrad {
        value,
        grad_x: from_planar(&grad_planar, shape),
    })
}

/// The five blurred maps, planar (`C` planes of `H x W`).
struct Stats<T> {
    x: Vec<T>,
    y: Vec<T>,
    mu_x: Vec<T>,
    mu_y: Vec<T>,
    e_xx: Vec<T>,
    e_yy: Vec<T>,
    e_xy: Vec<T>,
}

impl<T: Real> Stats<T> {
    fn new(x: &[T], y: &[T], shape: ImageShape) -> Self {
        let x = to_planar(x, shape);
        let y = to_planar(y, shape);
        let xx: Vec<T> = x.par_iter().map(|&v| v * v).collect();
        let yy: Vec<T> = y.par_iter().map(|&v| v * v).collect();
        let xy: Vec<T> = x.par_iter().zip(&y).map(|(&a, &b)| a * b).collect();
        let taps = taps::<T>();
        let (w, h) = (shape.width, shape.height);
        let rows = shape.channels * h;
        Stats {
            mu_x: blur(&x, w, h, rows, &taps),
            mu_y: blur(&y, w, h, rows, &taps),
            e_xx: blur(&xx, w, h, rows, &taps),
            e_yy: blur(&yy, w, h, rows, &taps),
            e_xy: blur(&xy, w, h, rows, &taps),
            x,
            y,
        }
    }

    fn ssim_map(&self) -> Vec<T> {
        let c1 = T::lit(C1);
        let c2 = T::lit(C2);
        let two = T::lit(2.0);
        (0..self.mu_x.len())
            .into_par_iter()
            .map(|k| {
                let (mx, my) = (self.mu_x[k], self.mu_y[k]);
                let sxx = self.e_xx[k] - mx * mx;
                let syy = self.e_yy[k] - my * my;
                let sxy = self.e_xy[k] - mx * my;
                ((two * mx * my + c1) * (two * sxy + c2))
                    / ((mx * mx + my * my + c1) * (sxx + syy + c2))
            })
            .collect()
    }
}

fn taps<T: Real>() -> [T; WINDOW_SIZE] {
    gaussian_window().map(T::lit)
}

/// Mean of a buffer, accumulated in `f64` per fixed-size chunk, then over chunks in order.
pub(crate) fn mean_f64<T: Real>(v: &[T]) -> f64 {
    sum_f64(v) / v.len() as f64
}

/// Sum of a buffer in `f64`, in a fixed order independent of the thread count.
pub(crate) fn sum_f64<T: Real>(v: &[T]) -> f64 {
    const CHUNK: usize = 4096;
    let partial: Vec<f64> = v
        .par_chunks(CHUNK)
        .map(|c| c.iter().map(|&a| a.to_f64_exact()).sum::<f64>())
        .collect();
    partial.iter().sum()
}

fn to_planar<T: Real>(v: &[T], shape: ImageShape) -> Vec<T> {
    let (c, hw) = (shape.channels, shape.width * shape.height);
    let mut out = vec![T::zero(); v.len()];
    out.par_chunks_mut(hw).enumerate().for_each(|(ch, plane)| {
        for (p, o) in plane.iter_mut().enumerate() {
            *o = v[p * c + ch];
        }
    });
    out
}

fn from_planar<T: Real>(v: &[T], shape: ImageShape) -> Vec<T> {
    let (c, hw) = (shape.channels, shape.width * shape.height);
    let mut out = vec![T::zero(); v.len()];
    out.par_chunks_mut(c).enumerate().for_each(|(p, px)| {
        for (ch, o) in px.iter_mut().enumerate() {
            *o = v[ch * hw + p];
        }
    });
    out
}

/// Zero-padded "same" correlation of `planes` stacked `H x W` planes (`rows = planes * H` rows)
/// with the separable window: a horizontal pass, then a vertical pass within each plane.
///
/// Each output value starts at zero and adds `tap * input` tap by tap in window order, skipping
/// taps outside the image; the passes loop over taps outside and pixels inside, which keeps that
/// order and lets the pixel loop run as vector code (compiled for the instruction set `pulp`
/// picks at run time; the same bits whichever it is).
fn blur<T: Real>(src: &[T], w: usize, h: usize, rows: usize, taps: &[T; WINDOW_SIZE]) -> Vec<T> {
    debug_assert_eq!(src.len(), w * rows);
    let mut horiz = vec![T::zero(); src.len()];
    horiz
        .par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(out, row)| {
            pulp::Arch::new().dispatch(HorizontalPass { out, row, taps });
        });
    let mut out = vec![T::zero(); src.len()];
    out.par_chunks_mut(w).enumerate().for_each(|(r, orow)| {
        let (plane, y) = (r / h, r % h);
        let base = plane * h;
        let horiz = &horiz[base * w..(base + h) * w];
        pulp::Arch::new().dispatch(VerticalPass {
            out: orow,
            plane: horiz,
            y,
            taps,
        });
    });
    out
}

/// `out[x] += tap * src[x + shift]` over the `x` where `src` has that index.
#[inline(always)]
fn add_shifted<T: Real>(out: &mut [T], src: &[T], tap: T, shift: isize) {
    let n = out.len().min(src.len()) as isize;
    let lo = (-shift).clamp(0, n) as usize;
    let hi = (n - shift).clamp(0, n) as usize;
    if lo >= hi {
        return;
    }
    let src = &src[(lo as isize + shift) as usize..(hi as isize + shift) as usize];
    for (o, &s) in out[lo..hi].iter_mut().zip(src) {
        *o += tap * s;
    }
}

/// The horizontal pass of [`blur`] over one row (`out` starts at zero).
struct HorizontalPass<'a, T> {
    out: &'a mut [T],
    row: &'a [T],
    taps: &'a [T; WINDOW_SIZE],
}

impl<T: Real> pulp::WithSimd for HorizontalPass<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        for (k, &t) in self.taps.iter().enumerate() {
            add_shifted(self.out, self.row, t, k as isize - HALF as isize);
        }
    }
}

/// The vertical pass of [`blur`] for row `y` of one `H x W` plane (`out` starts at zero).
struct VerticalPass<'a, T> {
    out: &'a mut [T],
    plane: &'a [T],
    y: usize,
    taps: &'a [T; WINDOW_SIZE],
}

impl<T: Real> pulp::WithSimd for VerticalPass<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let w = self.out.len();
        let h = self.plane.len() / w.max(1);
        for (k, &t) in self.taps.iter().enumerate() {
            let sy = self.y as isize + k as isize - HALF as isize;
            if sy >= 0 && (sy as usize) < h {
                let srow = &self.plane[sy as usize * w..(sy as usize + 1) * w];
                add_shifted(self.out, srow, t, 0);
            }
        }
    }
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
    fn blur_pixel_by_pixel(src: &[f32], w: usize, h: usize, taps: &[f32; WINDOW_SIZE]) -> Vec<f32> {
        let pass =
            |src: &[f32], stride: usize, len: usize, at: &dyn Fn(usize) -> (usize, usize)| {
                let mut out = vec![0.0f32; src.len()];
                for (i, o) in out.iter_mut().enumerate() {
                    let (base, pos) = at(i);
                    let mut acc = 0.0f32;
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

    #[test]
    fn vector_blur_gives_the_bits_of_the_pixel_by_pixel_sums() {
        let taps = taps::<f32>();
        // narrower and wider than the window, several planes
        for (w, h, planes) in [(1, 1, 1), (3, 14, 2), (13, 9, 3), (40, 23, 3)] {
            let src: Vec<f32> = (0..w * h * planes)
                .map(|i| ((i * 7919 % 1013) as f32) / 1013.0 - 0.4)
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
