//! `dsgs fit-geometry`: the geometry stage on a dataset, from posed images to a trained 3DGS
//! `.ply`, with held-out evaluation, checkpoints and resume.
//!
//! Configuration ([`FitGeometryConfig`], TOML): the keys of `train::GeometryConfig` at the top
//! level (so a plain geometry configuration is valid) plus a `[dataset]` table with the image
//! resolution and the evaluation split. The base configuration is `--config FILE` when given,
//! otherwise, when resuming, the `config.toml` of the output directory if there is one,
//! otherwise the defaults; command-line flags override it ([`GeometryOverrides`]), and the
//! effective configuration is written to `OUT/config.toml` before training starts.
//! `--iterations N` runs the base configuration's schedule stretched or compressed to `N`
//! iterations (the rule of `train::geometry`, [`GeometryConfig::scaled_to`]); without it the
//! step counts of the configuration are used as written.
//!
//! Outputs: `OUT/point_cloud/iteration_N/point_cloud.ply` at the save iterations and at the last
//! iteration run, `OUT/point_cloud.ply` (a copy of the last scene, not a link),
//! `OUT/chkpnt_N.safetensors` at the checkpoint iterations, and `OUT/checkpoint.safetensors`
//! every `checkpoint_interval` iterations and when a run is stopped early (the training-loop
//! driver's convention, `train::driver`).

use std::path::PathBuf;

use crate::cli::{at_least_one, list, positive, whole_in, with_default, CONFIG_HELP};
use crate::error::{bail, Context, Result};
use gaussian::dataset::{Dataset, LoadOptions, Resolution};
use serde::{Deserialize, Serialize};
use train::bake::STORED_SH_DEGREE;
use train::checkpoint::GeometryCheckpoint;
use train::geometry::{load_views, ply_path};
use train::{Evaluation, GeometryConfig, GeometryTrainer};
use train::{RunOutcome, Stage};

use crate::{config, Control};

/// How the dataset is read.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DatasetConfig {
    /// Resize the full-resolution images by `1 / downscale` on load (1: as stored).
    pub downscale: f64,
    /// Read the images from the `images_N` folder instead (COLMAP/LLFF layouts).
    pub images_folder: Option<u32>,
    /// Hold out every 8th image for evaluation.
    pub eval: bool,
}

impl Default for DatasetConfig {
    fn default() -> Self {
        DatasetConfig {
            downscale: 1.0,
            images_folder: None,
            eval: true,
        }
    }
}

/// The configuration of `dsgs fit-geometry`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FitGeometryConfig {
    /// How the dataset is read: the `[dataset]` table.
    pub dataset: DatasetConfig,
    /// The training configuration: the keys of `train::GeometryConfig`, at the top level.
    #[serde(flatten)]
    pub geometry: GeometryConfig,
}

impl FitGeometryConfig {
    /// The dataset load options.
    pub fn load_options(&self) -> Result<LoadOptions> {
        let d = &self.dataset;
        let resolution = match (d.images_folder, d.downscale) {
            (Some(n), 1.0) => {
                if n == 0 {
                    bail!("images_folder must be at least 1");
                }
                Resolution::Folder(n)
            }
            (Some(_), _) => bail!("give either a downscale factor or an images folder, not both"),
            (None, 1.0) => Resolution::Full,
            (None, f) if f > 0.0 && f.is_finite() => Resolution::Downscale(f),
            (None, f) => bail!("downscale {f} is not a positive factor"),
        };
        Ok(LoadOptions {
            resolution,
            background: self.geometry.background,
            ..LoadOptions::default()
        })
    }
}

