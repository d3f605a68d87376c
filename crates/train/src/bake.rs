//! Baking a style into a plain 3DGS scene.
//!
//! A [`SceneBundle`] renders a stylized view by rasterizing its per-Gaussian features and decoding
//! them ([`runtime::frame`]); a 3DGS viewer only shows SH colours. Baking fits the SH colours of
//! the bundle's frozen geometry to stylized renders, so that the geometry alone, saved in the
//! official `.ply` layout without features, reproduces the style:
//!
//! 1. Target cameras ([`bake_cameras`]): the bundle's cameras scaled by `resolution_scale`; for
//!    each camera and its nearest neighbour (by centre distance), `interpolated_per_pair`
//!    cameras in between ([`gaussian::camera_path::interpolate_pair`] at `s = k / (m + 1)`), which
//!    are not dataset views; optionally `orbit_views` cameras on an orbit around the point the
//!    cameras look at. `held_out` of the interpolated cameras, evenly spread over them, are kept
//!    for evaluation and never trained on; the rest are subsampled evenly to `target_views`.
//! 2. Targets ([`render_targets`]): every camera's stylized view under the given target
//!    statistics, decoded once and clamped to `[0, 1]`. By default
//!    ([`BakeConfig::composite_background`]) the view is then composited over the bundle's RGB
//!    background with the geometry's accumulated opacity `a` from the same camera:
//!    `a * stylized + (1 - a) * background`. The decoder paints every pixel, including those no
//!    Gaussian covers, and a plain scene shows its viewer's background there; fitting the
//!    painted background would only bleed it into the Gaussians at the silhouette. Views are
//!    decoded `render_batch` at a time in parallel (each view on its own, so the images do not
//!    depend on the thread count).
//! 3. Colour solve (fresh bakes, [`BakeConfig::solve_iterations`] > 0): the DC colours, and the
//!    degree-1 coefficients when [`BakeConfig::sh_degree`] is at least 1, are replaced by the
//!    least-squares colours (non-negative, with a ridge on degree 1) for the training targets
//!    through the frozen geometry ([`crate::colour_solve`], a majorize-minimize iteration with
//!    momentum on the renderer's exact linear model), starting from the bundle's own DC colours.
//! 4. Optimisation ([`bake`], [`BakeConfig::iterations`], 0 for the solve alone): the geometry
//!    stage's loss `0.8 L1 + 0.2 (1 - SSIM)`
//!    ([`crate::loss`]) of the colour render ([`crate::render`]) against one target per
//!    iteration, drawn without replacement within a pass over the targets (a seeded shuffle), and
//!    one Adam step of the SH coefficients (3DGS groups `f_dc` and `f_rest`, the latter at the DC
//!    rate divided by 20).
//!
//! # The baked scene
//! Means, rotations and (by default) opacities and scales are those of the bundle; features are
//! dropped (`feature_dim = 0`). SH coefficients are always stored at degree 3, so the `.ply` has
//! the official 62-property layout whatever degree is optimised: the coefficients above
//! [`BakeConfig::sh_degree`] stay zero, which makes a degree-3 render identical to a render at
//! the optimised degree. The DC term and degree 1 start from the colour solve's values (without
//! a solve, the bundle scene's own DC, its diffuse colour, and zero); the higher bands start at
//! zero, because the stylized targets are decoded from a view-consistent feature field and share
//! no view-dependent effects with the photographs the geometry was fitted to; whatever view
//! dependence the decoded views have is fitted to them.
//!
//! # Adapting the geometry
//! With [`BakeConfig::adapt_geometry`], opacity logits and log-scales are optimised too, at small
//! rates (defaults a fifth of the 3DGS rates), and after every step each is projected back into a
//! box around its initial value: `|logit - logit_0| <= opacity_logit_budget` and
//! `|log_scale - log_scale_0| <= log_scale_budget` per axis (defaults 0.5 and 0.1, i.e. scales
//! within a factor `e^{±0.1}`, about ±10%). Means and rotations never change.
//!
//! The background behind the Gaussians is the bundle's RGB background. Every kernel is
//! deterministic for any thread count and the view order comes from the seed, so a bake is
//! reproducible bit for bit.

use std::path::Path;

use gaussian::camera_path::{interpolate_pair, look_at_point, mean_up, orbit_from};
use gaussian::{Camera, FeatureGaussians};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use style::ChannelStats;

use crate::adam::{Adam, AdamConfig};
use crate::checkpoint::{StateReader, StateWriter};
use crate::colour_solve::{solve_colours, SolveSettings, SolveTarget};
use crate::driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
use crate::error::TrainError;
use crate::geometry::View;
use crate::init::{rgb_to_sh_dc, sh_dc_to_rgb};
use crate::loss::{photometric_loss_with_grad, psnr};
use crate::model::{F_DC, F_REST, OPACITY, SCALING};
use crate::render::{render_color, render_color_backward};
use base::event::{Quiet, Stage, Tally};
use base::Fnv1a;
use runtime::bundle::SceneBundle;

/// The SH degree the baked scene stores (the official 3DGS layout).
pub const STORED_SH_DEGREE: usize = 3;

