//! The camera-level renderer: projection (EWA), colour from spherical harmonics and/or learnable
//! features, rasterization, and the exact backward of the whole chain to the scene parameters.
//!
//! Forward: `project` gives 2D means, conics, depths and radii; opacities are
//! `sigmoid(opacity_logits)`; the blended channels are chosen by [`Channels`] (SH colour at an
//! active degree, the feature vectors, or colour then features concatenated); then
//! [`crate::rasterize`]. Backward: [`crate::rasterize_backward`], then the sigmoid, the SH colour
//! backward (which also reaches the means through the view direction) and `project_backward`;
//! for frozen geometry, [`render_backward_features`] stops after the rasterizer.
//! Conventions are the oracle's throughout (see the `gaussian` and `raster` module docs).
//!
//! Memory beyond the rasterizer's: per Gaussian, the projection (6 reals and 2 `u32`), the opacity,
//! the SH colour (3 reals, when colour is rendered) and, when colour and features are both
//! rendered, the concatenated channel rows (`3 + F` reals, rebuilt in the backward pass).

use std::borrow::Cow;

use base::memory::filled;
use rayon::prelude::*;

use gaussian::{project, project_backward, sh_colors, sh_colors_backward};
use gaussian::{Camera, FeatureGaussians, ProjectSettings, Projected, Real};

use crate::backward::{rasterize_backward, SplatGrads};
use crate::error::{check_len, RasterError};
use crate::forward::{rasterize, Rasterized};
use crate::splats::{Cotangents, Splats};
use crate::stats::ndc_grad_norms;
use crate::weights::{blend_weights, BlendWeights};

/// Below this many Gaussians per task, rayon's splitting overhead dominates.
const MIN_CHUNK: usize = 4096;

/// Which per-Gaussian values are blended into the image's channels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channels {
    /// RGB from the SH coefficients evaluated up to `sh_degree` (at most the scene's degree).
    Color {
        /// Highest SH band evaluated (0 = view-independent DC colour only).
        sh_degree: usize,
    },
    /// The scene's feature vectors (`feature_dim` channels).
    Features,
    /// RGB (as [`Channels::Color`]) followed by the features: `3 + feature_dim` channels.
    ColorAndFeatures {
        /// Highest SH band evaluated for the colour part (as in [`Channels::Color`]).
        sh_degree: usize,
    },
}

impl Channels {
    /// The active SH degree, when colour is rendered.
    pub fn sh_degree(&self) -> Option<usize> {
        match *self {
            Channels::Color { sh_degree } | Channels::ColorAndFeatures { sh_degree } => {
                Some(sh_degree)
            }
            Channels::Features => None,
        }
    }

    /// Whether the features are rendered.
    pub fn has_features(&self) -> bool {
        !matches!(self, Channels::Color { .. })
    }

    /// Number of image channels for a scene with `feature_dim` features.
    pub fn count(&self, feature_dim: usize) -> usize {
        match self {
            Channels::Color { .. } => 3,
            Channels::Features => feature_dim,
            Channels::ColorAndFeatures { .. } => 3 + feature_dim,
        }
    }
}

/// What to render and how.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions<T> {
    /// Which values are blended into the image channels (and hence how many channels there are).
    pub channels: Channels,
    /// One value per image channel.
    pub background: Vec<T>,
    /// Settings of the EWA projection: 2D low-pass `eps2d`, near/far culling depths and the
    /// screen radius in standard deviations.
    pub projection: ProjectSettings,
}

impl<T: Real> RenderOptions<T> {
    /// Options with the default projection settings.
    pub fn new(channels: Channels, background: Vec<T>) -> Self {
        RenderOptions {
            channels,
            background,
            projection: ProjectSettings::default(),
        }
    }
}

/// A rectangle of a camera's image, in pixels: columns `x .. x + width`, rows `y .. y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelWindow {
    /// First column.
    pub x: u32,
    /// First row.
    pub y: u32,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

impl PixelWindow {
    /// The whole image of `camera`.
    pub fn full(camera: &Camera) -> PixelWindow {
        PixelWindow {
            x: 0,
            y: 0,
            width: camera.intrinsics.width,
            height: camera.intrinsics.height,
        }
    }

