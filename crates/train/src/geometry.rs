//! The geometry stage: fitting a 3D Gaussian Splatting scene to posed images, iteration by
//! iteration as the original 3DGS `train.py` does.
//!
//! Iteration `i` (counted from 1):
//! 1. the position learning rate is set from its schedule at `i`;
//! 2. every `sh_degree_interval` (1,000) iterations the active SH degree grows by one;
//! 3. a training view is drawn without replacement from the views not yet seen in this pass
//!    (the pass restarts when all have been seen);
//! 4. the scene is rendered over the background colour, the loss
//!    `0.8 L1 + 0.2 (1 - SSIM)` is taken against the image and differentiated;
//! 5. below `densify_until_iter`, the densification statistics are gathered, density control and
//!    opacity resets run on their schedule ([`crate::density`]);
//! 6. Adam steps every group whose tensor was not replaced in step 5: in 3DGS, density control
//!    replaces every optimised tensor (which then has no gradient and is skipped by
//!    `optimizer.step()`), and an opacity reset replaces the opacity tensor. The last iteration
//!    takes no optimiser step (`if iteration < opt.iterations`). The SH colour backward runs
//!    inside the SH groups' Adam pass ([`GaussianModel::step_from_colours`], the bits of the
//!    full gradients followed by the step), so it is skipped with them.
//!
//! # Run length
//!
//! The defaults are the 30,000-iteration schedule of 3DGS. [`GeometryConfig::scaled_to`] gives
//! the same schedule stretched or compressed to `n` iterations:
//!
//! * points in time scale by `n / iterations`, rounded to the nearest step (halves up), 0
//!   staying 0, a point of the run (`1..=iterations`) staying in it (`1..=n`) and a later one
//!   after it: the position learning rate's decay length (`position_lr_max_steps`) and warm-up
//!   (`position_lr_delay_steps`), the densification window (`densify_from_iter`,
//!   `densify_until_iter`), and the test, save and checkpoint iterations (in their order, equal
//!   neighbours merged). So the position rate reaches its final value at the end of the run,
//!   and, with the defaults, densification stops half-way through it as in 3DGS, leaving the
//!   second half to refine: the last density-control pass never falls on the last iteration;
//! * intervals scale by `n / iterations` too, rounded the same way, at least 1 (0, off, stays
//!   0): `sh_degree_interval` (so the full SH degree arrives at the same fraction of the run),
//!   `densification_interval` and `opacity_reset_interval`. These last two set how many views a
//!   density decision averages and how long opacities have to recover after a reset: times
//!   that depend on the views and the learning rates, not on the run length. So when a run is
//!   shortened they stay at least
//!   [`density::MIN_DENSIFICATION_INTERVAL`](crate::density::MIN_DENSIFICATION_INTERVAL) (50)
//!   and [`density::MIN_OPACITY_RESET_INTERVAL`](crate::density::MIN_OPACITY_RESET_INTERVAL)
//!   (300) steps (or their configured values, if smaller). At 600 iterations, say, that is a
//!   density-control pass every 50 steps in (10, 300) and no periodic opacity reset (only the
//!   white-background one at `densify_from_iter`), where pure proportion would densify every 2
//!   steps and reset every 60 (on lego at 1/8 scale, white, 600 iterations: 27.6 dB held-out
//!   PSNR with 14k Gaussians, against 26.0 dB for pure proportion and 23.8 dB for the unscaled
//!   30,000-step schedule, whose first density-control pass is a prune at the last iteration);
//! * `checkpoint_interval` and `log_interval` are kept: they pace the safety copies and the
//!   log, not the optimisation.
//!
//! Scaling to the configured length changes nothing. Scaling to another length and back
//! restores every point in time to within rounding, and every interval too, except one that a
//! minimum raised on the way (shortened below it, or configured below it and stretched and
//! shortened back).
//!
//! Randomness (view order, split samples) comes from a generator seeded by the run seed and the
//! iteration number, so a run resumed from a checkpoint continues exactly as the uninterrupted
//! run would. Every kernel is deterministic for any thread count.

use std::path::{Path, PathBuf};

