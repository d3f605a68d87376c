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
//!   scene parameter.
//! * [`stats`] computes the densification statistics (screen radii, NDC gradient norms).
//!
//! Conventions are those of the oracle (`gen_fixtures.py`), documented in [`blend`] and [`tiles`].
//! Both passes run tiles in parallel with rayon and give bit-identical results for any number of
//! threads. Kernels are generic over [`gaussian::Real`] (`f32` for production, `f64` for checks).

pub mod backward;
pub mod blend;
pub mod error;
pub mod forward;
pub mod kernels;
pub mod render;
pub mod rows;
pub mod stats;
pub mod tiles;

pub use backward::{
    fold_normalized_depth_cotangent, rasterize_backward, rasterize_backward_with,
    rasterize_backward_with_budget, Cotangents, SplatGrads, DEFAULT_GRADIENT_BUFFER_VALUES,
};
pub use error::RasterError;
pub use forward::{rasterize, rasterize_binned, rasterize_binned_with, Rasterized, Splats};
pub use kernels::{Isa, Kernel};
pub use render::{render, render_backward, Channels, Render, RenderOptions, SceneGrads};
pub use stats::{ndc_grad_norms, screen_radii, DensificationStats};
pub use tiles::{tile_grid, tile_rect, TileBins, TileRect};
