//! Lens distortion of COLMAP's SIMPLE_RADIAL, RADIAL and OPENCV camera models.
//!
//! The models act on normalised image coordinates `(u, v) = ((x - cx) / fx, (y - cy) / fy)`
//! of an ideal pinhole camera, exactly as COLMAP's `BaseCameraModel::Distortion`: with
//! `r^2 = u^2 + v^2`,
//! * radial (SIMPLE_RADIAL has `k2 = 0`): `(u, v) (1 + k1 r^2 + k2 r^4)`;
//! * OPENCV adds tangential terms: `u' = u (1 + k1 r^2 + k2 r^4) + 2 p1 u v + p2 (r^2 + 2 u^2)`,
//!   `v' = v (1 + k1 r^2 + k2 r^4) + 2 p2 u v + p1 (r^2 + 2 v^2)`.
//!
//! Because the parameters are dimensionless, the same distortion applies to the image at any
//! resolution, provided the intrinsics are scaled with it.

use crate::Intrinsics;

/// A lens distortion in normalised image coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Distortion {
    /// SIMPLE_RADIAL (`k2 = 0`) and RADIAL.
    Radial {
        /// Coefficient of `r^2`.
        k1: f64,
        /// Coefficient of `r^4` (0 for SIMPLE_RADIAL).
        k2: f64,
    },
    /// OPENCV: radial `k1, k2` and tangential `p1, p2`.
    OpenCv {
        /// Coefficient of `r^2`.
        k1: f64,
        /// Coefficient of `r^4`.
        k2: f64,
        /// First tangential coefficient.
        p1: f64,
        /// Second tangential coefficient.
        p2: f64,
    },
}

impl Distortion {
    /// Whether the distortion is the identity.
    pub fn is_identity(&self) -> bool {
        match *self {
            Distortion::Radial { k1, k2 } => k1 == 0.0 && k2 == 0.0,
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                k1 == 0.0 && k2 == 0.0 && p1 == 0.0 && p2 == 0.0
            }
        }
    }

    /// Maps undistorted normalised coordinates to distorted ones.
    pub fn distort(&self, u: f64, v: f64) -> (f64, f64) {
        let r2 = u * u + v * v;
        match *self {
            Distortion::Radial { k1, k2 } => {
                let s = 1.0 + k1 * r2 + k2 * r2 * r2;
                (u * s, v * s)
            }
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                let s = 1.0 + k1 * r2 + k2 * r2 * r2;
                let uv = u * v;
                (
                    u * s + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u * u),
                    v * s + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v * v),
                )
            }
        }
    }

    /// Maps a pixel of the ideal pinhole image (continuous coordinates, pixel centres at
    /// `i + 0.5`) to the pixel of the distorted image that sees the same ray.
    pub fn distort_pixel(&self, k: &Intrinsics, x: f64, y: f64) -> (f64, f64) {
        let (ud, vd) = self.distort((x - k.cx) / k.fx, (y - k.cy) / k.fy);
        (k.fx * ud + k.cx, k.fy * vd + k.cy)
    }

    /// Parameters as written in a message, e.g. `k1=0.0578 k2=0`.
    pub fn describe(&self) -> String {
        match *self {
            Distortion::Radial { k1, k2 } => format!("k1={k1} k2={k2}"),
            Distortion::OpenCv { k1, k2, p1, p2 } => format!("k1={k1} k2={k2} p1={p1} p2={p2}"),
        }
    }
}
