//! The Gaussian scene, stored as a struct of arrays.
//!
//! Parameters are stored before activation, as the official 3DGS trainer does: log-scales,
//! unnormalised quaternions `(w, x, y, z)`, opacity logits. Spherical-harmonic coefficients are
//! Gaussian-major: Gaussian `n`, coefficient `k` (0 is DC), RGB, i.e. `sh[n * K + k]` with
//! `K = (sh_degree + 1)^2`. Features are `features[n * feature_dim + c]`.
//!
//! # Bounds on values read from files
//! Every stored value must be finite. A scene read from a file ([`crate::ply`]) must also keep
//! its activated values meaningful in `f32`: mean coordinates within ±[`MAX_ABS_POSITION`],
//! log-scales in [[`MIN_LOG_SCALE`], [`MAX_LOG_SCALE`]], opacity logits within
//! ±[`MAX_ABS_OPACITY_LOGIT`], and rotation quaternions with a norm in
//! [[`MIN_QUAT_NORM`], [`MAX_QUAT_NORM`]]. Each bound is far beyond what training produces, so
//! only corrupt or foreign files are refused.

use glam::DVec3;

use crate::{Camera, Real};

/// The largest absolute coordinate of a Gaussian's mean accepted from a file (world units).
///
/// `f32` spaces its values one unit apart at `1e7`, so a scene beyond it cannot be rendered at
/// any useful detail; georeferenced coordinates (UTM northings reach about `1e7`) still pass.
/// A larger value is a corrupt or foreign file, and its squares would overflow `f32` in the
/// projection.
pub const MAX_ABS_POSITION: f32 = 1e7;

/// The largest log-scale accepted from a file: `exp(20)` is about `4.9e8`, fifty times the
/// largest coordinate ([`MAX_ABS_POSITION`]). Larger values make the activated scale absurd and
/// soon overflow `f32` (the projected covariance grows with `exp(2 s)`; `exp(s)` itself
/// overflows above about 88.7).
pub const MAX_LOG_SCALE: f32 = 20.0;

/// The smallest log-scale accepted from a file. `exp(s)` is already exactly 0 in `f32` below
/// about -103.9, so a lower value only says the file is corrupt: training moves a log-scale by
/// at most its learning rate per step (a few hundred over a whole 3DGS run), never to -1000.
pub const MIN_LOG_SCALE: f32 = -1000.0;

/// The largest absolute opacity logit accepted from a file. The sigmoid is exactly 0 or 1 in
/// `f32` beyond about ±104, and training moves a logit by at most its learning rate per step
/// (under 1500 over a whole 3DGS run), so a larger logit only says the file is corrupt.
pub const MAX_ABS_OPACITY_LOGIT: f32 = 1e4;

/// The smallest norm of a rotation quaternion accepted from a file: [the
/// projection](mod@crate::project) normalises by `max(|q|, 1e-12)`, so a shorter quaternion (a
/// zero one among them) would not become a unit quaternion and would scale the Gaussian
/// instead of rotating it.
pub const MIN_QUAT_NORM: f64 = 1e-12;

/// The largest norm of a rotation quaternion accepted from a file: training keeps quaternions
/// near unit length (each step moves a component by about its learning rate), so a norm beyond
/// `1e6` only says the file is corrupt; far beyond, the norm overflows `f32`.
pub const MAX_QUAT_NORM: f64 = 1e6;

/// A set of 3D Gaussians with colour (SH) and an optional learnable feature per Gaussian.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FeatureGaussians<T: Real = f32> {
    /// World-space centres, one `[x, y, z]` per Gaussian.
    pub means: Vec<[T; 3]>,
    /// Natural-log standard deviations along the Gaussian's local axes (activated by `exp`), one
    /// `[x, y, z]` per Gaussian.
    pub log_scales: Vec<[T; 3]>,
    /// Unnormalised rotation quaternions `(w, x, y, z)`.
    pub quats: Vec<[T; 4]>,
    /// Opacity before the sigmoid, one per Gaussian.
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