    /// Whether the window is the whole image of `camera`.
    pub fn is_full(&self, camera: &Camera) -> bool {
        *self == PixelWindow::full(camera)
    }

    /// `Ok` when the window has pixels and lies inside the image of `camera`.
    fn check(&self, camera: &Camera) -> Result<(), RasterError> {
        let k = &camera.intrinsics;
        let inside = self.width > 0
            && self.height > 0
            && self.x as u64 + self.width as u64 <= k.width as u64
            && self.y as u64 + self.height as u64 <= k.height as u64;
        if inside {
            Ok(())
        } else {
            Err(scene_err(format!(
                "window {}x{} at ({}, {}) does not fit the camera's {}x{} image",
                self.width, self.height, self.x, self.y, k.width, k.height
            )))
        }
    }

    /// The 2D means in the window's pixel coordinates: borrowed for the whole image, shifted by
    /// `(-x, -y)` otherwise.
    fn means2d<'a, T: Real>(&self, camera: &Camera, means2d: &'a [[T; 2]]) -> Cow<'a, [[T; 2]]> {
        if self.is_full(camera) {
            return Cow::Borrowed(means2d);
        }
        let (ox, oy) = (T::lit(self.x as f64), T::lit(self.y as f64));
        Cow::Owned(
            means2d
                .par_iter()
                .with_min_len(MIN_CHUNK)
                .map(|m| [m[0] - ox, m[1] - oy])
                .collect(),
        )
    }
}

/// A rendered view and what its backward pass needs.
#[derive(Clone, Debug)]
pub struct Render<T> {
    /// The part of the camera's image rendered (the whole image for [`render`]); the raster
    /// images are `window.width x window.height`.
    pub window: PixelWindow,
    /// The projected Gaussians (radii `[0, 0]` for culled ones).
    pub projected: Projected<T>,
    /// `sigmoid(opacity_logits)`.
    pub opacities: Vec<T>,
    /// SH colours, when colour is rendered.
    pub colors: Option<Vec<[T; 3]>>,
    /// Image, alpha, depth, blend counts and tile bins.
    pub raster: Rasterized<T>,
}

impl<T: Real> Render<T> {
    /// Per-Gaussian screen radius `max(rx, ry)` in pixels for this view (0 when culled).
    pub fn screen_radii(&self) -> Vec<u32> {
        crate::stats::screen_radii(&self.projected.radii)
    }
}

/// Gradients of a loss with respect to the scene parameters, for one rendered view.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneGrads<T> {
    /// With respect to the world-space 3D means (through the projection and the SH view
    /// direction), one per Gaussian.
    pub means: Vec<[T; 3]>,
    /// With respect to the unnormalised quaternions.
    pub quats: Vec<[T; 4]>,
    /// With respect to the per-axis log scales, one per Gaussian.
    pub log_scales: Vec<[T; 3]>,
    /// With respect to the opacity logits (before the sigmoid), one per Gaussian.
    pub opacity_logits: Vec<T>,
    /// Same layout as the scene's `sh` (zero beyond the active degree, or everywhere when colour
    /// was not rendered).
    pub sh: Vec<[T; 3]>,
    /// Same layout as the scene's `features` (zero when features were not rendered).
    pub features: Vec<T>,
    /// With respect to the background, one value per channel.
    pub background: Vec<T>,
    /// With respect to the projected 2D means, in pixels.
    pub means2d: Vec<[T; 2]>,
    /// The densification statistic of this view: `|| (g_x W/2, g_y H/2) ||` of `means2d`
    /// (see [`crate::stats`]); accumulate it only for visible Gaussians.
    pub ndc_grad_norms: Vec<T>,
}

fn scene_err(msg: String) -> RasterError {
    RasterError::Scene(msg)
}

