//! Gaussian scenes, pinhole cameras, EWA projection and spherical harmonics (forward and exact
//! backward), the official 3DGS PLY layout, and datasets of posed images.
//!
//! Conventions follow the oracle: cameras are `camera_from_world` in OpenCV axes (x right, y down,
//! z forward), pixel centres sit at `(x + 0.5, y + 0.5)`, quaternions are `(w, x, y, z)`.

pub mod camera;
pub mod camera_path;
pub mod dataset;
pub mod npy;
pub mod ply;
pub mod project;
pub mod scene;
pub mod sh;

/// The workspace's numeric trait and exponential, from `dsgs-base`.
pub use base::{exp_f32, Real};
pub use camera::{Camera, Intrinsics};
pub use dataset::{Dataset, DatasetError, LoadOptions, Resolution};
pub use ply::{load_ply, save_ply, PlyError};
pub use project::{project, project_backward, ProjectSettings, Projected, ProjectionGrads};
pub use scene::{scene_extent_from_cameras, FeatureGaussians, SceneError};
pub use sh::{sh_colors, sh_colors_backward};