/// Settings of a bake.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BakeConfig {
    /// SH degree that is optimised and rendered (0..=3). The scene always stores degree 3; the
    /// coefficients above this degree stay zero.
    pub sh_degree: usize,
    /// Optimisation iterations after the solve, one target view each (0, the default: the solve
    /// alone; measured, the optimisation adds at most a few tenths of a dB to the degree-1
    /// solve's held-out PSNR in ten times its time).
    pub iterations: u64,
    /// Most iterations of the closed-form colour solve that starts a fresh
    /// bake ([`crate::colour_solve`]; 0: no solve, the optimisation starts from the bundle's
    /// colours).
    pub solve_iterations: usize,
    /// Training targets the colour solve fits, spread evenly over them (0: all of
    /// [`BakeConfig::target_views`]). Each solve iteration applies every one of them forward
    /// and backward.
    pub solve_views: usize,
    /// The colour solve's ridge on the degree-1 SH coefficients, relative to each Gaussian's
    /// total blend weight ([`crate::colour_solve::SolveSettings::ridge`]); the solve fits
    /// degree 1 when [`BakeConfig::sh_degree`] is at least 1, else the DC colours alone.
    pub solve_ridge: f64,
    /// Adam rate of the SH DC coefficients (3DGS: 0.0025).
    pub feature_lr: f64,
    /// The higher SH coefficients use `feature_lr / feature_rest_divisor` (3DGS: 20).
    pub feature_rest_divisor: f64,
    /// Weight of `1 - SSIM` in the loss (3DGS: 0.2).
    pub lambda_dssim: f64,
    /// Adam hyper-parameters (3DGS uses eps 1e-15).
    pub adam: AdamConfig,
    /// Composite the stylized targets over the background with the geometry's opacity (see the
    /// module documentation); without it the targets are the decoded views as they are.
    pub composite_background: bool,
    /// Also optimise opacity logits and log-scales, within the budgets below.
    pub adapt_geometry: bool,
    /// Adam rate of the opacity logits when adapting (a fifth of the 3DGS 0.05).
    pub opacity_lr: f64,
    /// Adam rate of the log-scales when adapting (a fifth of the 3DGS 0.005).
    pub scaling_lr: f64,
    /// Largest change of an opacity logit from its initial value.
    pub opacity_logit_budget: f32,
    /// Largest change of a log-scale from its initial value, per axis.
    pub log_scale_budget: f32,
    /// Number of training targets; the candidates (dataset, interpolated and orbit cameras, less
    /// the held-out ones) are subsampled evenly to this many. 0 keeps them all. The default, 64,
    /// is where the degree-1 solve alone matches a 3,000-iteration optimisation on every
    /// candidate (docs/results.md).
    pub target_views: usize,
    /// Interpolated cameras between each camera and its nearest neighbour.
    pub interpolated_per_pair: usize,
    /// Cameras on an orbit around the point the bundle's cameras look at (0: none).
    pub orbit_views: usize,
    /// Interpolated cameras held out for evaluation (never trained on).
    pub held_out: usize,
    /// Image size of the targets relative to the bundle's cameras.
    pub resolution_scale: f64,
    /// Views decoded at the same time while rendering targets (bounds the memory).
    pub render_batch: usize,
    /// Working memory of the networks per view decoded, in MiB: each view is decoded in tiles
    /// that fit it ([`SceneBundle::decode_in_tiles`]; the targets do not depend on it).
    pub tile_budget_mib: u64,
    /// Seed of the view order.
    pub seed: u64,
    /// Iterations between the periodic checkpoints of the optimisation (0: only when stopped).
    pub checkpoint_interval: u64,
    /// Iterations between log lines (0: none).
    pub log_interval: u64,
}

impl Default for BakeConfig {
    fn default() -> Self {
        BakeConfig {
            sh_degree: 3,
            iterations: 0,
            solve_iterations: 8,
            solve_views: 0,
            solve_ridge: 0.001,
            feature_lr: 0.0025,
            feature_rest_divisor: 20.0,
            lambda_dssim: 0.2,
            adam: AdamConfig {
                eps: 1e-15,
                ..AdamConfig::default()
            },
            composite_background: true,
            adapt_geometry: false,
            opacity_lr: 0.01,
            scaling_lr: 0.001,
            opacity_logit_budget: 0.5,
            log_scale_budget: 0.1,
            target_views: 64,
            interpolated_per_pair: 2,
            orbit_views: 0,
            held_out: 4,
            resolution_scale: 1.0,
            render_batch: 4,
            tile_budget_mib: runtime::DEFAULT_TILE_BUDGET_BYTES >> 20,
            seed: 0,
            checkpoint_interval: crate::driver::DEFAULT_CHECKPOINT_INTERVAL,
            log_interval: 0,
        }
    }
}

impl BakeConfig {
    /// Checks that every value can work.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::Config(m));
        if self.sh_degree > STORED_SH_DEGREE {
            return bad(format!("bake sh_degree {} is above 3", self.sh_degree));
        }
        if !(self.solve_ridge.is_finite() && self.solve_ridge > 0.0) {
            return bad(format!(
                "solve_ridge {} is not a positive number",
                self.solve_ridge
            ));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return bad(format!(
                "lambda_dssim {} is outside [0, 1]",
                self.lambda_dssim
            ));
        }
        if !(self.resolution_scale.is_finite() && self.resolution_scale > 0.0) {
            return bad(format!(
                "resolution_scale {} is not a positive number",
                self.resolution_scale
            ));
        }
        if self.render_batch == 0 {
            return bad("render_batch is 0".into());
        }
        if self.tile_budget_mib == 0 {
            return bad("tile_budget_mib is 0".into());
        }
        let rates = [
            ("feature_lr", self.feature_lr),
            ("opacity_lr", self.opacity_lr),
            ("scaling_lr", self.scaling_lr),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{name} {v} is not a non-negative number"));
            }
        }
        if !(self.feature_rest_divisor.is_finite() && self.feature_rest_divisor > 0.0) {
            return bad(format!(
                "feature_rest_divisor {} is not a positive number",
                self.feature_rest_divisor
            ));
        }
        let budgets = [
            ("opacity_logit_budget", self.opacity_logit_budget),
            ("log_scale_budget", self.log_scale_budget),
        ];
        for (name, v) in budgets {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{name} {v} is not a non-negative number"));
            }
        }
        Ok(())
    }
}