/// Checks the scene arrays needed by `channels` and returns the channel count.
fn validate<T: Real>(
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
) -> Result<usize, RasterError> {
    let n = scene.len();
    check_len("log_scales", scene.log_scales.len(), n)?;
    check_len("quats", scene.quats.len(), n)?;
    check_len("opacity_logits", scene.opacity_logits.len(), n)?;
    if let Some(degree) = opts.channels.sh_degree() {
        if degree > scene.sh_degree {
            return Err(scene_err(format!(
                "active SH degree {degree} exceeds the scene's degree {}",
                scene.sh_degree
            )));
        }
        if scene.sh_degree > 3 {
            return Err(scene_err(format!(
                "SH degree {} is not supported (0..=3)",
                scene.sh_degree
            )));
        }
        check_len("sh", scene.sh.len(), n * scene.sh_coeffs_per_gaussian())?;
    }
    if opts.channels.has_features() {
        check_len("features", scene.features.len(), n * scene.feature_dim)?;
    }
    let d = opts.channels.count(scene.feature_dim);
    check_len("background", opts.background.len(), d)?;
    Ok(d)
}

fn sigmoid<T: Real>(x: T) -> T {
    T::one() / (T::one() + (-x).exp())
}

/// The `N x D` channel rows for `channels`: borrowed features, or the colours (one per Gaussian
/// whenever colour is rendered) followed by the features.
fn channel_rows<'a, T: Real>(
    channels: Channels,
    scene: &'a FeatureGaussians<T>,
    colors: &'a [[T; 3]],
) -> Cow<'a, [T]> {
    let c = colors;
    match channels {
        Channels::Features => Cow::Borrowed(&scene.features),
        Channels::Color { .. } => Cow::Borrowed(c.as_flattened()),
        Channels::ColorAndFeatures { .. } => {
            let f = scene.feature_dim;
            let mut rows = Vec::with_capacity(c.len() * (3 + f));
            for (i, rgb) in c.iter().enumerate() {
                rows.extend_from_slice(rgb);
                rows.extend_from_slice(&scene.features[i * f..(i + 1) * f]);
            }
            Cow::Owned(rows)
        }
    }
}

/// Renders `scene` from `camera`.
pub fn render<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
) -> Result<Render<T>, RasterError> {
    render_window(camera, scene, opts, PixelWindow::full(camera))
}

/// Renders the part `window` of the image of `scene` seen from `camera`: the Gaussians are
/// projected (and culled) for the whole camera, as [`render`] does, and only the window's pixels
/// are rasterized, with the 2D means moved into the window's pixel coordinates. Each pixel
/// blends the same Gaussians in the same order as in the whole image; its value equals the
/// whole image's up to the rounding of that move (bit for bit for the whole image).
pub fn render_window<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    window: PixelWindow,
) -> Result<Render<T>, RasterError> {
    window.check(camera)?;
    let d = validate(scene, opts)?;
    let projected = project(
        camera,
        &scene.means,
        &scene.quats,
        &scene.log_scales,
        &opts.projection,
    );
    let opacities: Vec<T> = scene
        .opacity_logits
        .par_iter()
        .with_min_len(MIN_CHUNK)
        .map(|&x| sigmoid(x))
        .collect();
    let colors = opts.channels.sh_degree().map(|degree| {
        sh_colors(
            degree,
            scene.sh_coeffs_per_gaussian(),
            &scene.sh,
            &scene.means,
            camera.center_as(),
        )
    });
    let rows = channel_rows(opts.channels, scene, colors.as_deref().unwrap_or(&[]));
    let means2d = window.means2d(camera, &projected.means2d);
    let splats = Splats {
        means2d: &means2d,
        conics: &projected.conics,
        depths: &projected.depths,
        radii: &projected.radii,
        opacities: &opacities,
        channels: &rows,
        channel_count: d,
    };
    let raster = rasterize(&splats, window.width, window.height, &opts.background)?;
    drop(rows);
    drop(means2d);
    Ok(Render {
        window,
        projected,
        opacities,
        colors,
        raster,
    })
}

/// Checks that `render` was made from `camera` for a scene of `scene`'s size: its window fits
/// the camera and it has a projection and an opacity per Gaussian.
fn check_render<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    render: &Render<T>,
) -> Result<(), RasterError> {
    render.window.check(camera)?;
    let n = scene.len();
    check_len("render.opacities", render.opacities.len(), n)?;
    check_len("render.projected", render.projected.means2d.len(), n)?;
    Ok(())
}

