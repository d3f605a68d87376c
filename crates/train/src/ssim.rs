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
//! for any thread count.

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
fn blur<T: Real>(src: &[T], w: usize, h: usize, rows: usize, taps: &[T; WINDOW_SIZE]) -> Vec<T> {
    debug_assert_eq!(src.len(), w * rows);
    let mut horiz = vec![T::zero(); src.len()];
    horiz
        .par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(out, row)| {
            for (x, o) in out.iter_mut().enumerate() {
                let mut acc = T::zero();
                for (k, &t) in taps.iter().enumerate() {
                    let sx = x as isize + k as isize - HALF as isize;
                    if sx >= 0 && (sx as usize) < w {
                        acc += t * row[sx as usize];
                    }
                }
                *o = acc;
            }
        });
    let mut out = vec![T::zero(); src.len()];
    out.par_chunks_mut(w).enumerate().for_each(|(r, orow)| {
        let (plane, y) = (r / h, r % h);
        let base = plane * h;
        for (k, &t) in taps.iter().enumerate() {
            let sy = y as isize + k as isize - HALF as isize;
            if sy >= 0 && (sy as usize) < h {
                let srow = &horiz[(base + sy as usize) * w..(base + sy as usize + 1) * w];
                for (o, &s) in orow.iter_mut().zip(srow) {
                    *o += t * s;
                }
            }
        }
    });
    out
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