use gaussian::dataset::Dataset;
use gaussian::{Camera, FeatureGaussians};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::adam::AdamConfig;
use crate::checkpoint::{CheckpointParts, GeometryCheckpoint};
use crate::density::{scale_interval, scale_point, DensifyConfig, DensifyReport};
use crate::driver::{drive, Cadence, Run, RunOutcome, TrainingLoop, DEFAULT_CHECKPOINT_INTERVAL};
use crate::error::TrainError;
use crate::init::{gaussians_from_points, random_points_in_box, PointCloud};
use crate::loss::{photometric_loss_with_grad, psnr, LossTerms};
use crate::model::{ColourGrads, GaussianModel, LearningRates, OPACITY};
use crate::render::{render_color, render_color_backward_before_sh};
use crate::ssim::{ssim, ImageShape};
use base::event::{Event, Metric, Sink, Stage};

/// Settings of a geometry run. Defaults are those of the original 3DGS code.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GeometryConfig {
    /// Total iterations.
    pub iterations: u64,
    /// Seed of every random choice (initial points, view order, split samples).
    pub seed: u64,
    /// Maximum SH degree.
    pub sh_degree: usize,
    /// Iterations between increments of the active SH degree.
    pub sh_degree_interval: u64,
    /// Weight of `1 - SSIM` in the loss.
    pub lambda_dssim: f64,
    /// Background colour behind the Gaussians (and behind transparent dataset pixels).
    pub background: [f32; 3],
    /// Random initial points when the dataset has none (NeRF-synthetic).
    pub random_init_points: usize,
    /// Half side of the cube the random points fill.
    pub random_init_half_extent: f64,
    /// Adam learning rates per parameter group and the position schedule.
    pub learning_rates: LearningRates,
    /// Adam hyper-parameters; 3DGS uses eps 1e-15.
    pub adam: AdamConfig,
    /// Density control: cloning, splitting, pruning and opacity resets.
    pub densify: DensifyConfig,
    /// Iterations after which the held-out views are evaluated.
    pub test_iterations: Vec<u64>,
    /// Iterations after which the scene is written as a `.ply`.
    pub save_iterations: Vec<u64>,
    /// Iterations after which a resumable checkpoint is kept as `chkpnt_I.safetensors` (the
    /// 3DGS name).
    pub checkpoint_iterations: Vec<u64>,
    /// Iterations between the periodic checkpoints `checkpoint.safetensors` (replaced each time;
    /// 0: only when the run is stopped).
    pub checkpoint_interval: u64,
    /// Iterations between log lines (0: none); useful when the output is a log file.
    pub log_interval: u64,
}

impl Default for GeometryConfig {
    fn default() -> Self {
        GeometryConfig {
            iterations: 30_000,
            seed: 0,
            sh_degree: 3,
            sh_degree_interval: 1000,
            lambda_dssim: 0.2,
            background: [0.0; 3],
            random_init_points: 100_000,
            random_init_half_extent: 1.3,
            learning_rates: LearningRates::default(),
            adam: AdamConfig {
                eps: 1e-15,
                ..AdamConfig::default()
            },
            densify: DensifyConfig::default(),
            test_iterations: vec![7000, 30_000],
            save_iterations: vec![7000, 30_000],
            checkpoint_iterations: Vec::new(),
            checkpoint_interval: DEFAULT_CHECKPOINT_INTERVAL,
            log_interval: 0,
        }
    }
}

impl GeometryConfig {
    /// The same schedule stretched or compressed to `n` iterations (the rule is in the
    /// [module documentation](self#run-length)). `n == iterations` returns the configuration
    /// unchanged; so does a configuration of 0 iterations (no schedule to scale), except for
    /// `iterations` itself.
    pub fn scaled_to(&self, n: u64) -> GeometryConfig {
        let from = self.iterations;
        let mut c = self.clone();
        c.iterations = n;
        if from == 0 || from == n {
            return c;
        }
        let step = |x: u64| scale_point(x, from, n);
        let events = |list: &[u64]| {
            let mut out: Vec<u64> = list.iter().map(|&x| step(x)).collect();
            out.dedup();
            out
        };
        c.sh_degree_interval = scale_interval(self.sh_degree_interval, from, n, 1);
        let lr = &mut c.learning_rates;
        lr.position_lr_max_steps = step(self.learning_rates.position_lr_max_steps);
        lr.position_lr_delay_steps = step(self.learning_rates.position_lr_delay_steps);
        c.densify = self.densify.scaled(from, n);
        c.test_iterations = events(&self.test_iterations);
        c.save_iterations = events(&self.save_iterations);
        c.checkpoint_iterations = events(&self.checkpoint_iterations);
        c
    }