/// Command-line values that override the configuration.
///
/// As [`clap::Args`], the flags from `--iterations` to `--sh-degree`; the two run intervals are
/// the program's to declare with its other run flags (`--checkpoint-every`, `--log-every`).
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct GeometryOverrides {
    /// Total iterations (`--iterations`; key `iterations`): the configuration's schedule
    /// stretched or compressed to this length (see [`apply`](Self::apply)).
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations (at least 1); the configuration's schedule (learning-rate decay, \
         densification window and interval, opacity resets, SH degree steps, test, save and \
         checkpoint iterations) is stretched or compressed to it, keeping density control at \
         least 50 and opacity resets at least 300 steps apart. With --resume it stretches the \
         stopped run's schedule (its OUT/config.toml) to the new length: the steps already \
         taken stay, the rest follow the new schedule",
        FitGeometryConfig::default().geometry.iterations,
    ))]
    pub iterations: Option<u64>,
    /// Resize the images by `1 / F` on load (`--downscale`; key `dataset.downscale`); clears
    /// `dataset.images_folder`.
    #[arg(long, conflicts_with = "resolution", value_parser = positive, help = with_default(
        "Resize the images by 1/F on load (above 0)",
        FitGeometryConfig::default().dataset.downscale,
    ))]
    pub downscale: Option<f64>,
    /// Read the images from the `images_N` folder (`--resolution`; key
    /// `dataset.images_folder`); resets `dataset.downscale` to 1.
    #[arg(
        id = "resolution",
        long = "resolution",
        value_name = "RESOLUTION",
        value_parser = at_least_one::<u32>(),
        help = "Read the images from the images_N folder (at least 1) [default: none: the images \
                folder]"
    )]
    pub images_folder: Option<u32>,
    /// White background, for NeRF-synthetic scenes (`--white`; key `background`). `false`
    /// leaves the configuration's background.
    #[arg(long, help = "White background (NeRF-synthetic scenes)")]
    pub white: bool,
    /// Iterations at which to evaluate the held-out views and save the scene
    /// (`--test-iterations`; key `test_iterations`, and `save_iterations` unless given).
    #[arg(long, value_delimiter = ',', help = with_default(
        "Iterations at which to evaluate the held-out views and save the scene (comma-separated; \
         used as given)",
        format!(
            "{}, scaled with --iterations",
            list(&FitGeometryConfig::default().geometry.test_iterations)
        ),
    ))]
    pub test_iterations: Option<Vec<u64>>,
    /// Iterations at which to save the scene, when they differ from the test iterations
    /// (`--save-iterations`; key `save_iterations`).
    #[arg(
        long,
        value_delimiter = ',',
        help = "Iterations at which to save the scene, when they differ from the test \
                iterations (comma-separated) [default: the test iterations]"
    )]
    pub save_iterations: Option<Vec<u64>>,
    /// Iterations at which to write a resumable `chkpnt_N.safetensors`
    /// (`--checkpoint-iterations`; key `checkpoint_iterations`).
    #[arg(long, value_delimiter = ',', help = with_default(
        "Iterations at which to write a resumable checkpoint (comma-separated)",
        list(&FitGeometryConfig::default().geometry.checkpoint_iterations),
    ))]
    pub checkpoint_iterations: Option<Vec<u64>>,
    /// Train on every image, no held-out split (`--no-eval`; key `dataset.eval = false`).
    #[arg(long, help = "Train on every image (no held-out split)")]
    pub no_eval: bool,
    /// Seed of every random choice (`--seed`; key `seed`).
    #[arg(long, help = with_default(
        "Seed of every random choice",
        FitGeometryConfig::default().geometry.seed,
    ))]
    pub seed: Option<u64>,
    /// Maximum SH degree, 0..=3 (`--sh-degree`; key `sh_degree`).
    #[arg(long, value_parser = whole_in(0, STORED_SH_DEGREE), help = with_default(
        "Maximum SH degree (0 to 3)",
        FitGeometryConfig::default().geometry.sh_degree,
    ))]
    pub sh_degree: Option<usize>,
    /// Iterations between log lines (`--log-every`; key `log_interval`).
    #[arg(skip)]
    pub log_every: Option<u64>,
    /// Iterations between writes of `OUT/checkpoint.safetensors`, 0 for only when stopped
    /// (`--checkpoint-every`; key `checkpoint_interval`).
    #[arg(skip)]
    pub checkpoint_every: Option<u64>,
}