/// A named target camera.
#[derive(Clone, Debug, PartialEq)]
pub struct NamedCamera {
    /// The view's name, carried by its stylized target.
    pub name: String,
    /// The camera the target is rendered from and the bake is fitted at.
    pub camera: Camera,
}

/// The cameras of a bake.
#[derive(Clone, Debug, PartialEq)]
pub struct BakeCameras {
    /// Cameras whose stylized views are fitted.
    pub train: Vec<NamedCamera>,
    /// Interpolated cameras kept for evaluation.
    pub held_out: Vec<NamedCamera>,
}

/// `count` indices spread evenly over `0..len` (`floor((i + 0.5) len / count)`), all of them
/// when `count >= len`.
fn even_indices(len: usize, count: usize) -> Vec<usize> {
    if count >= len {
        return (0..len).collect();
    }
    (0..count)
        .map(|i| ((2 * i + 1) * len) / (2 * count))
        .collect()
}

/// The target and held-out cameras for `cameras` (the bundle's) under `config`
/// (see the module documentation).
pub fn bake_cameras(cameras: &[Camera], config: &BakeConfig) -> Result<BakeCameras, TrainError> {
    config.validate()?;
    if cameras.is_empty() {
        return Err(TrainError::Config(
            "the bundle has no cameras to bake from".into(),
        ));
    }
    let scaled: Vec<Camera> = cameras
        .iter()
        .map(|c| c.scaled(config.resolution_scale))
        .collect();
    let dataset: Vec<NamedCamera> = scaled
        .iter()
        .enumerate()
        .map(|(i, &camera)| NamedCamera {
            name: format!("view_{i:04}"),
            camera,
        })
        .collect();

    // Each camera with its nearest neighbour; every unordered pair once, in first-seen order.
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for (i, c) in scaled.iter().enumerate() {
        let nearest = scaled
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .map(|(j, o)| (c.center().distance_squared(o.center()), j))
            .min_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        if let Some((_, j)) = nearest {
            let p = (i.min(j), i.max(j));
            if !pairs.contains(&p) {
                pairs.push(p);
            }
        }
    }
    let m = config.interpolated_per_pair;
    let mut interpolated = Vec::with_capacity(pairs.len() * m);
    for &(i, j) in &pairs {
        for k in 1..=m {
            let s = k as f64 / (m + 1) as f64;
            interpolated.push(NamedCamera {
                name: format!("interp_{i:04}_{j:04}_{k}"),
                camera: interpolate_pair(&scaled[i], &scaled[j], s),
            });
        }
    }
    if config.held_out > interpolated.len() {
        return Err(TrainError::Config(format!(
            "{} held-out views asked for, but there are only {} interpolated cameras \
             ({} camera pairs x {m})",
            config.held_out,
            interpolated.len(),
            pairs.len()
        )));
    }
    let held_idx = even_indices(interpolated.len(), config.held_out);
    let mut held_out = Vec::with_capacity(held_idx.len());
    let mut train_interp = Vec::with_capacity(interpolated.len() - held_idx.len());
    for (i, c) in interpolated.into_iter().enumerate() {
        if held_idx.contains(&i) {
            held_out.push(c);
        } else {
            train_interp.push(c);
        }
    }

    let mut orbit = Vec::new();
    if config.orbit_views > 0 {
        let center = look_at_point(&scaled).ok_or_else(|| {
            TrainError::Config(
                "orbit cameras need cameras that look at a common point, but their axes are \
                 parallel"
                    .into(),
            )
        })?;
        // Image "up" is the camera's -y axis; average it over the cameras.
        let up = mean_up(&scaled).ok_or_else(|| {
            TrainError::Config(
                "orbit cameras need an image-up direction, but the cameras' cancel out".into(),
            )
        })?;
        let path = orbit_from(&scaled[0], center, config.orbit_views, up)
            .map_err(|e| TrainError::Config(format!("orbit cameras: {e}")))?;
        orbit = path
            .into_iter()
            .enumerate()
            .map(|(k, camera)| NamedCamera {
                name: format!("orbit_{k:04}"),
                camera,
            })
            .collect();
    }

    let candidates: Vec<NamedCamera> = dataset
        .into_iter()
        .chain(train_interp)
        .chain(orbit)
        .collect();
    let keep = if config.target_views == 0 {
        candidates.len()
    } else {
        config.target_views
    };
    let picked = even_indices(candidates.len(), keep);
    let train = picked.iter().map(|&i| candidates[i].clone()).collect();
    Ok(BakeCameras { train, held_out })
}

