//! The Gaussian scene, stored as a struct of arrays.
//!
//! Parameters are stored before activation, as the official 3DGS trainer does: log-scales,
//! unnormalised quaternions `(w, x, y, z)`, opacity logits. Spherical-harmonic coefficients are
//! Gaussian-major: Gaussian `n`, coefficient `k` (0 is DC), RGB, i.e. `sh[n * K + k]` with
//! `K = (sh_degree + 1)^2`. Features are `features[n * feature_dim + c]`.

use crate::Real;

/// A set of 3D Gaussians with colour (SH) and an optional learnable feature per Gaussian.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FeatureGaussians<T: Real = f32> {
    pub means: Vec<[T; 3]>,
    pub log_scales: Vec<[T; 3]>,
    /// Unnormalised rotation quaternions `(w, x, y, z)`.
    pub quats: Vec<[T; 4]>,
    pub opacity_logits: Vec<T>,
    /// Spherical-harmonic degree, 0..=3.
    pub sh_degree: usize,
    /// `len() * sh_coeffs_per_gaussian()` RGB coefficients, Gaussian-major.
    pub sh: Vec<[T; 3]>,
    /// Channels per feature vector; 0 when the scene carries no features.
    pub feature_dim: usize,
    /// `len() * feature_dim` values, Gaussian-major.
    pub features: Vec<T>,
}

impl<T: Real> FeatureGaussians<T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether the scene has no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// SH coefficients per Gaussian and colour channel: `(sh_degree + 1)^2`.
    pub fn sh_coeffs_per_gaussian(&self) -> usize {
        (self.sh_degree + 1) * (self.sh_degree + 1)
    }
}
