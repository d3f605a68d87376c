//! Gaussian scenes, pinhole cameras, EWA projection and spherical harmonics (forward and exact
//! backward), the official 3DGS PLY layout, and datasets of posed images.
//!
//! Conventions follow the oracle: cameras are `camera_from_world` in OpenCV axes (x right, y down,
//! z forward), pixel centres sit at `(x + 0.5, y + 0.5)`, quaternions are `(w, x, y, z)`.
//!
//! # Example
//!
//! Load a 3DGS `.ply`, aim a camera at it and project every Gaussian to the screen:
//!
//! ```
//! use gaussian::camera_path::look_at;
//! use gaussian::{load_ply, project, Intrinsics, ProjectSettings};
//! use glam::DVec3;
//!
//! let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../fixtures/ply/tiny_ascii_deg1.ply");
//! let scene = load_ply(path)?;
//! assert_eq!((scene.len(), scene.sh_degree, scene.feature_dim), (2, 1, 0));
//!
//! // A 128 x 96 pinhole camera 60 units in front of the centre of the means, image up along -y.
//! let (lo, hi) = scene.bounds().expect("not empty");
//! let center = DVec3::from_array(std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]) as f64));
//! let intrinsics = Intrinsics {
//!     fx: 100.0,
//!     fy: 100.0,
//!     cx: 64.0,
//!     cy: 48.0,
//!     width: 128,
//!     height: 96,
//! };
//! let up = DVec3::new(0.0, -1.0, 0.0);
//! let eye = center - 60.0 * DVec3::Z;
//! let camera = look_at(intrinsics, eye, center, up).expect("up is not the view axis");
//!
//! let settings = ProjectSettings::default();
//! let p = project(&camera, &scene.means, &scene.quats, &scene.log_scales, &settings);
//! for i in 0..scene.len() {
//!     // In front of the camera, inside the image, and its 2D conic is positive definite.
//!     assert!(p.is_visible(i) && p.depths[i] > 0.0);
//!     let [a, b, c] = p.conics[i];
//!     assert!(a > 0.0 && a * c - b * b > 0.0);
//!     let (m, z, r) = (p.means2d[i], p.depths[i], p.radii[i]);
//!     println!("Gaussian {i}: pixel {m:?}, depth {z}, radii {r:?}");
//! }
//! // Projecting a mean with the camera alone agrees with the EWA projection.
//! let (u, v, z) = camera.project_point(DVec3::from_array(scene.means[0].map(f64::from)));
//! let [pu, pv] = p.means2d[0].map(f64::from);
//! assert!((u - pu).abs() < 1e-3 && (v - pv).abs() < 1e-3);
//! assert!((z - p.depths[0] as f64).abs() < 1e-3);
//! # Ok::<(), gaussian::PlyError>(())
//! ```

#![warn(missing_docs)]

pub mod camera;
pub mod camera_path;
pub mod dataset;
pub mod npy;
pub mod ply;
pub mod project;
pub mod scene;
pub mod sh;

/// The workspace's numeric trait and exponential, from `dsgs-base`.
pub use base::{exp_f32, exp_f32_in_range, Real, EXP_F32_HIGH, EXP_F32_LOW};
pub use camera::{Camera, Intrinsics};
pub use dataset::{Dataset, DatasetError, LoadOptions, Resolution};
pub use ply::{load_ply, save_ply, PlyError};
pub use project::{project, project_backward, ProjectSettings, Projected, ProjectionGrads};
pub use scene::{scene_extent_from_cameras, FeatureGaussians, SceneError};
pub use sh::{sh_colors, sh_colors_backward, sh_colors_backward_rows};