/// The stylized view of `camera`: features rendered and decoded under `stats` (in tiles within
/// `tile_budget` bytes, [`SceneBundle::decode_in_tiles`]), clamped to
/// `[0, 1]`, row-major RGB; with `composite`, blended over the bundle's background with the
/// geometry's accumulated opacity (see the module documentation).
pub fn stylized_view(
    bundle: &SceneBundle,
    stats: &ChannelStats<f32>,
    camera: &Camera,
    composite: bool,
    tile_budget: u64,
) -> Result<Vec<f32>, TrainError> {
    let k = camera.intrinsics;
    let features = bundle.render_features(camera)?;
    let (image, _) = bundle.decode_in_tiles(&features, stats, k.width, k.height, tile_budget)?;
    let mut rgb = runtime::frame::rgb_clamped(&image)?.data;
    if composite {
        let bg = bundle.info.background;
        let alpha = render_color(camera, &bundle.scene, 0, bg)?.raster.alpha;
        for (px, &a) in rgb.chunks_exact_mut(3).zip(&alpha) {
            for (v, &b) in px.iter_mut().zip(&bg) {
                *v = a * *v + (1.0 - a) * b;
            }
        }
    }
    Ok(rgb)
}

/// The stylized views of `cameras` ([`stylized_view`], with the configuration's compositing
/// and tile budget), `render_batch` at a time in parallel, each batch counted on `tally`. Returns `Ok(None)` when the run's stop flag is raised (checked
/// between batches).
pub fn render_targets(
    bundle: &SceneBundle,
    stats: &ChannelStats<f32>,
    cameras: &[NamedCamera],
    config: &BakeConfig,
    run: &Run,
    tally: &mut Tally,
) -> Result<Option<Vec<View>>, TrainError> {
    let (composite, batch) = (config.composite_background, config.render_batch);
    let tile_budget = config.tile_budget_mib.saturating_mul(1 << 20);
    let mut views = Vec::with_capacity(cameras.len());
    for chunk in cameras.chunks(batch.max(1)) {
        if run.stop_requested() {
            return Ok(None);
        }
        let images: Vec<Vec<f32>> = chunk
            .par_iter()
            .map(|c| stylized_view(bundle, stats, &c.camera, composite, tile_budget))
            .collect::<Result<_, _>>()?;
        for (c, image) in chunk.iter().zip(images) {
            views.push(View {
                name: c.name.clone(),
                camera: c.camera,
                image,
            });
        }
        tally.advance(chunk.len(), "");
    }
    Ok(Some(views))
}

/// Mean over `views` of the PSNR of `scene`'s colour render (SH degree `sh_degree`, over
/// `background`, clamped to `[0, 1]`) against each view's image. `None` without views.
pub fn mean_psnr(
    scene: &FeatureGaussians<f32>,
    sh_degree: usize,
    background: [f32; 3],
    views: &[View],
) -> Result<Option<f64>, TrainError> {
    if views.is_empty() {
        return Ok(None);
    }
    let mut total = 0.0;
    for v in views {
        let fwd = render_color(&v.camera, scene, sh_degree, background)?;
        let img: Vec<f32> = fwd.raster.image.iter().map(|x| x.clamp(0.0, 1.0)).collect();
        total += psnr(&img, &v.image, v.shape())?;
    }
    Ok(Some(total / views.len() as f64))
}

/// The mean PSNR of a baked scene against the stylized views of arbitrary `cameras` (rendered
/// here from `bundle` under `stats` as `config` renders targets), with the baked scene rendered
/// at its stored SH degree over the bundle's background. `None` without cameras.
pub fn evaluate_baked(
    bundle: &SceneBundle,
    stats: &ChannelStats<f32>,
    baked: &FeatureGaussians<f32>,
    cameras: &[Camera],
    config: &BakeConfig,
) -> Result<Option<f64>, TrainError> {
    let named: Vec<NamedCamera> = cameras
        .iter()
        .enumerate()
        .map(|(i, &camera)| NamedCamera {
            name: format!("eval_{i:04}"),
            camera,
        })
        .collect();
    // Without a stop flag the rendering always completes.
    let views = render_targets(
        bundle,
        stats,
        &named,
        config,
        &Run::in_memory(),
        &mut Tally::start(Stage::BakeTargets, named.len(), &Quiet),
    )?
    .unwrap_or_default();
    mean_psnr(baked, baked.sh_degree, bundle.info.background, &views)
}

/// The scene baking starts from: the bundle's geometry without features, SH stored at degree 3
/// with the bundle's DC and zero higher bands.
pub fn initial_baked_scene(
    scene: &FeatureGaussians<f32>,
) -> Result<FeatureGaussians<f32>, TrainError> {
    let n = scene.len();
    let k_in = scene.sh_coeffs_per_gaussian();
    if scene.sh.len() != n * k_in
        || scene.log_scales.len() != n
        || scene.quats.len() != n
        || scene.opacity_logits.len() != n
    {
        return Err(TrainError::Shape(format!(
            "inconsistent bundle scene: {n} means, {} log-scales, {} quaternions, {} opacities, \
             {} SH rows for degree {}",
            scene.log_scales.len(),
            scene.quats.len(),
            scene.opacity_logits.len(),
            scene.sh.len(),
            scene.sh_degree
        )));
    }
    let k = (STORED_SH_DEGREE + 1) * (STORED_SH_DEGREE + 1);
    let mut sh = vec![[0.0f32; 3]; n * k];
    for i in 0..n {
        sh[i * k] = scene.sh[i * k_in];
    }
    Ok(FeatureGaussians {
        means: scene.means.clone(),
        log_scales: scene.log_scales.clone(),
        quats: scene.quats.clone(),
        opacity_logits: scene.opacity_logits.clone(),
        sh_degree: STORED_SH_DEGREE,
        sh,
        feature_dim: 0,
        features: Vec::new(),
    })
}

