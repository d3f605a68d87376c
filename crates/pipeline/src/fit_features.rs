//! `dsgs fit-features`: feature training on frozen geometry (the third stage), from a trained
//! 3DGS `.ply`, its dataset, style images and the frozen encoder and decoder to a scene bundle
//! (`train::features`).
//!
//! Configuration ([`FitFeaturesConfig`], TOML): the keys of `train::FeatureTrainConfig` at the
//! top level, the RGB `background` the geometry was trained on (recorded in the bundle and used
//! to composite RGBA images) and the `[dataset]` table of `dsgs fit-geometry` (resolution and
//! held-out split; held-out views are recorded in the bundle but never trained on). The base is
//! `--config FILE` when given, otherwise, when resuming, the `config.toml` of the output
//! directory if there is one, otherwise the defaults; flags override it ([`FeatureOverrides`])
//! and the effective configuration is written to `OUT/config.toml` before training starts.
//!
//! Setup: the dataset's training views and every style image are decoded, then the views and
//! styles are encoded, reported as `Stage::Prepare` progress; a bad image stops the run before
//! anything is written. The encodings are cached in `OUT/encodings/` (`train::features`,
//! "Encoding cache"), so a resumed or repeated run with the same inputs skips the encoding and
//! trains exactly as without the cache.
//!
//! Evaluation: with a held-out split, `eval_pairs` fixed samples of held-out views and paintings
//! (`--eval-style`, or the training styles) are evaluated before training, every
//! `eval_interval` iterations and at the end (`train::features`, "Evaluation"), reported as
//! evaluation events; without one, training views and styles.
//!
//! Outputs: the scene bundle `OUT/bundle/` (loadable by `dsgs stylize`) and
//! `OUT/checkpoint.safetensors`, written at the checkpoint interval and again at the end.

use std::path::PathBuf;

use crate::cli::{at_least_one, positive, with_default};
use crate::error::{Context, Error, Result};
use gaussian::dataset::{Dataset, LoadOptions};
use gaussian::ply::load_ply;
use serde::{Deserialize, Serialize};
use train::features::{dataset_views, FeatureSetup, ENCODINGS_DIR, FEATURE_CHECKPOINT_FILE};
use train::geometry::{load_views, View};
use train::{
    DecoderMode, FeatureEvaluation, FeatureInputs, FeatureNorm, FeatureTrainConfig, FeatureTrainer,
    GeometryConfig, Variant,
};

use crate::fit_geometry::{DatasetConfig, FitGeometryConfig};
use crate::pretrain_decoder::{open_images, NetworkFiles};
use crate::{config, Control};
use train::RunOutcome;

/// The configuration of `dsgs fit-features`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FitFeaturesConfig {
    /// The RGB background of the geometry (RGBA images are composited onto it).
    pub background: [f32; 3],
    /// How the dataset is read: the `[dataset]` table, as in `dsgs fit-geometry`.
    pub dataset: DatasetConfig,
    /// The training configuration: the keys of `train::FeatureTrainConfig`, at the top level.
    #[serde(flatten)]
    pub features: FeatureTrainConfig,
}

impl FitFeaturesConfig {
    /// The dataset load options (the same rules as `dsgs fit-geometry`).
    pub fn load_options(&self) -> Result<LoadOptions> {
        FitGeometryConfig {
            dataset: self.dataset.clone(),
            geometry: GeometryConfig {
                background: self.background,
                ..GeometryConfig::default()
            },
        }
        .load_options()
    }
}