    fn validate(&self) -> Result<(), TrainError> {
        if self.sh_degree > 3 {
            return Err(TrainError::Config(format!(
                "sh_degree {} is above 3",
                self.sh_degree
            )));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return Err(TrainError::Config(format!(
                "lambda_dssim {} is outside [0, 1]",
                self.lambda_dssim
            )));
        }
        if self.densify.split_count == 0 {
            return Err(TrainError::Config("densify.split_count is 0".into()));
        }
        Ok(())
    }
}

/// A posed image: the camera and its RGB image (row-major, `height * width * 3`, in [0, 1]).
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// The image's name in the dataset.
    pub name: String,
    /// The camera the image was taken with.
    pub camera: Camera,
    /// RGB values, row-major `[height, width, 3]`, in [0, 1].
    pub image: Vec<f32>,
}

impl View {
    /// The image shape.
    pub fn shape(&self) -> ImageShape {
        let k = self.camera.intrinsics;
        ImageShape::new(k.width as usize, k.height as usize, 3)
    }

    /// Refuses an image whose length is not the camera's `width x height x 3` (or an empty
    /// camera), naming the view.
    pub(crate) fn check(&self) -> Result<(), TrainError> {
        let s = self.shape();
        if s.is_empty() || self.image.len() != s.len() {
            return Err(TrainError::Dataset(format!(
                "view `{}`: image has {} values, its {}x{} camera needs {}",
                self.name,
                self.image.len(),
                s.width,
                s.height,
                s.len()
            )));
        }
        Ok(())
    }
}

/// Loads the images at `indices` of a dataset as views.
pub fn load_views(dataset: &Dataset, indices: &[usize]) -> Result<Vec<View>, TrainError> {
    let images = dataset.load_images(indices)?;
    indices
        .iter()
        .zip(images)
        .map(|(&i, img)| {
            let v = View {
                name: dataset.names[i].clone(),
                camera: dataset.cameras[i],
                image: img.data,
            };
            v.check()?;
            Ok(v)
        })
        .collect()
}

/// The initial point cloud of a dataset: its points (COLMAP `points3D`) when present, otherwise
/// the 3DGS random cube.
pub fn initial_points(dataset: &Dataset, config: &GeometryConfig) -> PointCloud {
    match &dataset.points {
        Some(p) if !p.positions.is_empty() => PointCloud {
            positions: p.positions.clone(),
            colors: p.colors_f32(),
        },
        _ => {
            let h = config.random_init_half_extent;
            random_points_in_box(config.random_init_points, [-h; 3], [h; 3], config.seed)
        }
    }
}

/// What one iteration did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepReport {
    /// The iteration number (from 1).
    pub step: u64,
    /// The photometric loss terms of this iteration's render.
    pub loss: LossTerms,
    /// PSNR of the (unclamped) render against the training image.
    pub psnr: f64,
    /// Gaussians after the iteration.
    pub gaussians: usize,
    /// What density control did, when it ran at this iteration (the Adam step is then skipped).
    pub densified: Option<DensifyReport>,
    /// Whether the opacities were reset at this iteration (the opacity group then skips its Adam
    /// step).
    pub opacity_reset: bool,
}

/// Held-out image quality, averaged over views (per-view PSNR averaged, as 3DGS reports it).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Completed iterations when evaluated.
    pub step: u64,
    /// Number of views averaged.
    pub views: usize,
    /// Mean per-view PSNR in dB, of the render clamped to [0, 1].
    pub psnr: f64,
    /// Mean per-view SSIM.
    pub ssim: f64,
    /// Mean per-view mean absolute error.
    pub l1: f64,
    /// Gaussians in the scene when evaluated.
    pub gaussians: usize,
}

impl Evaluation {
    /// The evaluation as event metrics.
    pub fn metrics(&self) -> Vec<Metric> {
        [
            ("psnr", self.psnr),
            ("ssim", self.ssim),
            ("l1", self.l1),
            ("views", self.views as f64),
            ("gaussians", self.gaussians as f64),
        ]
        .map(|(name, value)| Metric { name, value })
        .to_vec()
    }
}

/// The result of [`GeometryTrainer::train`].
#[derive(Clone, Debug, PartialEq)]
pub struct TrainSummary {
    /// How the run ended (iterations, time, interruption, stop checkpoint).
    pub run: RunOutcome,
    /// The held-out evaluations made during this call, at the test iterations.
    pub evaluations: Vec<Evaluation>,
    /// Gaussians in the final scene.
    pub gaussians: usize,
}