/// What a bake produced.
#[derive(Clone, Debug)]
pub struct BakeReport {
    /// The baked scene: `feature_dim = 0`, SH stored at degree 3 (official layout).
    pub scene: FeatureGaussians<f32>,
    /// How the optimisation ended: iterations, time, interruption (`scene` is then the partial
    /// bake) and the stop checkpoint.
    pub run: RunOutcome,
    /// Number of training targets.
    pub train_views: usize,
    /// Number of held-out targets.
    pub held_out_views: usize,
    /// Mean PSNR of the baked scene against the training targets.
    pub train_psnr: f64,
    /// Mean PSNR of the baked scene against the held-out targets (`None` without held-out views).
    pub held_out_psnr: Option<f64>,
    /// Mean PSNR of the bundle's own colours (its SH at its degree) against the training targets,
    /// before baking.
    pub unbaked_train_psnr: f64,
    /// Mean PSNR of the bundle's own colours against the held-out targets, before baking
    /// (`None` without held-out views).
    pub unbaked_held_out_psnr: Option<f64>,
    /// Wall time of the target rendering, in seconds.
    pub target_seconds: f64,
    /// The closed-form colour solve that started the bake (`None` when resumed or disabled).
    pub solve: Option<BakeSolveReport>,
}

/// What the closed-form colour solve of a bake did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BakeSolveReport {
    /// SH degree solved for: 0 (DC colours) or 1 (and the degree-1 coefficients).
    pub degree: usize,
    /// Iterations run.
    pub iterations: usize,
    /// The last step's size relative to the first's.
    pub residual: f64,
    /// Gaussians no training target sees, which kept the bundle's colour.
    pub unseen: usize,
    /// Wall time, in seconds.
    pub seconds: f64,
    /// Mean PSNR of the solved scene (before any optimisation) against the held-out targets.
    pub held_out_psnr: Option<f64>,
}

/// Replaces the DC colours of `scene` (SH stored at degree 3, higher bands zero), and at
/// `degree` 1 its degree-1 coefficients, by the non-negative least-squares colours for
/// `targets` ([`crate::colour_solve`]), starting from its own DC colours.
fn solve_colours_of(
    scene: &mut FeatureGaussians<f32>,
    targets: &[View],
    background: [f32; 3],
    settings: SolveSettings,
) -> Result<BakeSolveReport, TrainError> {
    let start = std::time::Instant::now();
    let k = scene.sh_coeffs_per_gaussian();
    let n = scene.len();
    let initial: Vec<[f32; 3]> = (0..n)
        .map(|i| scene.sh[i * k].map(|dc| sh_dc_to_rgb(dc as f64) as f32))
        .collect();
    let solve_targets: Vec<SolveTarget<'_, f32>> = targets
        .iter()
        .map(|v| SolveTarget {
            camera: &v.camera,
            image: &v.image,
        })
        .collect();
    let out = solve_colours(scene, &solve_targets, background, &initial, settings)?;
    for (i, c) in out.colours.iter().enumerate() {
        scene.sh[i * k] = c.map(|v| rgb_to_sh_dc(v as f64) as f32);
    }
    for (i, rest) in out.degree_one.iter().enumerate() {
        scene.sh[i * k + 1..i * k + 4].copy_from_slice(rest);
    }
    Ok(BakeSolveReport {
        degree: settings.degree,
        iterations: out.iterations,
        residual: out.residuals.last().copied().unwrap_or(1.0),
        unseen: out.unseen,
        seconds: start.elapsed().as_secs_f64(),
        held_out_psnr: None,
    })
}

/// Projects every value of `values` into `[initial - budget, initial + budget]`.
fn project_into_budget(values: &mut [f32], initial: &[f32], budget: f32) {
    values
        .par_iter_mut()
        .zip(initial)
        .for_each(|(v, &v0)| *v = v.clamp(v0 - budget, v0 + budget));
}

/// The stylized targets of a bake ([`render_bake_targets`], or read back from target files).
#[derive(Clone, Debug)]
pub struct BakeTargets {
    /// Targets fitted to.
    pub train: Vec<View>,
    /// Targets held out for evaluation.
    pub held_out: Vec<View>,
    /// Wall time of their rendering, in seconds.
    pub seconds: f64,
}

/// Checks that target statistics have the bundle's lifter width.
fn check_stats(bundle: &SceneBundle, stats: &ChannelStats<f32>) -> Result<(), TrainError> {
    let c = bundle.lifter.out_channels();
    if stats.batch() != 1 || stats.channels() != c {
        return Err(TrainError::Shape(format!(
            "target statistics are {}x{}, expected 1x{c}",
            stats.batch(),
            stats.channels()
        )));
    }
    Ok(())
}

/// Every target camera of a bake in one sequence: the held-out cameras, then the training ones
/// (the order in which [`bake`] renders them, and the items a sharded target rendering splits).
pub fn target_sequence(cameras: &BakeCameras) -> Vec<NamedCamera> {
    cameras
        .held_out
        .iter()
        .chain(&cameras.train)
        .cloned()
        .collect()
}

/// Renders the stylized targets of `cameras` (a block of [`target_sequence`], or all of it),
/// counting them as [`Stage::BakeTargets`] units on `run`'s sink. A stop request fails with
/// [`TrainError::Interrupted`].
pub fn render_bake_targets(
    bundle: &SceneBundle,
    stats: &ChannelStats<f32>,
    cameras: &[NamedCamera],
    config: &BakeConfig,
    run: &Run,
) -> Result<(Vec<View>, f64), TrainError> {
    config.validate()?;
    bundle.validate()?;
    check_stats(bundle, stats)?;
    let mut tally = Tally::start(Stage::BakeTargets, cameras.len(), run.sink);
    let views = render_targets(bundle, stats, cameras, config, run, &mut tally)?
        .ok_or_else(|| TrainError::Interrupted("rendering the stylized targets".into()))?;
    Ok((views, tally.finish()))
}