/// A scene whose arrays disagree with each other or hold non-finite values.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// An array's length does not match the number of Gaussians (times the per-Gaussian width).
    #[error("array `{array}` has {actual} entries, expected {expected}")]
    Length {
        /// Name of the offending field of [`FeatureGaussians`].
        array: &'static str,
        /// Its length.
        actual: usize,
        /// The length implied by `len()`, `sh_degree` and `feature_dim`.
        expected: usize,
    },
    /// `sh_degree` is above 3.
    #[error("SH degree {0} is not supported (0..=3)")]
    ShDegree(usize),
    /// A parameter array contains a NaN or infinity.
    #[error("array `{array}` holds a non-finite value at index {index}")]
    NonFinite {
        /// Name of the offending field of [`FeatureGaussians`].
        array: &'static str,
        /// Gaussian (row) index, or the flat element index for `sh` and `features`.
        index: usize,
    },
    /// Two scenes being combined differ in SH degree or feature width.
    #[error("cannot combine scenes with {what} {left} and {right}")]
    Mismatch {
        /// Which property differs: `"SH degrees"` or `"feature widths"`.
        what: &'static str,
        /// Its value in the scene being extended.
        left: usize,
        /// Its value in the scene being appended.
        right: usize,
    },
    /// A keep mask's length differs from the number of Gaussians.
    #[error("keep mask has {actual} entries for {expected} Gaussians")]
    MaskLength {
        /// Entries in the mask.
        actual: usize,
        /// Gaussians in the scene.
        expected: usize,
    },
}

fn check_len(array: &'static str, actual: usize, expected: usize) -> Result<(), SceneError> {
    if actual == expected {
        Ok(())
    } else {
        Err(SceneError::Length {
            array,
            actual,
            expected,
        })
    }
}

/// The first index of a non-finite value in an array of fixed-size rows (the row index).
fn check_finite_rows<T: Real, const D: usize>(
    array: &'static str,
    rows: &[[T; D]],
) -> Result<(), SceneError> {
    match rows.iter().position(|r| r.iter().any(|v| !v.is_finite())) {
        None => Ok(()),
        Some(index) => Err(SceneError::NonFinite { array, index }),
    }
}

fn check_finite<T: Real>(array: &'static str, values: &[T]) -> Result<(), SceneError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(SceneError::NonFinite { array, index }),
    }
}

#[inline]
fn cast_row<T: Real, U: Real, const D: usize>(r: &[T; D]) -> [U; D] {
    r.map(|v| U::lit(v.to_f64_exact()))
}

/// Logistic sigmoid `1 / (1 + exp(-x))`.
#[inline]
pub fn sigmoid<T: Real>(x: T) -> T {
    T::one() / (T::one() + (-x).exp())
}

/// Normalises a `(w, x, y, z)` quaternion (returns it unchanged when its norm is zero).
#[inline]
pub fn normalize_quat<T: Real>(q: [T; 4]) -> [T; 4] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n > T::zero() {
        q.map(|v| v / n)
    } else {
        q
    }
}