/// A geometry training run.
pub struct GeometryTrainer {
    /// The run's settings.
    pub config: GeometryConfig,
    /// The scene with its Adam state and densification statistics.
    pub model: GaussianModel,
    /// Completed iterations.
    pub step: u64,
    /// The scene extent (3DGS `cameras_extent`, from the training cameras).
    pub extent: f64,
    /// The views trained on.
    pub train_views: Vec<View>,
    /// The held-out views, evaluated at the test iterations.
    pub test_views: Vec<View>,
    view_stack: Vec<usize>,
    ema_loss: f64,
    ema_psnr: f64,
}

impl GeometryTrainer {
    /// A run at step 0 from initial Gaussians (see [`crate::init`]). The extent is computed
    /// from the training cameras.
    pub fn new(
        config: GeometryConfig,
        initial: FeatureGaussians<f32>,
        train_views: Vec<View>,
        test_views: Vec<View>,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        if train_views.is_empty() {
            return Err(TrainError::Dataset("no training views".into()));
        }
        for v in train_views.iter().chain(&test_views) {
            v.check()?;
        }
        if initial.sh_degree != config.sh_degree {
            return Err(TrainError::Config(format!(
                "initial Gaussians store SH degree {}, the configuration asks for {}",
                initial.sh_degree, config.sh_degree
            )));
        }
        let cams: Vec<Camera> = train_views.iter().map(|v| v.camera).collect();
        let extent = gaussian::scene_extent_from_cameras(&cams);
        let model = GaussianModel::new(initial, &config.learning_rates, config.adam, extent)?;
        Ok(GeometryTrainer {
            config,
            model,
            step: 0,
            extent,
            train_views,
            test_views,
            view_stack: Vec::new(),
            ema_loss: 0.0,
            ema_psnr: 0.0,
        })
    }

    /// A run at step 0 on a dataset: the training views are all images, or those of the
    /// every-8th split when `eval_split` is set (the held-out ones become test views); the
    /// initial Gaussians come from [`initial_points`].
    pub fn from_dataset(
        config: GeometryConfig,
        dataset: &Dataset,
        eval_split: bool,
    ) -> Result<Self, TrainError> {
        let (train_idx, test_idx) = if eval_split {
            let s = dataset.split();
            (s.train, s.test)
        } else {
            ((0..dataset.len()).collect(), Vec::new())
        };
        let train = load_views(dataset, &train_idx)?;
        let test = load_views(dataset, &test_idx)?;
        let cloud = initial_points(dataset, &config);
        let initial = gaussians_from_points(&cloud, config.sh_degree)?;
        GeometryTrainer::new(config, initial, train, test)
    }

    /// Continues a run from a checkpoint with the same views (the configuration may differ,
    /// e.g. more iterations).
    pub fn resume(
        config: GeometryConfig,
        checkpoint: GeometryCheckpoint,
        train_views: Vec<View>,
        test_views: Vec<View>,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        if let Some(&bad) = checkpoint
            .view_stack
            .iter()
            .find(|&&i| i >= train_views.len())
        {
            return Err(TrainError::Config(format!(
                "the checkpoint refers to training view {bad}, but there are only {} views",
                train_views.len()
            )));
        }
        for v in train_views.iter().chain(&test_views) {
            v.check()?;
        }
        Ok(GeometryTrainer {
            config,
            model: checkpoint.model,
            step: checkpoint.step,
            extent: checkpoint.extent,
            train_views,
            test_views,
            view_stack: checkpoint.view_stack,
            ema_loss: checkpoint.ema_loss,
            ema_psnr: checkpoint.ema_psnr,
        })
    }

    /// The resumable state of the run.
    pub fn checkpoint(&self) -> Result<GeometryCheckpoint, TrainError> {
        Ok(self.checkpoint_parts(&self.config_json()?).to_owned())
    }