/// Validates a backward pass's inputs and runs the rasterizer's backward pass on the render's
/// splats: the gradients with respect to the splats, and the channel count.
fn splat_grads<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    render: &Render<T>,
    v_image: &[T],
    v_alpha: Option<&[T]>,
    v_depth: Option<&[T]>,
) -> Result<(SplatGrads<T>, usize), RasterError> {
    let d = validate(scene, opts)?;
    check_render(camera, scene, render)?;
    let n = scene.len();
    if opts.channels.sh_degree().is_some() != render.colors.is_some() {
        return Err(scene_err(
            "the render was made with other channel options".to_string(),
        ));
    }
    if let Some(c) = &render.colors {
        check_len("render.colors", c.len(), n)?;
    }
    let rows = channel_rows(
        opts.channels,
        scene,
        render.colors.as_deref().unwrap_or(&[]),
    );
    let p = &render.projected;
    // The 2D means move by a constant into the window, so their gradient is unchanged.
    let means2d = render.window.means2d(camera, &p.means2d);
    let splats = Splats {
        means2d: &means2d,
        conics: &p.conics,
        depths: &p.depths,
        radii: &p.radii,
        opacities: &render.opacities,
        channels: &rows,
        channel_count: d,
    };
    let cot = Cotangents {
        image: v_image,
        alpha: v_alpha,
        depth: v_depth,
    };
    let g = rasterize_backward(&splats, &render.raster.bins, &opts.background, &cot)?;
    Ok((g, d))
}

/// The feature part of the channel gradients `channels` (`D = d` per Gaussian), in the layout
/// of the scene's `features` (zero when the features were not rendered).
fn feature_grads<T: Real>(
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    channels: &[T],
    d: usize,
) -> Vec<T> {
    let f = scene.feature_dim;
    let feature_offset = match opts.channels {
        Channels::Color { .. } => None,
        Channels::Features => Some(0),
        Channels::ColorAndFeatures { .. } => Some(3),
    };
    let mut features = filled(scene.features.len(), T::zero());
    if let Some(off) = feature_offset {
        for (i, dst) in features
            .chunks_exact_mut(f.max(1))
            .enumerate()
            .take(scene.len())
        {
            dst.copy_from_slice(&channels[i * d + off..i * d + off + f]);
        }
    }
    features
}

/// The gradient with respect to the features alone, for geometry (and colour) held fixed:
/// `render_backward(..).features`, bit for bit, without the backward passes of the opacities,
/// the SH colour and the projection, whose results such a caller would discard. Only the image
/// cotangent reaches the features (the alpha and depth images do not depend on them).
pub fn render_backward_features<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    render: &Render<T>,
    v_image: &[T],
) -> Result<Vec<T>, RasterError> {
    let (g, d) = splat_grads(camera, scene, opts, render, v_image, None, None)?;
    Ok(feature_grads(scene, opts, &g.channels, d))
}

/// The blend weights ([`crate::weights`]) of `render` (made by [`render`] or [`render_window`]
/// from the same camera, scene and options): for fixed geometry, its channel image is
/// `W c + T b`, and `W^T v` is [`render_backward_features`]'s gradient up to the order of the
/// sums.
pub fn render_weights<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    render: &Render<T>,
) -> Result<BlendWeights<T>, RasterError> {
    check_render(camera, scene, render)?;
    let p = &render.projected;
    let means2d = render.window.means2d(camera, &p.means2d);
    let splats = Splats {
        means2d: &means2d,
        conics: &p.conics,
        depths: &p.depths,
        radii: &p.radii,
        opacities: &render.opacities,
        channels: &[],
        channel_count: 0,
    };
    blend_weights(&splats, &render.raster.bins)
}

