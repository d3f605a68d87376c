//! Colour rendering for the geometry stage: the rasterizer's camera-level `render` and
//! `render_backward` with RGB channels from SH evaluated to the active degree, over a background.

use gaussian::{Camera, FeatureGaussians};
use raster::{
    render, render_backward, render_backward_before_sh, Channels, Render, RenderOptions, SceneGrads,
};

use crate::error::TrainError;

/// The options of a colour render at SH degree `sh_degree` over `background`.
pub fn color_options(sh_degree: usize, background: [f32; 3]) -> RenderOptions<f32> {
    RenderOptions::new(Channels::Color { sh_degree }, background.to_vec())
}

/// Renders `scene` from `camera` (image: row-major RGB, `height * width * 3`).
pub fn render_color(
    camera: &Camera,
    scene: &FeatureGaussians<f32>,
    sh_degree: usize,
    background: [f32; 3],
) -> Result<Render<f32>, TrainError> {
    Ok(render(
        camera,
        scene,
        &color_options(sh_degree, background),
    )?)
}

/// The gradients of a loss with respect to `scene`, given `v_image = dL/d image` for the render
/// `fwd` made by [`render_color`] with the same arguments.
pub fn render_color_backward(
    camera: &Camera,
    scene: &FeatureGaussians<f32>,
    sh_degree: usize,
    background: [f32; 3],
    fwd: &Render<f32>,
    v_image: &[f32],
) -> Result<SceneGrads<f32>, TrainError> {
    Ok(render_backward(
        camera,
        scene,
        &color_options(sh_degree, background),
        fwd,
        v_image,
        None,
        None,
    )?)
}

/// [`render_color_backward`] stopped before the SH colour backward
/// ([`raster::render_backward_before_sh`]): the gradients without the SH coefficients' and
/// with the means' through the projection only, and the colour cotangent, one RGB triple per
/// Gaussian.
pub fn render_color_backward_before_sh(
    camera: &Camera,
    scene: &FeatureGaussians<f32>,
    sh_degree: usize,
    background: [f32; 3],
    fwd: &Render<f32>,
    v_image: &[f32],
) -> Result<(SceneGrads<f32>, Vec<[f32; 3]>), TrainError> {
    let (grads, colours) = render_backward_before_sh(
        camera,
        scene,
        &color_options(sh_degree, background),
        fwd,
        v_image,
        None,
        None,
    )?;
    let colours = colours.expect("colour renders have a colour cotangent");
    Ok((grads, colours))
}