    /// Writes a checkpoint atomically: the file of [`GeometryTrainer::checkpoint`], written from
    /// the trainer's state without copying it first.
    pub fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        self.checkpoint_parts(&self.config_json()?).save(path)
    }

    /// What a checkpoint records, borrowed from the trainer (`config_json`: the configuration
    /// as [`GeometryTrainer::config_json`] writes it).
    fn checkpoint_parts<'a>(&'a self, config_json: &'a str) -> CheckpointParts<'a> {
        CheckpointParts {
            step: self.step,
            model: &self.model,
            view_stack: &self.view_stack,
            ema_loss: self.ema_loss,
            ema_psnr: self.ema_psnr,
            seed: self.config.seed,
            extent: self.extent,
            config_json,
        }
    }

    /// The configuration as a checkpoint records it.
    fn config_json(&self) -> Result<String, TrainError> {
        serde_json::to_string(&self.config).map_err(|e| TrainError::Config(e.to_string()))
    }

    /// Writes the scene as an official 3DGS `.ply` (atomically).
    pub fn save_ply(&self, path: &Path) -> Result<(), TrainError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| TrainError::io(dir, e))?;
        }
        gaussian::ply::save_ply(path, &self.model.scene)?;
        Ok(())
    }

    /// The generator for iteration `step`: a function of the seed and the iteration only.
    fn rng_for(&self, step: u64) -> StdRng {
        StdRng::seed_from_u64(splitmix64(self.config.seed ^ splitmix64(step)))
    }

    /// Runs one iteration.
    pub fn train_step(&mut self) -> Result<StepReport, TrainError> {
        let it = self.step + 1;
        let mut rng = self.rng_for(it);
        let sched = self.config.learning_rates.position_schedule(self.extent);
        self.model.set_position_lr(sched.at(it))?;
        if self.config.sh_degree_interval > 0 && it.is_multiple_of(self.config.sh_degree_interval) {
            self.model.one_up_sh_degree();
        }
        if self.view_stack.is_empty() {
            self.view_stack = (0..self.train_views.len()).collect();
        }
        let pick = rng.random_range(0..self.view_stack.len());
        let view_index = self.view_stack.remove(pick);
        let view = &self.train_views[view_index];
        let shape = view.shape();

        let fwd = render_color(
            &view.camera,
            &self.model.scene,
            self.model.active_sh_degree,
            self.config.background,
        )?;
        let image = &fwd.raster.image;
        let (loss, v_image) =
            photometric_loss_with_grad(image, &view.image, shape, self.config.lambda_dssim)?;
        let train_psnr = psnr(image, &view.image, shape)?;
        // The SH colour backward runs inside the SH groups' Adam pass (`step_from_colours`),
        // and not at all on the steps that skip Adam.
        let (grads, v_colours) = render_color_backward_before_sh(
            &view.camera,
            &self.model.scene,
            self.model.active_sh_degree,
            self.config.background,
            &fwd,
            &v_image,
        )?;

        let d = self.config.densify;
        let mut densified = None;
        let mut opacity_reset = false;
        if d.gathers_stats(it) {
            self.model
                .stats
                .accumulate(&fwd.projected.radii, &grads.ndc_grad_norms)?;
            if d.densifies_at(it) {
                let prune_large = d.prunes_large_at(it);
                densified =
                    Some(
                        self.model
                            .densify_and_prune(&d, self.extent, prune_large, &mut rng)?,
                    );
            }
            let white = self.config.background == [1.0; 3];
            if d.resets_opacity_at(it, white) {
                self.model.reset_opacity(d.opacity_reset_value)?;
                opacity_reset = true;
            }
        }
        if it < self.config.iterations && densified.is_none() {
            let g = ColourGrads {
                means: &grads.means,
                quats: &grads.quats,
                log_scales: &grads.log_scales,
                opacity_logits: &grads.opacity_logits,
                colours: &v_colours,
                sh_degree: self.model.active_sh_degree,
                camera_center: view.camera.center_as(),
            };
            let skip: &[&str] = if opacity_reset { &[OPACITY] } else { &[] };
            self.model.step_from_colours(&g, skip)?;
        }
        self.step = it;
        if it == 1 {
            self.ema_loss = loss.total;
            self.ema_psnr = train_psnr;
        } else {
            self.ema_loss = 0.4 * loss.total + 0.6 * self.ema_loss;
            self.ema_psnr = 0.4 * train_psnr + 0.6 * self.ema_psnr;
        }
        Ok(StepReport {
            step: it,
            loss,
            psnr: train_psnr,
            gaussians: self.model.len(),
            densified,
            opacity_reset,
        })
    }

    /// Renders every test view (clamped to [0, 1], as 3DGS evaluates) and averages PSNR, SSIM
    /// and L1 over them. `None` without test views.
    pub fn evaluate(&self) -> Result<Option<Evaluation>, TrainError> {
        self.evaluate_views(&self.test_views)
    }

    /// [`GeometryTrainer::evaluate`] on any views.
    pub fn evaluate_views(&self, views: &[View]) -> Result<Option<Evaluation>, TrainError> {
        if views.is_empty() {
            return Ok(None);
        }
        let (mut p, mut s, mut l) = (0.0, 0.0, 0.0);
        for v in views {
            let fwd = render_color(
                &v.camera,
                &self.model.scene,
                self.model.active_sh_degree,
                self.config.background,
            )?;
            let img: Vec<f32> = fwd.raster.image.iter().map(|x| x.clamp(0.0, 1.0)).collect();
            let shape = v.shape();
            p += psnr(&img, &v.image, shape)?;
            s += ssim(&img, &v.image, shape)?;
            l += crate::loss::l1_loss(&img, &v.image, shape)?;
        }
        let n = views.len() as f64;
        Ok(Some(Evaluation {
            step: self.step,
            views: views.len(),
            psnr: p / n,
            ssim: s / n,
            l1: l / n,
            gaussians: self.model.len(),
        }))
    }

    /// Trains up to `config.iterations` through the [driver](crate::driver). With an output
    /// folder, writes `.ply` scenes (`out_dir/point_cloud/iteration_I/point_cloud.ply`) at the
    /// save iterations, kept checkpoints (`out_dir/chkpnt_I.safetensors`) at the checkpoint
    /// iterations and the periodic and stop checkpoint `out_dir/checkpoint.safetensors`; held-out
    /// views are evaluated at the test iterations.
    pub fn train(&mut self, run: &Run) -> Result<TrainSummary, TrainError> {
        let cadence = Cadence {
            checkpoint_interval: self.config.checkpoint_interval,
            log_interval: self.config.log_interval,
        };
        let mut l = GeometryLoop {
            t: self,
            evaluations: Vec::new(),
            gaussians: 0,
        };
        let run = drive(&mut l, cadence, run)?;
        Ok(TrainSummary {
            run,
            evaluations: l.evaluations,
            gaussians: self.model.len(),
        })
    }

    /// The running averages of loss and training PSNR shown by the progress bar.
    pub fn running_averages(&self) -> (f64, f64) {
        (self.ema_loss, self.ema_psnr)
    }
}