impl GeometryOverrides {
    /// Applies the overrides. A new iteration count `n` scales every step count of the
    /// configuration's schedule from its `iterations` to `n` ([`GeometryConfig::scaled_to`]:
    /// learning-rate decay, densification window and intervals, opacity resets, SH degree
    /// steps, test, save and checkpoint iterations), then drops the test, save and checkpoint
    /// iterations beyond `n` and adds `n` to the test and save iterations. Explicit
    /// `test_iterations` also become the save iterations unless `save_iterations` are given
    /// (as the 3DGS trainer does). Without an iteration count, the configuration's step counts
    /// are kept as written.
    pub fn apply(&self, c: &mut FitGeometryConfig) {
        let g = &mut c.geometry;
        if let Some(n) = self.iterations {
            *g = g.scaled_to(n);
            g.test_iterations.retain(|&t| t <= n);
            g.save_iterations.retain(|&t| t <= n);
            g.checkpoint_iterations.retain(|&t| t <= n);
            for list in [&mut g.test_iterations, &mut g.save_iterations] {
                if !list.contains(&n) {
                    list.push(n);
                }
            }
        }
        if let Some(t) = &self.test_iterations {
            g.test_iterations = t.clone();
            g.save_iterations = t.clone();
        }
        if let Some(s) = &self.save_iterations {
            g.save_iterations = s.clone();
        }
        if let Some(ck) = &self.checkpoint_iterations {
            g.checkpoint_iterations = ck.clone();
        }
        if let Some(s) = self.seed {
            g.seed = s;
        }
        if let Some(d) = self.sh_degree {
            g.sh_degree = d;
        }
        if let Some(l) = self.log_every {
            g.log_interval = l;
        }
        if self.white {
            g.background = [1.0; 3];
        }
        if let Some(k) = self.checkpoint_every {
            g.checkpoint_interval = k;
        }
        if let Some(f) = self.downscale {
            c.dataset.downscale = f;
            c.dataset.images_folder = None;
        }
        if let Some(n) = self.images_folder {
            c.dataset.images_folder = Some(n);
            c.dataset.downscale = 1.0;
        }
        if self.no_eval {
            c.dataset.eval = false;
        }
    }
}

/// What to run; as [`clap::Args`], the arguments of `dsgs fit-geometry` up to `--sh-degree`
/// (`--resume` is the program's to declare with its other run flags).
#[derive(Clone, Debug, clap::Args)]
pub struct FitSettings {
    /// Dataset directory in COLMAP, NeRF-synthetic or LLFF layout (the `DATASET` argument).
    #[arg(help = "Dataset directory (COLMAP, NeRF-synthetic or LLFF layout)")]
    pub dataset: PathBuf,
    /// Output directory (`--output`).
    #[arg(
        short,
        long = "output",
        value_name = "OUTPUT",
        help = "Output directory"
    )]
    pub out_dir: PathBuf,
    /// Base configuration file (`--config`): [`FitGeometryConfig`] keys.
    #[arg(long, help = CONFIG_HELP)]
    pub config: Option<PathBuf>,
    /// Continue from this checkpoint of a stopped run (`--resume`).
    #[arg(skip)]
    pub resume: Option<PathBuf>,
    /// Command-line values applied on top of the configuration.
    #[command(flatten)]
    pub overrides: GeometryOverrides,
}