/// Bakes the style given by `stats` (from [`SceneBundle::target_stats`], or any statistics of
/// the lifter's width) into the bundle's geometry (see the module documentation): renders the
/// targets ([`render_bake_targets`]) and fits them ([`bake_targets`]). A stop request during the
/// target rendering fails with [`TrainError::Interrupted`].
pub fn bake(
    bundle: &SceneBundle,
    stats: &ChannelStats<f32>,
    config: &BakeConfig,
    resume: Option<&Path>,
    run: &Run,
) -> Result<BakeReport, TrainError> {
    // The configuration, the bundle and the statistics are checked before any rendering.
    let cameras = bake_cameras(&bundle.cameras(), config)?;
    let (mut views, seconds) =
        render_bake_targets(bundle, stats, &target_sequence(&cameras), config, run)?;
    let train = views.split_off(cameras.held_out.len());
    let targets = BakeTargets {
        train,
        held_out: views,
        seconds,
    };
    bake_targets(bundle, targets, config, resume, run)
}

/// Fits the bundle's geometry to rendered targets (see the module documentation). The
/// optimisation runs through the [driver](crate::driver): with an output folder in `run` it
/// writes `checkpoint.safetensors` there periodically and when stopped, and `resume` continues
/// from such a checkpoint exactly (the targets must be the same ones, bit for bit); a stop
/// request ends the run with the partial bake.
pub fn bake_targets(
    bundle: &SceneBundle,
    targets: BakeTargets,
    config: &BakeConfig,
    resume: Option<&Path>,
    run: &Run,
) -> Result<BakeReport, TrainError> {
    config.validate()?;
    bundle.validate()?;
    let background = bundle.info.background;
    let BakeTargets {
        train,
        held_out,
        seconds: target_seconds,
    } = targets;
    if train.is_empty() {
        return Err(TrainError::Config("no training targets to bake".into()));
    }

    let unbaked_train_psnr =
        mean_psnr(&bundle.scene, bundle.scene.sh_degree, background, &train)?.unwrap_or(0.0);
    let unbaked_held_out_psnr =
        mean_psnr(&bundle.scene, bundle.scene.sh_degree, background, &held_out)?;

    let mut initial = initial_baked_scene(&bundle.scene)?;
    // A fresh bake starts from the least-squares DC colours; a resumed one from its checkpoint.
    let solve = match (resume, config.solve_iterations) {
        (None, iterations @ 1..) => {
            let chosen: Vec<View> = match config.solve_views {
                0 => train.clone(),
                k => even_indices(train.len(), k)
                    .into_iter()
                    .map(|i| train[i].clone())
                    .collect(),
            };
            let settings = SolveSettings {
                iterations,
                degree: config.sh_degree.min(1),
                ridge: config.solve_ridge,
                ..SolveSettings::default()
            };
            let report = solve_colours_of(&mut initial, &chosen, background, settings)?;
            let held_out_psnr = mean_psnr(&initial, config.sh_degree, background, &held_out)?;
            Some(BakeSolveReport {
                held_out_psnr,
                ..report
            })
        }
        _ => None,
    };
    let mut baker = match resume {
        None => Baker::new(initial, &train, background, config)?,
        Some(p) => Baker::resume(p, initial, &train, background, config)?,
    };
    let outcome = baker.train(run)?;
    let scene = baker.scene;

    let d = config.sh_degree;
    Ok(BakeReport {
        solve,
        train_psnr: mean_psnr(&scene, d, background, &train)?.unwrap_or(0.0),
        held_out_psnr: mean_psnr(&scene, d, background, &held_out)?,
        scene,
        run: outcome,
        train_views: train.len(),
        held_out_views: held_out.len(),
        unbaked_train_psnr,
        unbaked_held_out_psnr,
        target_seconds,
    })
}

/// The value of the `format` metadata entry of bake target files.
pub const BAKE_TARGET_FORMAT: &str = "dsgs-bake-target-v1";

/// Encodes one stylized target as a safetensors file: the image as `image` (`f32`,
/// `[height, width, 3]`, its exact bits) and the view's name as metadata. Its camera is not
/// stored: a reader takes it from the bake's cameras and checks the name and size.
pub fn target_to_bytes(view: &View) -> Result<Vec<u8>, TrainError> {
    let k = view.camera.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    if view.image.len() != w * h * 3 {
        return Err(TrainError::Shape(format!(
            "target `{}` has {} values for a {w}x{h} camera",
            view.name,
            view.image.len()
        )));
    }
    let mut st = StateWriter::new(BAKE_TARGET_FORMAT);
    st.meta("name", &view.name);
    st.f32s("image", vec![h, w, 3], &view.image);
    st.finish()
}

/// Reads a target file ([`target_to_bytes`]) written for `camera`: the file must hold a view
/// of that name and the camera's size. `path` names the file in errors.
pub fn target_from_bytes(
    bytes: &[u8],
    path: &Path,
    camera: &NamedCamera,
) -> Result<View, TrainError> {
    let r = StateReader::new(bytes, path, BAKE_TARGET_FORMAT)?;
    let name = r.meta_str("name")?;
    if name != camera.name {
        return Err(r.err(format!(
            "holds the target `{name}`, expected `{}`",
            camera.name
        )));
    }
    let k = camera.camera.intrinsics;
    let image = r.f32s("image", &[k.height as usize, k.width as usize, 3])?;
    Ok(View {
        name: camera.name.clone(),
        camera: camera.camera,
        image,
    })
}