/// A geometry run as the driver sees it, collecting this call's evaluations.
struct GeometryLoop<'t> {
    t: &'t mut GeometryTrainer,
    evaluations: Vec<Evaluation>,
    gaussians: usize,
}

impl TrainingLoop for GeometryLoop<'_> {
    const STAGE: Stage = Stage::Geometry;

    fn step(&self) -> u64 {
        self.t.step
    }

    fn iterations(&self) -> u64 {
        self.t.config.iterations
    }

    fn advance(&mut self) -> Result<(), TrainError> {
        self.gaussians = self.t.train_step()?.gaussians;
        Ok(())
    }

    fn status(&self) -> String {
        format!(
            "loss {:.5} psnr {:.2} N {}",
            self.t.ema_loss, self.t.ema_psnr, self.gaussians
        )
    }

    fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        self.t.save_checkpoint(path)
    }

    fn after_step(&mut self, out_dir: Option<&Path>, sink: &dyn Sink) -> Result<(), TrainError> {
        let it = self.t.step;
        if self.t.config.test_iterations.contains(&it) {
            if let Some(e) = self.t.evaluate()? {
                sink.emit(Event::Evaluation {
                    stage: Stage::Geometry,
                    step: it,
                    metrics: e.metrics(),
                });
                self.evaluations.push(e);
            }
        }
        let Some(dir) = out_dir else { return Ok(()) };
        if self.t.config.save_iterations.contains(&it) {
            let path = ply_path(dir, it);
            self.t.save_ply(&path)?;
            sink.emit(Event::OutputWritten {
                stage: Stage::Geometry,
                what: "scene",
                path,
            });
        }
        if self.t.config.checkpoint_iterations.contains(&it) {
            let path = checkpoint_path(dir, it);
            self.t.save_checkpoint(&path)?;
            sink.emit(Event::CheckpointWritten {
                stage: Stage::Geometry,
                step: it,
                path,
            });
        }
        Ok(())
    }
}

/// `out_dir/point_cloud/iteration_I/point_cloud.ply`, where 3DGS writes its scenes.
pub fn ply_path(out_dir: &Path, iteration: u64) -> PathBuf {
    out_dir
        .join("point_cloud")
        .join(format!("iteration_{iteration}"))
        .join("point_cloud.ply")
}

/// `out_dir/chkpnt_I.safetensors`.
pub fn checkpoint_path(out_dir: &Path, iteration: u64) -> PathBuf {
    out_dir.join(format!("chkpnt_{iteration}.safetensors"))
}

/// The SplitMix64 finaliser: a bijective mix of 64 bits.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