/// What a run did.
#[derive(Clone, Debug)]
pub struct FitReport {
    /// The effective configuration, as saved to `OUT/config.toml`.
    pub config: FitGeometryConfig,
    /// Training views.
    pub train_views: usize,
    /// Held-out views.
    pub test_views: usize,
    /// Image width of the first training view, in pixels.
    pub width: u32,
    /// Image height of the first training view, in pixels.
    pub height: u32,
    /// Gaussians when the run started (the initial point cloud, or the resumed checkpoint's).
    pub initial_gaussians: usize,
    /// How the run ended (iterations, time, interruption, the stop checkpoint).
    pub run: RunOutcome,
    /// Gaussians at the end of the run.
    pub gaussians: usize,
    /// The held-out evaluations at the test iterations reached by this run.
    pub evaluations: Vec<Evaluation>,
    /// `OUT/point_cloud.ply`.
    pub ply: PathBuf,
}

/// The summary of a run, a line each: the views, every evaluation and the scene written
/// (how the run ended is [`FitReport::run`]'s to tell).
impl std::fmt::Display for FitReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} training and {} test views at {}x{}, {} initial Gaussians",
            self.train_views, self.test_views, self.width, self.height, self.initial_gaussians
        )?;
        for e in &self.evaluations {
            writeln!(
                f,
                "iteration {}: held-out PSNR {:.3} dB, SSIM {:.4}, L1 {:.5}, {} Gaussians",
                e.step, e.psnr, e.ssim, e.l1, e.gaussians
            )?;
        }
        writeln!(
            f,
            "{} Gaussians; scene written to {}",
            self.gaussians,
            self.ply.display()
        )
    }
}

/// The effective configuration of a run (base configuration plus overrides).
pub fn effective_config(settings: &FitSettings) -> Result<FitGeometryConfig> {
    config::effective(
        settings.config.as_deref(),
        settings.resume.is_some(),
        &settings.out_dir,
        |c| settings.overrides.apply(c),
    )
}