/// The value of the `format` metadata entry of bake checkpoints.
pub const BAKE_CHECKPOINT_FORMAT: &str = "dsgs-bake-checkpoint-v1";

/// FNV-1a over the targets' names, sizes and pixel bits: which targets a checkpoint was fitted
/// to.
fn targets_fingerprint(targets: &[View]) -> String {
    let mut h = Fnv1a::new();
    for v in targets {
        h.eat(v.name.as_bytes());
        let k = v.camera.intrinsics;
        h.eat(&[k.width.to_le_bytes(), k.height.to_le_bytes()].concat());
        v.image.iter().for_each(|&x| h.eat_f32(x));
    }
    h.hex()
}

/// A bake optimisation in progress: `scene`'s SH colours (and, with `adapt_geometry`, its
/// opacities and scales within their budgets) fitted to `targets`, one view an iteration.
pub struct Baker<'a> {
    /// The scene being baked (SH stored at degree 3).
    pub scene: FeatureGaussians<f32>,
    targets: &'a [View],
    background: [f32; 3],
    config: BakeConfig,
    adam: Adam<f32>,
    g_dc: usize,
    g_rest: Option<usize>,
    geometry_groups: Option<(usize, usize)>,
    opacity0: Vec<f32>,
    log_scales0: Vec<f32>,
    rng: StdRng,
    /// Target indices left in the current pass, popped from the back.
    order: Vec<usize>,
    /// Running averages of the loss and PSNR.
    ema: Option<[f64; 2]>,
    step: u64,
}

impl<'a> Baker<'a> {
    /// A bake at step 0 from `scene`, which must store SH at degree 3.
    pub fn new(
        scene: FeatureGaussians<f32>,
        targets: &'a [View],
        background: [f32; 3],
        config: &BakeConfig,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        if targets.is_empty() {
            return Err(TrainError::Config("no training targets to bake".into()));
        }
        if scene.sh_degree != STORED_SH_DEGREE {
            return Err(TrainError::Shape(format!(
                "the scene stores SH degree {}, baking needs {STORED_SH_DEGREE}",
                scene.sh_degree
            )));
        }
        for v in targets {
            let s = v.shape();
            if v.image.len() != s.len() {
                return Err(TrainError::Shape(format!(
                    "target `{}` has {} values for a {}x{} camera",
                    v.name,
                    v.image.len(),
                    s.width,
                    s.height
                )));
            }
        }
        let n = scene.len();
        let k_opt = (config.sh_degree + 1) * (config.sh_degree + 1);
        let mut adam = Adam::<f32>::new(config.adam);
        let g_dc = adam.add_param(F_DC, config.feature_lr, n, 3);
        let g_rest = (k_opt > 1).then(|| {
            adam.add_param(
                F_REST,
                config.feature_lr / config.feature_rest_divisor,
                n,
                3 * (k_opt - 1),
            )
        });
        let geometry_groups = config.adapt_geometry.then(|| {
            (
                adam.add_param(OPACITY, config.opacity_lr, n, 1),
                adam.add_param(SCALING, config.scaling_lr, n, 3),
            )
        });
        Ok(Baker {
            opacity0: scene.opacity_logits.clone(),
            log_scales0: scene.log_scales.as_flattened().to_vec(),
            scene,
            targets,
            background,
            config: config.clone(),
            adam,
            g_dc,
            g_rest,
            geometry_groups,
            rng: StdRng::seed_from_u64(config.seed),
            order: Vec::new(),
            ema: None,
            step: 0,
        })
    }

    /// The bake of `checkpoint`, continuing from `initial` (the scene baking started from) on
    /// the same `targets` and configuration.
    pub fn resume(
        checkpoint: &Path,
        initial: FeatureGaussians<f32>,
        targets: &'a [View],
        background: [f32; 3],
        config: &BakeConfig,
    ) -> Result<Self, TrainError> {
        let bytes = std::fs::read(checkpoint).map_err(|e| TrainError::io(checkpoint, e))?;
        let r = StateReader::new(&bytes, checkpoint, BAKE_CHECKPOINT_FORMAT)?;
        let mut b = Baker::new(initial, targets, background, config)?;
        // The same configuration, but for the tile budget, which changes no result (and is
        // absent from the checkpoints of earlier versions).
        let stored: BakeConfig = serde_json::from_str(r.meta_str("config")?)
            .map_err(|e| r.err(format!("its configuration cannot be read: {e}")))?;
        let same = BakeConfig {
            tile_budget_mib: config.tile_budget_mib,
            ..stored
        };
        if &same != config {
            return Err(r.err(
                "it was written with another bake configuration; resume with the same settings"
                    .into(),
            ));
        }
        let (found, want) = (r.meta_str("targets")?, targets_fingerprint(targets));
        if found != want {
            return Err(r.err(format!(
                "it belongs to other targets (fingerprint {found}, these are {want}): another \
                 bundle, style or strength"
            )));
        }
        let n = b.scene.len();
        let k = b.scene.sh_coeffs_per_gaussian();
        let sh = r.f32s("sh", &[n, k, 3])?;
        b.scene.sh = sh.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        b.scene.opacity_logits = r.f32s("opacity_logits", &[n])?;
        let ls = r.f32s("log_scales", &[n, 3])?;
        b.scene.log_scales = ls.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        let adam = r.adam(config.adam)?;
        let shapes = |a: &Adam<f32>| -> Vec<(String, usize, usize)> {
            let p = a.params();
            p.iter()
                .map(|p| (p.name.clone(), p.rows(), p.width()))
                .collect()
        };
        if shapes(&adam) != shapes(&b.adam) {
            return Err(r.err(format!(
                "optimiser tensors {:?} do not fit this bake",
                shapes(&adam)
            )));
        }
        b.adam = adam;
        b.ema = r.ema()?;
        let step: u64 = r.meta_parse("step")?;
        // The view order: the same draws from the seeded generator as the run so far.
        for _ in 0..step {
            b.next_target();
        }
        b.step = step;
        Ok(b)
    }