/// The rotation matrix (row-major, `r[row][col]`) of a unit `(w, x, y, z)` quaternion.
#[inline]
pub fn quat_to_rotmat<T: Real>(q: [T; 4]) -> [[T; 3]; 3] {
    let [w, x, y, z] = q;
    let one = T::one();
    let two = T::lit(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

impl<T: Real> FeatureGaussians<T> {
    /// Checks that every array has the length `len()` implies (`sh`: `len() * K`, `features`:
    /// `len() * feature_dim`), that `sh_degree <= 3`, and that every value is finite. The error
    /// names the first offending array and, for non-finite values, the index of the Gaussian
    /// (for `sh` and `features`, the flat index into the array).
    pub fn validate(&self) -> Result<(), SceneError> {
        let n = self.len();
        if self.sh_degree > 3 {
            return Err(SceneError::ShDegree(self.sh_degree));
        }
        check_len("log_scales", self.log_scales.len(), n)?;
        check_len("quats", self.quats.len(), n)?;
        check_len("opacity_logits", self.opacity_logits.len(), n)?;
        check_len("sh", self.sh.len(), n * self.sh_coeffs_per_gaussian())?;
        check_len("features", self.features.len(), n * self.feature_dim)?;
        check_finite_rows("means", &self.means)?;
        check_finite_rows("log_scales", &self.log_scales)?;
        check_finite_rows("quats", &self.quats)?;
        check_finite("opacity_logits", &self.opacity_logits)?;
        check_finite_rows("sh", &self.sh)?;
        check_finite("features", &self.features)?;
        Ok(())
    }

    /// Activated scale of Gaussian `i`: `exp(log_scale)` per axis.
    pub fn scale(&self, i: usize) -> [T; 3] {
        self.log_scales[i].map(T::exp)
    }

    /// Activated scales of all Gaussians.
    pub fn scales(&self) -> Vec<[T; 3]> {
        self.log_scales.iter().map(|s| s.map(T::exp)).collect()
    }

    /// Activated opacity of Gaussian `i`: `sigmoid(opacity_logit)`.
    pub fn opacity(&self, i: usize) -> T {
        sigmoid(self.opacity_logits[i])
    }

    /// Activated opacities of all Gaussians.
    pub fn opacities(&self) -> Vec<T> {
        self.opacity_logits.iter().map(|&v| sigmoid(v)).collect()
    }

    /// Unit rotation quaternion `(w, x, y, z)` of Gaussian `i`.
    pub fn rotation(&self, i: usize) -> [T; 4] {
        normalize_quat(self.quats[i])
    }

    /// Rotation matrix (row-major) of Gaussian `i`.
    pub fn rotation_matrix(&self, i: usize) -> [[T; 3]; 3] {
        quat_to_rotmat(self.rotation(i))
    }

    /// SH coefficients of Gaussian `i` (`sh_coeffs_per_gaussian()` RGB triples, DC first).
    pub fn sh_of(&self, i: usize) -> &[[T; 3]] {
        let k = self.sh_coeffs_per_gaussian();
        &self.sh[i * k..(i + 1) * k]
    }

    /// Feature vector of Gaussian `i` (empty when the scene has no features).
    pub fn feature_of(&self, i: usize) -> &[T] {
        let f = self.feature_dim;
        &self.features[i * f..(i + 1) * f]
    }

    /// Axis-aligned bounds `(min, max)` of the means; `None` for an empty scene.
    pub fn bounds(&self) -> Option<([T; 3], [T; 3])> {
        let first = *self.means.first()?;
        Some(self.means.iter().fold((first, first), |(lo, hi), m| {
            (
                [lo[0].min(m[0]), lo[1].min(m[1]), lo[2].min(m[2])],
                [hi[0].max(m[0]), hi[1].max(m[1]), hi[2].max(m[2])],
            )
        }))
    }

    /// Half the diagonal of [`bounds`](Self::bounds), i.e. the radius of the sphere around the
    /// box centre that contains every mean; 0 for an empty scene. (The extent that 3DGS
    /// densification thresholds use comes from the cameras instead, see
    /// [`scene_extent_from_cameras`].)
    pub fn extent(&self) -> f64 {
        match self.bounds() {
            None => 0.0,
            Some((lo, hi)) => {
                let d2: f64 = (0..3)
                    .map(|a| (hi[a].to_f64_exact() - lo[a].to_f64_exact()).powi(2))
                    .sum();
                0.5 * d2.sqrt()
            }
        }
    }

    /// The same scene with a fresh feature of `dim` channels per Gaussian, all set to `init`
    /// (replacing any existing features).
    pub fn with_features(mut self, dim: usize, init: T) -> Self {
        self.feature_dim = dim;
        self.features = vec![init; self.len() * dim];
        self
    }

    /// The scene converted to another scalar type (rounding when narrowing to `f32`).
    pub fn cast<U: Real>(&self) -> FeatureGaussians<U> {
        FeatureGaussians {
            means: self.means.iter().map(cast_row).collect(),
            log_scales: self.log_scales.iter().map(cast_row).collect(),
            quats: self.quats.iter().map(cast_row).collect(),
            opacity_logits: self
                .opacity_logits
                .iter()
                .map(|v| U::lit(v.to_f64_exact()))
                .collect(),
            sh_degree: self.sh_degree,
            sh: self.sh.iter().map(cast_row).collect(),
            feature_dim: self.feature_dim,
            features: self
                .features
                .iter()
                .map(|v| U::lit(v.to_f64_exact()))
                .collect(),
        }
    }

    /// The Gaussians at `indices`, in that order (an index may repeat, which clones a Gaussian).
    ///
    /// # Panics
    /// If an index is out of range (a caller bug, not a data error).
    pub fn subset(&self, indices: &[usize]) -> Self {
        let k = self.sh_coeffs_per_gaussian();
        let f = self.feature_dim;
        let mut out = FeatureGaussians {
            means: Vec::with_capacity(indices.len()),
            log_scales: Vec::with_capacity(indices.len()),
            quats: Vec::with_capacity(indices.len()),
            opacity_logits: Vec::with_capacity(indices.len()),
            sh_degree: self.sh_degree,
            sh: Vec::with_capacity(indices.len() * k),
            feature_dim: f,
            features: Vec::with_capacity(indices.len() * f),
        };
        for &i in indices {
            out.means.push(self.means[i]);
            out.log_scales.push(self.log_scales[i]);
            out.quats.push(self.quats[i]);
            out.opacity_logits.push(self.opacity_logits[i]);
            out.sh.extend_from_slice(&self.sh[i * k..(i + 1) * k]);
            out.features
                .extend_from_slice(&self.features[i * f..(i + 1) * f]);
        }
        out
    }

    /// Appends the Gaussians of `other`, which must have the same SH degree and feature width.
    pub fn extend(&mut self, other: &Self) -> Result<(), SceneError> {
        if other.sh_degree != self.sh_degree {
            return Err(SceneError::Mismatch {
                what: "SH degrees",
                left: self.sh_degree,
                right: other.sh_degree,
            });
        }
        if other.feature_dim != self.feature_dim {
            return Err(SceneError::Mismatch {
                what: "feature widths",
                left: self.feature_dim,
                right: other.feature_dim,
            });
        }
        self.means.extend_from_slice(&other.means);
        self.log_scales.extend_from_slice(&other.log_scales);
        self.quats.extend_from_slice(&other.quats);
        self.opacity_logits.extend_from_slice(&other.opacity_logits);
        self.sh.extend_from_slice(&other.sh);
        self.features.extend_from_slice(&other.features);
        Ok(())
    }

    /// Keeps the Gaussians whose entry in `keep` is true, in order.
    pub fn retain(&mut self, keep: &[bool]) -> Result<(), SceneError> {
        if keep.len() != self.len() {
            return Err(SceneError::MaskLength {
                actual: keep.len(),
                expected: self.len(),
            });
        }
        let indices: Vec<usize> = (0..keep.len()).filter(|&i| keep[i]).collect();
        *self = self.subset(&indices);
        Ok(())
    }
}

/// The scene extent 3DGS derives from its training cameras (`getNerfppNorm`): 1.1 times the
/// largest distance of a camera centre from the mean of all camera centres. 0 without cameras.
pub fn scene_extent_from_cameras(cameras: &[Camera]) -> f64 {
    if cameras.is_empty() {
        return 0.0;
    }
    let centers: Vec<DVec3> = cameras.iter().map(Camera::center).collect();
    let mean = centers.iter().copied().sum::<DVec3>() / centers.len() as f64;
    let max_dist = centers
        .iter()
        .map(|c| c.distance(mean))
        .fold(0.0f64, f64::max);
    1.1 * max_dist
}