/// Runs the geometry stage, reporting to the control's sink. A stop request ends the run after
/// the current iteration with a checkpoint of it ([`RunOutcome::stop_checkpoint`]); the scene
/// so far is written as for a finished run.
pub fn run(settings: &FitSettings, control: &Control) -> Result<FitReport> {
    let cfg = effective_config(settings)?;
    let options = cfg.load_options()?;
    let dataset = Dataset::load(&settings.dataset, &options)
        .with_context(|| format!("loading the dataset {}", settings.dataset.display()))?;
    control.report_dataset(&dataset);
    config::save(&cfg, &settings.out_dir)?;
    let eval = cfg.dataset.eval;
    let mut trainer = match &settings.resume {
        None => GeometryTrainer::from_dataset(cfg.geometry.clone(), &dataset, eval)?,
        Some(p) => {
            let (train_idx, test_idx) = if eval {
                let s = dataset.split();
                (s.train, s.test)
            } else {
                ((0..dataset.len()).collect(), Vec::new())
            };
            let ck = GeometryCheckpoint::load(p)
                .with_context(|| format!("reading the checkpoint {}", p.display()))?;
            GeometryTrainer::resume(
                cfg.geometry.clone(),
                ck,
                load_views(&dataset, &train_idx)?,
                load_views(&dataset, &test_idx)?,
            )
            .with_context(|| format!("resuming from {}", p.display()))?
        }
    };
    let k = trainer.train_views[0].camera.intrinsics;
    let first_step = trainer.step;
    let initial_gaussians = trainer.model.len();
    control.log(
        Stage::Geometry,
        format!(
            "{} training and {} held-out views at {}x{}; {} Gaussians at iteration {} of {}",
            trainer.train_views.len(),
            trainer.test_views.len(),
            k.width,
            k.height,
            initial_gaussians,
            first_step,
            cfg.geometry.iterations
        ),
    );
    let summary = trainer.train(&control.run_in(&settings.out_dir))?;
    trainer.save_ply(&ply_path(&settings.out_dir, trainer.step))?;
    let ply = settings.out_dir.join("point_cloud.ply");
    trainer.save_ply(&ply)?;
    Ok(FitReport {
        train_views: trainer.train_views.len(),
        test_views: trainer.test_views.len(),
        width: k.width,
        height: k.height,
        initial_gaussians,
        run: summary.run,
        gaussians: summary.gaussians,
        evaluations: summary.evaluations,
        ply,
        config: cfg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn plain_geometry_configs_are_valid_and_round_trip() {
        let c: FitGeometryConfig =
            config::parse("iterations = 500\n[densify]\n", Path::new("g.toml")).unwrap();
        assert_eq!(c.geometry.iterations, 500);
        assert_eq!(c.dataset, DatasetConfig::default());
        let text = config::to_toml(&c).unwrap();
        let back: FitGeometryConfig = config::parse(&text, Path::new("back.toml")).unwrap();
        assert_eq!(back, c);
        let e =
            config::parse::<FitGeometryConfig>("[dataset]\ndownscal = 2.0\n", Path::new("g.toml"))
                .unwrap_err()
                .to_string();
        assert!(e.contains("dataset.downscal"), "{e}");
    }

    #[test]
    fn overrides_adjust_schedules() {
        let mut c = FitGeometryConfig::default();
        GeometryOverrides {
            iterations: Some(5000),
            seed: Some(3),
            white: true,
            downscale: Some(2.0),
            ..Default::default()
        }
        .apply(&mut c);
        let g = &c.geometry;
        assert_eq!(g.iterations, 5000);
        // The schedule is the default one scaled to the run: the position rate decays over
        // the run, densification stops within it, every event falls in it, and the run's end
        // is evaluated and saved.
        assert_eq!(g.learning_rates.position_lr_max_steps, 5000);
        assert!(g.densify.densify_until_iter < 5000);
        assert!(g.sh_degree_interval < GeometryConfig::default().sh_degree_interval);
        for list in [&g.test_iterations, &g.save_iterations] {
            assert!(list.iter().all(|&t| (1..=5000).contains(&t)), "{list:?}");
            assert!(list.contains(&5000), "{list:?}");
        }
        assert_eq!(c.geometry.seed, 3);
        assert_eq!(c.geometry.background, [1.0; 3]);
        assert_eq!(
            c.load_options().unwrap().resolution,
            Resolution::Downscale(2.0)
        );
        GeometryOverrides {
            images_folder: Some(8),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!(c.load_options().unwrap().resolution, Resolution::Folder(8));
        c.dataset.downscale = -1.0;
        c.dataset.images_folder = None;
        assert!(c.load_options().is_err());
    }

    #[test]
    fn iterations_scale_the_configured_schedule_and_its_absence_keeps_it() {
        let text = "iterations = 2000\nsh_degree_interval = 100\n\
                    [densify]\ndensify_from_iter = 200\ndensify_until_iter = 1000\n";
        let written: FitGeometryConfig = config::parse(text, Path::new("g.toml")).unwrap();
        // Other flags leave the written step counts alone.
        let mut kept = written.clone();
        GeometryOverrides {
            seed: Some(1),
            white: true,
            ..Default::default()
        }
        .apply(&mut kept);
        assert_eq!(kept.geometry.densify, written.geometry.densify);
        assert_eq!(
            kept.geometry.sh_degree_interval,
            written.geometry.sh_degree_interval
        );
        // --iterations compresses the written schedule, not the default one.
        let mut half = written.clone();
        GeometryOverrides {
            iterations: Some(1000),
            ..Default::default()
        }
        .apply(&mut half);
        // Half the run: the file's densification window at half its steps.
        let (d, w) = (&half.geometry.densify, &written.geometry.densify);
        assert_eq!(2 * d.densify_from_iter, w.densify_from_iter);
        assert_eq!(2 * d.densify_until_iter, w.densify_until_iter);
        assert_eq!(
            2 * half.geometry.learning_rates.position_lr_max_steps,
            written.geometry.learning_rates.position_lr_max_steps
        );
    }
}