    /// The index of the next target: the passes over the targets follow a seeded shuffle.
    fn next_target(&mut self) -> usize {
        if self.order.is_empty() {
            self.order = (0..self.targets.len()).collect();
            self.order.shuffle(&mut self.rng);
            self.order.reverse(); // popped from the back: the shuffled order, front first
        }
        self.order.pop().expect("refilled above")
    }

    /// Completed iterations.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// One iteration: render, loss against the next target, one Adam step, projection into
    /// the budgets. Returns the loss and the PSNR of the render.
    pub fn train_step(&mut self) -> Result<(f64, f64), TrainError> {
        let view = &self.targets[self.next_target()];
        let (d, bg) = (self.config.sh_degree, self.background);
        let stride = 3 * self.scene.sh_coeffs_per_gaussian();
        let shape = view.shape();
        let fwd = render_color(&view.camera, &self.scene, d, bg)?;
        let (loss, v_image) = photometric_loss_with_grad(
            &fwd.raster.image,
            &view.image,
            shape,
            self.config.lambda_dssim,
        )?;
        let step_psnr = psnr(&fwd.raster.image, &view.image, shape)?;
        let grads = render_color_backward(&view.camera, &self.scene, d, bg, &fwd, &v_image)?;
        drop(fwd);

        let scene = &mut self.scene;
        let sh_grads = grads.sh.as_flattened();
        let adam = &mut self.adam;
        adam.step_strided(self.g_dc, scene.sh.as_flattened_mut(), sh_grads, stride, 0)?;
        if let Some(g) = self.g_rest {
            adam.step_strided(g, scene.sh.as_flattened_mut(), sh_grads, stride, 3)?;
        }
        if let Some((g_op, g_sc)) = self.geometry_groups {
            let c = &self.config;
            adam.step(g_op, &mut scene.opacity_logits, &grads.opacity_logits)?;
            project_into_budget(
                &mut scene.opacity_logits,
                &self.opacity0,
                c.opacity_logit_budget,
            );
            let log_scales = scene.log_scales.as_flattened_mut();
            adam.step(g_sc, log_scales, grads.log_scales.as_flattened())?;
            project_into_budget(log_scales, &self.log_scales0, c.log_scale_budget);
        }

        self.step += 1;
        self.ema = Some(match self.ema {
            None => [loss.total, step_psnr],
            Some([l, p]) => [0.4 * loss.total + 0.6 * l, 0.4 * step_psnr + 0.6 * p],
        });
        Ok((loss.total, step_psnr))
    }

    /// The checkpoint as safetensors bytes.
    pub fn checkpoint_bytes(&self) -> Result<Vec<u8>, TrainError> {
        let mut w = StateWriter::new(BAKE_CHECKPOINT_FORMAT);
        w.meta("step", self.step);
        w.meta(
            "config",
            serde_json::to_string(&self.config).map_err(|e| TrainError::Config(e.to_string()))?,
        );
        w.meta("targets", targets_fingerprint(self.targets));
        w.ema(self.ema.as_ref().map(|e| e.as_slice()));
        let (n, k) = (self.scene.len(), self.scene.sh_coeffs_per_gaussian());
        w.f32s("sh", vec![n, k, 3], self.scene.sh.as_flattened());
        w.f32s("opacity_logits", vec![n], &self.scene.opacity_logits);
        w.f32s(
            "log_scales",
            vec![n, 3],
            self.scene.log_scales.as_flattened(),
        );
        w.adam(&self.adam);
        w.finish()
    }

    /// Writes a checkpoint atomically.
    pub fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        base::write_atomic(path, &self.checkpoint_bytes()?).map_err(|e| TrainError::io(path, e))
    }

    /// Runs the optimisation to `config.iterations` through the [driver](crate::driver).
    pub fn train(&mut self, run: &Run) -> Result<RunOutcome, TrainError> {
        let cadence = Cadence {
            checkpoint_interval: self.config.checkpoint_interval,
            log_interval: self.config.log_interval,
        };
        drive(self, cadence, run)
    }
}

impl TrainingLoop for Baker<'_> {
    const STAGE: Stage = Stage::Bake;

    fn step(&self) -> u64 {
        self.step
    }

    fn iterations(&self) -> u64 {
        self.config.iterations
    }

    fn advance(&mut self) -> Result<(), TrainError> {
        self.train_step().map(|_| ())
    }

    fn status(&self) -> String {
        let [l, p] = self.ema.unwrap_or_default();
        format!("loss {l:.5} psnr {p:.2}")
    }

    fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        Baker::save_checkpoint(self, path)
    }
}
