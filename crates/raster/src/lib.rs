//! A tile-based Gaussian splatting rasterizer for any number of channels, with an exact backward
//! pass: the CPU counterpart of the 3DGS / gsplat CUDA rasterizer.
//!
//! * [`rasterize`] blends projected Gaussians ([`Splats`]: 2D means, conics, depths, radii,
//!   opacities and `D` channel values each) into a channel image, an alpha image, a depth image
//!   (accumulated and alpha-normalised) and a per-pixel count of blended Gaussians.
//! * [`rasterize_backward`] returns exact gradients with respect to all of those inputs and the
//!   background, from cotangents on the channel, alpha and depth images.
//! * [`render()`] and [`render_backward`] chain projection, SH colour and/or features, and the
//!   rasterizer, from a camera and a [`gaussian::FeatureGaussians`] scene to gradients of every
//!   scene parameter; [`render_backward_features`] gives the features' gradient alone, for
//!   frozen geometry, and [`render_backward_before_sh`] stops at the colour cotangent for a
//!   caller that runs the SH backward itself.
//! * [`blend_weights`] and [`render_weights`] give an image's blend weights as a sparse matrix
//!   ([`BlendWeights`]): for fixed geometry the image as a linear map of the channel values, for
//!   solvers that apply it many times.
//! * [`stats`] computes the densification statistics (screen radii, NDC gradient norms).
//! * [`supersample`] averages a finer render over each coarse pixel's footprint, and back.
//!
//! Conventions are those of the oracle (`gen_fixtures.py`), documented in [`blend`] and [`tiles`].
//! Both passes run tiles in parallel with rayon and give bit-identical results for any number of
//! threads. Kernels are generic over [`gaussian::Real`] (`f32` for production, `f64` for checks).
//!
//! # Example
//!
//! Render colour and a 4-channel feature of three Gaussians, then take the gradients of
//! `loss = sum(image)` with respect to every scene parameter:
//!
//! ```
//! use gaussian::{Camera, FeatureGaussians, Intrinsics};
//! use glam::DMat4;
//! use raster::{render, render_backward, Channels, RenderOptions};
//!
//! // Three Gaussians 4 to 6 units in front of a camera at the origin (OpenCV axes, z forward).
//! let scene = FeatureGaussians::<f32> {
//!     means: vec![[-0.4, 0.0, 4.0], [0.3, 0.2, 5.0], [0.0, -0.3, 6.0]],
//!     log_scales: vec![[-1.5, -1.8, -2.0]; 3],
//!     quats: vec![[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.3, 0.0], [0.7, 0.0, 0.0, 0.7]],
//!     opacity_logits: vec![0.5, 1.0, 2.0],
//!     sh_degree: 0,
//!     sh: vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], // one DC coefficient each
//!     ..Default::default()
//! }
//! .with_features(4, 0.25);
//! scene.validate()?;
//! let intrinsics = Intrinsics {
//!     fx: 40.0,
//!     fy: 40.0,
//!     cx: 24.0,
//!     cy: 16.0,
//!     width: 48,
//!     height: 32,
//! };
//! let camera = Camera::new(intrinsics, DMat4::IDENTITY);
//!
//! // RGB followed by the 4 feature channels, on a black background.
//! let opts = RenderOptions::new(Channels::ColorAndFeatures { sh_degree: 0 }, vec![0.0; 7]);
//! let out = render(&camera, &scene, &opts)?;
//! let img = &out.raster;
//! assert_eq!((img.width, img.height, img.channel_count), (48, 32, 7));
//! assert!(img.alpha.iter().all(|a| (0.0..=1.0).contains(a)));
//! assert!(img.pixel(24, 16)[3] > 0.0, "the centre pixel sees the features");
//!
//! // d loss / d image is 1 everywhere for loss = sum(image); no loss on alpha or depth.
//! let ones = vec![1.0; img.image.len()];
//! let grads = render_backward(&camera, &scene, &opts, &out, &ones, None, None)?;
//! assert!(grads.means.iter().flatten().all(|g| g.is_finite()));
//! assert!(grads.opacity_logits.iter().all(|&g| g > 0.0), "more opacity, more light");
//! // The image is linear in the features: each gradient is the Gaussian's total blend weight.
//! let loss = |s: &FeatureGaussians| -> f32 {
//!     render(&camera, s, &opts).unwrap().raster.image.iter().sum()
//! };
//! let mut bumped = scene.clone();
//! bumped.features[4] += 1.0; // feature channel 0 of Gaussian 1
//! let finite_difference = loss(&bumped) - loss(&scene);
//! assert!((finite_difference - grads.features[4]).abs() < 1e-3 * grads.features[4]);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

pub mod backward;
pub mod blend;
pub mod error;
pub mod forward;
pub mod kernels;
pub mod render;
pub mod rows;
pub mod splats;
pub mod stats;
pub mod supersample;
pub mod tiles;
pub mod weights;

pub use backward::{
    fold_normalized_depth_cotangent, rasterize_backward, rasterize_backward_with,
    rasterize_backward_with_budget, SplatGrads, DEFAULT_GRADIENT_BUFFER_VALUES,
};
pub use error::RasterError;
pub use forward::{rasterize, rasterize_binned, rasterize_binned_with, Rasterized};
pub use kernels::{Isa, Kernel};
pub use render::{
    add_view_direction_term, render, render_backward, render_backward_before_sh,
    render_backward_features, render_weights, render_window, Channels, GradsBeforeSh, PixelWindow,
    Render, RenderOptions, SceneGrads,
};
pub use splats::{Cotangents, Splats};
pub use stats::{ndc_grad_norms, screen_radii, DensificationStats};
pub use tiles::{tile_grid, tile_rect, TileBins, TileRect};
pub use weights::{blend_weights, BlendWeights};
