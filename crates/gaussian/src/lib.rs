//! Gaussian scenes, pinhole cameras, EWA projection and spherical harmonics (forward and exact
//! backward), the official 3DGS PLY layout, and datasets of posed images.
//!
//! Conventions follow the oracle: cameras are `camera_from_world` in OpenCV axes (x right, y down,
//! z forward), pixel centres sit at `(x + 0.5, y + 0.5)`, quaternions are `(w, x, y, z)`.

pub mod camera;
pub mod real;
pub mod scene;

pub use camera::{Camera, Intrinsics};
pub use real::Real;
pub use scene::FeatureGaussians;