/// Command-line values that override the configuration.
///
/// As [`clap::Args`], the flags from `--iterations` to `--no-eval`; the design flags shown
/// before the configuration file (`--eval-every`, `--variant`, `--decoder-mode`,
/// `--lr-decoder`, `--normalize`) and the two run intervals (`--checkpoint-every`,
/// `--log-every`) are the program's to declare.
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct FeatureOverrides {
    /// Total iterations (`--iterations`; key `iterations`).
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations, the warm-up included (at least 1)",
        FitFeaturesConfig::default().features.iterations,
    ))]
    pub iterations: Option<u64>,
    /// Channels of each Gaussian's feature (`--feature-dim`; key `feature_dim`).
    #[arg(long, value_parser = at_least_one::<usize>(), help = with_default(
        "Channels of each Gaussian's feature (at least 1)",
        FitFeaturesConfig::default().features.feature_dim,
    ))]
    pub feature_dim: Option<usize>,
    /// Resize the images by `1 / F` on load (`--downscale`; key `dataset.downscale`); clears
    /// `dataset.images_folder`.
    #[arg(long, value_parser = positive, help = with_default(
        "Resize the images by 1/F on load (above 0)",
        FitFeaturesConfig::default().dataset.downscale,
    ))]
    pub downscale: Option<f64>,
    /// Alignment loss only (`--align-only`: keys `lambda_content` and `lambda_style` set to 0).
    #[arg(
        long,
        help = "Train with the alignment loss only (no content and style terms)"
    )]
    pub align_only: bool,
    /// Iterations of alignment-only warm-up (`--align-warmup`; key `align_warmup`).
    #[arg(long, help = with_default(
        "Iterations at the start with the alignment loss only (cheap; gives the features the \
         scene's content before the content and style terms join)",
        FitFeaturesConfig::default().features.align_warmup,
    ))]
    pub align_warmup: Option<u64>,
    /// Seed of every random choice (`--seed`; key `seed`).
    #[arg(long, help = with_default(
        "Seed of every random choice",
        FitFeaturesConfig::default().features.seed,
    ))]
    pub seed: Option<u64>,
    /// Side of the feature-map window run through the networks, in feature pixels (`--crop`;
    /// key `crop`).
    #[arg(long, value_parser = at_least_one::<u32>(), help = feature_crop_help())]
    pub crop: Option<u32>,
    /// Side of the block of rendered pixels averaged into each feature pixel (`--supersample`;
    /// key `supersample`).
    #[arg(long, value_parser = at_least_one::<u32>(), help = with_default(
        "Render the feature map N times finer and average each NxN block into one feature \
         pixel (1: one sample per feature pixel); the bundle keeps it for stylization (1 to 16)",
        FitFeaturesConfig::default().features.supersample,
    ))]
    pub supersample: Option<u32>,
    /// White background, for NeRF-synthetic scenes (`--white`; key `background`). `false`
    /// leaves the configuration's background.
    #[arg(long, help = "White background (NeRF-synthetic scenes)")]
    pub white: bool,
    /// Train on every image, no held-out split (`--no-eval`; key `dataset.eval = false`).
    #[arg(long, help = "Train on every image (no held-out split)")]
    pub no_eval: bool,
    /// Network variant (`--variant`; key `variant`).
    #[arg(skip)]
    pub variant: Option<Variant>,
    /// The decoder ablation (`--decoder-mode`; key `decoder_mode`).
    #[arg(skip)]
    pub decoder_mode: Option<DecoderMode>,
    /// Adam learning rate of a decoder trained in stage 3 (`--lr-decoder`; key `lr_decoder`).
    #[arg(skip)]
    pub lr_decoder: Option<f64>,
    /// The normalisation design (`--normalize`; key `normalize`).
    #[arg(skip)]
    pub normalize: Option<FeatureNorm>,
    /// Iterations between log lines (`--log-every`; key `log_interval`).
    #[arg(skip)]
    pub log_every: Option<u64>,
    /// Iterations between checkpoints, 0 for only when stopped (`--checkpoint-every`; key
    /// `checkpoint_interval`).
    #[arg(skip)]
    pub checkpoint_every: Option<u64>,
    /// Iterations between evaluations (`--eval-every`; key `eval_interval`).
    #[arg(skip)]
    pub eval_every: Option<u64>,
}

