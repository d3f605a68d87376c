//! Colour preservation: before a style image is encoded, its RGB colour distribution is matched
//! to the content image's, so the stylized result keeps the content's colours.
//!
//! Method (the linear "colour histogram matching" of Gatys et al., *Preserving Color in Neural
//! Artistic Style Transfer*, 2016, as used by the AdaIN reference code): with mean `mu` and
//! covariance `Sigma` of the RGB pixels of each image, every style pixel `x` becomes
//!
//! ```text
//! x' = A (x - mu_s) + mu_c,      A = (Sigma_c + eps I)^{1/2} (Sigma_s + eps I)^{-1/2}
//! ```
//!
//! with symmetric matrix square roots from an eigendecomposition (cyclic Jacobi on the 3x3
//! matrix, in `f64`). Then `A (Sigma_s + eps I) A^T = Sigma_c + eps I`, so the new style pixels
//! have the content's mean and (up to the ridge `eps`) its covariance. The ridge keeps a flat or
//! grey style image well defined. Covariances use the `1/(m-1)` normaliser; the choice cancels
//! in `A`. The result is not clamped to [0, 1].

use base::Real;
use ndarray::Array4;

use crate::error::{Result, StyleError};
use crate::stats::dims;

/// The ridge added to both covariances.
pub const COLOUR_EPS: f64 = 1e-5;

type Mat3 = [[f64; 3]; 3];

/// Mean and covariance of the RGB pixels of sample `n` of an `[N, 3, H, W]` image.
fn rgb_moments<T: Real>(img: &Array4<T>, n: usize) -> ([f64; 3], Mat3) {
    let (_, _, h, w) = dims(img);
    let m = (h * w) as f64;
    let mut mu = [0.0f64; 3];
    for (c, mu_c) in mu.iter_mut().enumerate() {
        *mu_c = img
            .slice(ndarray::s![n, c, .., ..])
            .iter()
            .fold(0.0, |s, &v| s + v.to_f64_exact())
            / m;
    }
    let mut cov = [[0.0f64; 3]; 3];
    for y in 0..h {
        for x in 0..w {
            let d = [0, 1, 2].map(|c| img[[n, c, y, x]].to_f64_exact() - mu[c]);
            for i in 0..3 {
                for j in 0..3 {
                    cov[i][j] += d[i] * d[j];
                }
            }
        }
    }
    for row in cov.iter_mut() {
        for v in row.iter_mut() {
            *v /= m - 1.0;
        }
    }
    (mu, cov)
}

/// Eigendecomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations:
/// returns `(eigenvalues, V)` with `a = V diag(eigenvalues) V^T` and eigenvectors as columns.
pub(crate) fn sym_eigen3(mut a: Mat3) -> ([f64; 3], Mat3) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..64 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        let diag = a[0][0].powi(2) + a[1][1].powi(2) + a[2][2].powi(2);
        if off <= 1e-32 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            // Rotation angle that zeroes a[p][q] (Golub & Van Loan, symmetric Schur 2x2).
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // a <- J^T a J with J the rotation in the (p, q) plane.
            for row in a.iter_mut() {
                let (akp, akq) = (row[p], row[q]);
                row[p] = c * akp - s * akq;
                row[q] = s * akp + c * akq;
            }
            let (row_p, row_q) = (a[p], a[q]);
            for k in 0..3 {
                a[p][k] = c * row_p[k] - s * row_q[k];
                a[q][k] = s * row_p[k] + c * row_q[k];
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// `V diag(f(lambda)) V^T` for a symmetric matrix.
fn sym_fn(a: Mat3, f: impl Fn(f64) -> f64) -> Mat3 {
    let (l, v) = sym_eigen3(a);
    let fl = l.map(f);
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, o) in row.iter_mut().enumerate() {
            *o = (0..3).map(|k| v[i][k] * fl[k] * v[j][k]).sum();
        }
    }
    out
}

fn matmul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, o) in row.iter_mut().enumerate() {
            *o = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

/// The style image with its colour statistics matched to the content image's (see the module
/// documentation), using the ridge [`COLOUR_EPS`]. Both images are `[N, 3, H, W]` RGB; a content
/// with `N = 1` serves every style sample, otherwise the batches must agree.
pub fn preserve_colour<T: Real>(style: &Array4<T>, content: &Array4<T>) -> Result<Array4<T>> {
    preserve_colour_with_eps(style, content, COLOUR_EPS)
}

/// [`preserve_colour`] with an explicit ridge `eps >= 0`.
pub fn preserve_colour_with_eps<T: Real>(
    style: &Array4<T>,
    content: &Array4<T>,
    eps: f64,
) -> Result<Array4<T>> {
    let (ns, cs, hs, ws) = dims(style);
    let (nc, cc, hc, wc) = dims(content);
    if cs != 3 || cc != 3 || (nc != 1 && nc != ns) {
        return Err(StyleError::Invalid {
            what: "colour preservation",
            problem: format!(
                "need RGB images [N,3,H,W] with content batch 1 or N; got style {:?}, content {:?}",
                style.shape(),
                content.shape()
            ),
        });
    }
    if hs * ws < 2 || hc * wc < 2 {
        return Err(StyleError::TooFewPixels {
            what: "colour preservation",
            count: (hs * ws).min(hc * wc),
        });
    }
    if !(eps >= 0.0 && eps.is_finite()) {
        return Err(StyleError::NonFinite {
            what: "colour preservation ridge",
            value: eps,
        });
    }
    let mut out = style.clone();
    for n in 0..ns {
        let (mu_s, mut cov_s) = rgb_moments(style, n);
        let (mu_c, mut cov_c) = rgb_moments(content, if nc == 1 { 0 } else { n });
        for i in 0..3 {
            cov_s[i][i] += eps;
            cov_c[i][i] += eps;
        }
        let inv_sqrt_s = sym_fn(cov_s, |l| if l > 0.0 { 1.0 / l.sqrt() } else { 0.0 });
        let sqrt_c = sym_fn(cov_c, |l| l.max(0.0).sqrt());
        let a = matmul(&sqrt_c, &inv_sqrt_s);
        for y in 0..hs {
            for x in 0..ws {
                let d = [0, 1, 2].map(|c| style[[n, c, y, x]].to_f64_exact() - mu_s[c]);
                for c in 0..3 {
                    let v = a[c][0] * d[0] + a[c][1] * d[1] + a[c][2] * d[2] + mu_c[c];
                    out[[n, c, y, x]] = T::lit(v);
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_reconstructs_a_symmetric_matrix() {
        let a = [[4.0, 1.0, -2.0], [1.0, 3.0, 0.5], [-2.0, 0.5, 5.0]];
        let r = sym_fn(a, |l| l);
        for i in 0..3 {
            for j in 0..3 {
                assert!(
                    (r[i][j] - a[i][j]).abs() < 1e-12,
                    "{i}{j}: {} vs {}",
                    r[i][j],
                    a[i][j]
                );
            }
        }
        let s = sym_fn(a, f64::sqrt);
        let ss = matmul(&s, &s);
        for i in 0..3 {
            for j in 0..3 {
                assert!((ss[i][j] - a[i][j]).abs() < 1e-12);
            }
        }
    }
}