/// Gradients of the loss `sum v_image image + sum v_alpha alpha + sum v_depth depth` (the images
/// of `render`, from the same camera, scene and options, [`render`] or [`render_window`]; the
/// cotangents cover its window) with respect to the scene parameters and the background. `depth` is the accumulated depth `sum_i w_i z_i`; see
/// [`crate::fold_normalized_depth_cotangent`] for a cotangent on the normalised depth.
pub fn render_backward<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    render: &Render<T>,
    v_image: &[T],
    v_alpha: Option<&[T]>,
    v_depth: Option<&[T]>,
) -> Result<SceneGrads<T>, RasterError> {
    let (mut grads, v_colors) =
        render_backward_before_sh(camera, scene, opts, render, v_image, v_alpha, v_depth)?;
    grads.sh = match (v_colors, opts.channels.sh_degree()) {
        (Some(v_colors), Some(degree)) => {
            let (d_sh, d_means) = sh_colors_backward(
                degree,
                scene.sh_coeffs_per_gaussian(),
                &scene.sh,
                &scene.means,
                camera.center_as(),
                &v_colors,
            );
            add_view_direction_term(&mut grads.means, &d_means);
            d_sh
        }
        _ => filled(scene.sh.len(), [T::zero(); 3]),
    };
    Ok(grads)
}

/// Adds the SH view direction's mean gradients `d_means` (from
/// [`gaussian::sh_colors_backward`] or [`gaussian::sh_colors_backward_rows`]) to the
/// projection's `means`, as [`render_backward`] does: together they are the gradients with
/// respect to the means.
pub fn add_view_direction_term<T: Real>(means: &mut [[T; 3]], d_means: &[[T; 3]]) {
    for (m, dm) in means.iter_mut().zip(d_means) {
        for a in 0..3 {
            m[a] += dm[a];
        }
    }
}

/// What [`render_backward_before_sh`] returns: the gradients without the SH coefficients' (and
/// the means' without the view direction's term), and the colour cotangent when colour was
/// rendered.
pub type GradsBeforeSh<T> = (SceneGrads<T>, Option<Vec<[T; 3]>>);

/// [`render_backward`] stopped before the SH colour backward, for a caller that runs that step
/// itself (the geometry trainer applies Adam to each chunk of SH coefficients as soon as their
/// gradients exist). The returned gradients' `sh` is empty and their `means` lack the view
/// direction's term; the second value is the colour cotangent, one RGB triple per Gaussian
/// (`None` when colour was not rendered). [`gaussian::sh_colors_backward`] on it, with
/// [`add_view_direction_term`], gives the rest of [`render_backward`], bit for bit.
pub fn render_backward_before_sh<T: Real>(
    camera: &Camera,
    scene: &FeatureGaussians<T>,
    opts: &RenderOptions<T>,
    render: &Render<T>,
    v_image: &[T],
    v_alpha: Option<&[T]>,
    v_depth: Option<&[T]>,
) -> Result<GradsBeforeSh<T>, RasterError> {
    let (g, d) = splat_grads(camera, scene, opts, render, v_image, v_alpha, v_depth)?;
    let n = scene.len();
    let p = &render.projected;
    let opacity_logits = g
        .opacities
        .iter()
        .zip(&render.opacities)
        .map(|(&v, &o)| v * o * (T::one() - o))
        .collect();

    let features = feature_grads(scene, opts, &g.channels, d);
    let proj = project_backward(
        camera,
        &scene.means,
        &scene.quats,
        &scene.log_scales,
        &opts.projection,
        p,
        &g.means2d,
        &g.conics,
        &g.depths,
    );
    let means = proj.means;
    // The colour channels come first whenever colour is rendered.
    let v_colors = opts.channels.sh_degree().map(|_| {
        if d == 3 {
            g.channels.as_chunks::<3>().0.to_vec()
        } else {
            (0..n)
                .map(|i| std::array::from_fn(|c| g.channels[i * d + c]))
                .collect()
        }
    });
    let k = &camera.intrinsics;
    let ndc_grad_norms = ndc_grad_norms(&g.means2d, k.width, k.height);
    let grads = SceneGrads {
        means,
        quats: proj.quats,
        log_scales: proj.log_scales,
        opacity_logits,
        // made by the caller's SH step
        sh: Vec::new(),
        features,
        background: g.background,
        means2d: g.means2d,
        ndc_grad_norms,
    };
    Ok((grads, v_colors))
}