impl FeatureOverrides {
    /// Applies the overrides.
    pub fn apply(&self, c: &mut FitFeaturesConfig) {
        let f = &mut c.features;
        if let Some(v) = self.iterations {
            f.iterations = v;
        }
        if let Some(v) = self.feature_dim {
            f.feature_dim = v;
        }
        if self.align_only {
            f.lambda_content = 0.0;
            f.lambda_style = 0.0;
        }
        if let Some(v) = self.align_warmup {
            f.align_warmup = v;
        }
        if let Some(v) = self.seed {
            f.seed = v;
        }
        if let Some(v) = self.crop {
            f.crop = Some(v);
        }
        if let Some(v) = self.supersample {
            f.supersample = v;
        }
        if let Some(v) = self.variant {
            f.variant = v;
        }
        if let Some(v) = self.decoder_mode {
            f.decoder_mode = v;
        }
        if let Some(v) = self.lr_decoder {
            f.lr_decoder = v;
        }
        if let Some(v) = self.normalize {
            f.normalize = v;
        }
        if let Some(v) = self.log_every {
            f.log_interval = v;
        }
        if let Some(k) = self.checkpoint_every {
            f.checkpoint_interval = k;
        }
        if let Some(k) = self.eval_every {
            f.eval_interval = k;
        }
        if let Some(v) = self.downscale {
            c.dataset.downscale = v;
            c.dataset.images_folder = None;
        }
        if self.white {
            c.background = [1.0; 3];
        }
        if self.no_eval {
            c.dataset.eval = false;
        }
    }
}

/// The dataset argument of `dsgs fit-features`: the first positional argument, as in
/// `fit-geometry`, or `--dataset` as before it became one (kept for a release, hidden from
/// `--help`).
#[derive(Clone, Debug, clap::Args)]
pub struct DatasetArg {
    /// The dataset the geometry was trained on (COLMAP, NeRF-synthetic or LLFF layout).
    #[arg(required_unless_present = "dataset_flag")]
    dataset: Option<PathBuf>,
    #[arg(long = "dataset", hide = true, conflicts_with = "dataset")]
    dataset_flag: Option<PathBuf>,
}

impl DatasetArg {
    /// The dataset's path, however it was given.
    pub fn path(&self) -> Result<PathBuf> {
        match self.dataset.as_ref().or(self.dataset_flag.as_ref()) {
            Some(p) => Ok(p.clone()),
            None => crate::error::bail!("give the dataset: dsgs fit-features DATASET ..."),
        }
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct FitFeaturesSettings {
    /// The trained geometry (`.ply`).
    pub geometry: PathBuf,
    /// Its dataset directory.
    pub dataset: PathBuf,
    /// Style image folders and/or files.
    pub styles: Vec<PathBuf>,
    /// Paintings never trained on, for the evaluation (`--eval-style`); empty: the training
    /// styles.
    pub eval_styles: Vec<PathBuf>,
    /// The frozen encoder and decoder: `--weights`, and `--decoder` to replace its decoder.
    pub networks: NetworkFiles,
    /// Output directory (`--output`); the bundle goes to `OUT/bundle`.
    pub out_dir: PathBuf,
    /// Base configuration file (`--config`): [`FitFeaturesConfig`] keys.
    pub config: Option<PathBuf>,
    /// Continue from this checkpoint of a stopped run (`--resume`).
    pub resume: Option<PathBuf>,
    /// Command-line values applied on top of the configuration.
    pub overrides: FeatureOverrides,
    /// Keep the view and style encodings in `OUT/encodings/` for a resumed or repeated run
    /// (`true` unless `--no-encoding-cache`); they take about as much disk as memory.
    pub encoding_cache: bool,
}

/// What a run did.
#[derive(Clone, Debug)]
pub struct FitFeaturesReport {
    /// The effective configuration, as saved to `OUT/config.toml`.
    pub config: FitFeaturesConfig,
    /// Gaussians of the geometry.
    pub gaussians: usize,
    /// Training views of the dataset.
    pub train_views: usize,
    /// Style images trained on.
    pub style_images: usize,
    /// How the run ended; its output is `OUT/bundle` when it completed.
    pub run: RunOutcome,
    /// Running averages of the total, align, content and style losses at the end.
    pub running_losses: Option<[f64; 4]>,
    /// The evaluations of this run, in order (see [`FitFeaturesReport::held_out`]).
    pub evaluations: Vec<FeatureEvaluation>,
    /// Whether the evaluations are on held-out views (the dataset's held-out split, with
    /// `--eval-style` paintings when given); otherwise on training views and styles.
    pub held_out: bool,
    /// `OUT/checkpoint.safetensors`.
    pub checkpoint: PathBuf,
}

/// The summary of a run, a line each: the inputs, the running losses and every evaluation
/// (how the run ended is [`FitFeaturesReport::run`]'s to tell).
impl std::fmt::Display for FitFeaturesReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} Gaussians, {} training views, {} style images, {}-d features, {} networks",
            self.gaussians,
            self.train_views,
            self.style_images,
            self.config.features.feature_dim,
            self.config.features.variant.as_str()
        )?;
        if let Some([total, align, content, style]) = self.running_losses {
            writeln!(
                f,
                "running loss {total:.5} (align {align:.5}, content {content:.5}, style \
                 {style:.5})"
            )?;
        }
        let samples = if self.held_out {
            "held-out"
        } else {
            "training"
        };
        for e in &self.evaluations {
            writeln!(
                f,
                "iteration {}: evaluation loss {:.5} (align {:.5}, content {:.5}, style {:.5}, {} \
                 {samples} samples)",
                e.step, e.loss, e.loss_align, e.loss_content, e.loss_style, e.pairs
            )?;
        }
        Ok(())
    }
}

/// The effective configuration of a run (base configuration plus overrides).
pub fn effective_config(settings: &FitFeaturesSettings) -> Result<FitFeaturesConfig> {
    config::effective(
        settings.config.as_deref(),
        settings.resume.is_some(),
        &settings.out_dir,
        |c| settings.overrides.apply(c),
    )
}

/// Reads every input of a run, and the held-out views of the evaluation (none without a
/// held-out split or evaluation).
fn inputs(
    settings: &FitFeaturesSettings,
    cfg: &FitFeaturesConfig,
    control: &Control,
) -> Result<(FeatureInputs, Vec<View>)> {
    let geometry = load_ply(&settings.geometry)
        .with_context(|| format!("reading the geometry {}", settings.geometry.display()))?;
    let styles = open_images(&settings.styles, false, "style")?;
    let encoder = settings.networks.load_encoder()?;
    let decoder = settings.networks.load_decoder()?;
    let options = cfg.load_options()?;
    let dataset = Dataset::load(&settings.dataset, &options)
        .with_context(|| format!("loading the dataset {}", settings.dataset.display()))?;
    control.report_dataset(&dataset);
    let (views, cameras) = dataset_views(&dataset, cfg.dataset.eval, control.sink)
        .with_context(|| format!("reading the views of {}", settings.dataset.display()))?;
    let held_out = if cfg.features.eval_pairs > 0 && cfg.dataset.eval {
        load_views(&dataset, &dataset.split().test).with_context(|| {
            format!(
                "reading the held-out views of {}",
                settings.dataset.display()
            )
        })?
    } else {
        Vec::new()
    };
    let n = &settings.networks;
    let mut provenance = vec![
        (
            "geometry".to_string(),
            settings.geometry.display().to_string(),
        ),
        (
            "dataset".to_string(),
            settings.dataset.display().to_string(),
        ),
    ];
    for (key, path) in [
        ("weights", &n.weights),
        ("encoder", &n.encoder),
        ("decoder", &n.decoder),
    ] {
        if let Some(p) = path {
            provenance.push((key.to_string(), p.display().to_string()));
        }
    }
    Ok((
        FeatureInputs {
            geometry,
            views,
            cameras,
            styles,
            encoder,
            decoder,
            background: cfg.background,
            provenance,
        },
        held_out,
    ))
}

/// Trains the features, reporting to the control's sink. A stop request ends the run after the
/// current iteration with a checkpoint of it ([`RunOutcome::stop_checkpoint`]).
pub fn run(settings: &FitFeaturesSettings, control: &Control) -> Result<FitFeaturesReport> {
    let cfg = effective_config(settings)?;
    let (inputs, held_out) = inputs(settings, &cfg, control)?;
    let (gaussians, train_views) = (inputs.geometry.len(), inputs.views.len());
    if held_out.is_empty() && !settings.eval_styles.is_empty() {
        return Err(Error::Message(format!(
            "the evaluation paintings ({}) are for held-out views, and this run has none \
             (the dataset's held-out split is off, or eval_pairs is 0)",
            settings
                .eval_styles
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    // Evaluation paintings of their own, or (None) the training paintings.
    let eval_styles = if held_out.is_empty() || settings.eval_styles.is_empty() {
        None
    } else {
        Some(open_images(
            &settings.eval_styles,
            false,
            "evaluation style",
        )?)
    };
    let cache = settings.out_dir.join(ENCODINGS_DIR);
    let setup = FeatureSetup {
        sink: control.sink,
        cache: settings.encoding_cache.then_some(cache.as_path()),
    };
    let mut trainer = match &settings.resume {
        Some(ck) => FeatureTrainer::resume_with(ck, cfg.features.clone(), inputs, &setup)
            .with_context(|| format!("resuming from {}", ck.display()))?,
        None => FeatureTrainer::new_with(cfg.features.clone(), inputs, &setup)
            .context("setting up feature training")?,
    };
    if !held_out.is_empty() {
        trainer = match &eval_styles {
            Some(styles) => trainer.with_held_out(&held_out, styles, control.sink),
            None => trainer.with_held_out_views(&held_out, control.sink),
        }
        .context("encoding the held-out views and styles of the evaluation")?;
    }
    config::save(&cfg, &settings.out_dir)?;
    let summary = trainer.train(&control.run_in(&settings.out_dir))?;
    let checkpoint = settings.out_dir.join(FEATURE_CHECKPOINT_FILE);
    if !summary.run.interrupted {
        trainer
            .save_checkpoint(&checkpoint)
            .with_context(|| format!("writing {}", checkpoint.display()))?;
    }
    Ok(FitFeaturesReport {
        config: cfg,
        gaussians,
        train_views,
        style_images: trainer.counts().1,
        run: summary.run,
        running_losses: summary.running_losses,
        evaluations: summary.evaluations,
        held_out: !held_out.is_empty(),
        checkpoint,
    })
}

/// The help of `fit-features --crop`, with the default of each variant.
fn feature_crop_help() -> String {
    let side = |variant| {
        FeatureTrainConfig {
            variant,
            ..FitFeaturesConfig::default().features
        }
        .crop_side()
    };
    format!(
        "Side of the feature-map window run through the networks, in feature pixels (at least 1) \
         [default: {} for standard, {} for fullres networks]",
        side(Variant::Standard),
        side(Variant::Fullres)
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn feature_configs_round_trip_and_overrides_apply() {
        let c: FitFeaturesConfig = config::parse(
            "iterations = 50\nbackground = [1.0, 1.0, 1.0]\n[dataset]\neval = false\n",
            Path::new("f.toml"),
        )
        .unwrap();
        assert_eq!(c.features.iterations, 50);
        assert_eq!(c.background, [1.0; 3]);
        assert!(!c.dataset.eval);
        let back: FitFeaturesConfig =
            config::parse(&config::to_toml(&c).unwrap(), Path::new("b.toml")).unwrap();
        assert_eq!(back, c);
        let mut c = c;
        FeatureOverrides {
            align_only: true,
            crop: Some(16),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!(
            (c.features.lambda_content, c.features.lambda_style),
            (0.0, 0.0)
        );
        assert_eq!(c.features.crop_side(), 16);
        let e = config::parse::<FitFeaturesConfig>("lambda_styel = 1.0", Path::new("f.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("lambda_styel"), "{e}");
    }
}
