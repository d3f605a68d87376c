//! `dsgs bake`: bakes one style into a plain 3DGS `.ply` (SH colours of the bundle's frozen
//! geometry fitted to stylized views, `train::bake`), for any 3DGS viewer.
//!
//! The style target is built as `dsgs stylize` builds it ([`crate::stylize::style_targets`]):
//! each `--style` image is read (longer side at most `style_side`) and encoded with the bundle's
//! encoder; several styles must be mixed with `--mix` into one target, since a `.ply` holds
//! one set of colours. The deepest level's statistics at strength `alpha`
//! (`SceneBundle::target_stats`) drive the stylized targets.
//!
//! Configuration: the keys of `train::BakeConfig` (TOML, `--config`), overridden by flags
//! ([`BakeOverrides`]). Outputs: the `.ply` (written atomically) and, beside it, a JSON report
//! with the same stem ([`report_path`]): the inputs, the effective configuration, the PSNR of the
//! baked and of the unbaked scene against the training and held-out targets, and the times.
//!
//! Inputs are checked before the bundle is loaded or anything is trained or written: the
//! strength and the mixture weights ([`crate::stylize::check_style_settings`]), the output
//! name, and every style image, read and decoded up front; then, with the bundle, the size of
//! every target view at `resolution_scale` ([`crate::cameras::check_image_size`]).
//!
//! The optimisation checkpoints into a folder beside the `.ply` ([`checkpoint_dir`]:
//! `baked.ply` -> `baked.checkpoint/checkpoint.safetensors`) periodically and when stopped; a
//! stopped bake writes no `.ply` and continues exactly with `--resume` and the same inputs.

use std::path::{Path, PathBuf};

use crate::cli::{mebibytes, non_negative, positive, whole_in, with_default};
use crate::error::{bail, Context, Result};
use base::write_atomic;
use gaussian::ply::save_ply;
use serde::Serialize;
use train::bake::STORED_SH_DEGREE;
use train::{BakeConfig, BakeReport, Variant};

use crate::cameras::check_image_size;
use crate::open::load_bundle;
use crate::shard::{Invocation, Part, Shard};
use crate::stylize::{check_style_settings, load_styles, style_targets};
use crate::{config, Control};
use train::RunOutcome;

/// Command-line values that override the configuration.
///
/// As [`clap::Args`], the flags from `--iterations` to `--tile-budget`; the two run intervals
/// are the program's to declare with its other run flags (`--checkpoint-every`,
/// `--log-every`).
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct BakeOverrides {
    /// Optimisation iterations after the colour solve (`--iterations`; key `iterations`).
    #[arg(long, help = with_default(
        "Optimisation iterations after the closed-form colour solve (colour and degree-1 SH). \
         0: the solve alone, in seconds (on the 100x100 demo bundle 24.9 dB on held-out \
         stylized views in 5 s; 1,000 iterations add 0.1 dB in 14 s more, 3,000 add 0.2 dB in \
         41 s; docs/results.md)",
        BakeConfig::default().iterations,
    ))]
    pub iterations: Option<u64>,
    /// Iterations of the colour solve (`--solve-iterations`; key
    /// `solve_iterations`).
    #[arg(long, help = with_default(
        "Most iterations of the closed-form colour solve that starts the bake (0: no solve, \
         the optimisation starts from the bundle's colours)",
        BakeConfig::default().solve_iterations,
    ))]
    pub solve_iterations: Option<usize>,
    /// SH degree that is optimised, 0..=3; the `.ply` always stores degree 3 (`--sh-degree`; key
    /// `sh_degree`).
    #[arg(long, value_parser = whole_in(0, STORED_SH_DEGREE), help = with_default(
        "SH degree that is optimised (0 to 3; the .ply always stores degree 3)",
        BakeConfig::default().sh_degree,
    ))]
    pub sh_degree: Option<usize>,
    /// Also adapt opacities and scales, within small budgets (`--adapt-geometry`; key
    /// `adapt_geometry`). `false` leaves the configuration's value.
    #[arg(long, help = "Also adapt opacities and scales, within small budgets")]
    pub adapt_geometry: bool,
    /// Adam rate of the SH DC coefficients (`--lr`; key `feature_lr`).
    #[arg(long, value_parser = non_negative, help = with_default(
        "Adam rate of the SH DC coefficients (0 or more)",
        BakeConfig::default().feature_lr,
    ))]
    pub lr: Option<f64>,
    /// Number of training target views, 0 for all candidates (`--target-views`; key
    /// `target_views`).
    #[arg(long, help = with_default(
        "Number of training target views (0: all candidates)",
        BakeConfig::default().target_views,
    ))]
    pub target_views: Option<usize>,
    /// Interpolated views held out for evaluation (`--held-out`; key `held_out`).
    #[arg(long, help = with_default(
        "Interpolated views held out for evaluation",
        BakeConfig::default().held_out,
    ))]
    pub held_out: Option<usize>,
    /// Image size of the targets relative to the bundle's cameras (`--resolution-scale`; key
    /// `resolution_scale`).
    #[arg(long, value_parser = positive, help = with_default(
        "Image size of the targets relative to the bundle's cameras (above 0)",
        BakeConfig::default().resolution_scale,
    ))]
    pub resolution_scale: Option<f64>,
    /// Seed of the view order (`--seed`; key `seed`).
    #[arg(long, help = with_default("Seed of the view order", BakeConfig::default().seed))]
    pub seed: Option<u64>,
    /// Iterations between log lines (`--log-every`; key `log_interval`).
    #[arg(skip)]
    pub log_every: Option<u64>,
    /// Iterations between periodic checkpoints, 0 for only when stopped (`--checkpoint-every`;
    /// key `checkpoint_interval`).
    #[arg(skip)]
    pub checkpoint_every: Option<u64>,
    /// Working memory of the networks per decoded target view, in MiB (`--tile-budget`; key
    /// `tile_budget_mib`).
    #[arg(long = "tile-budget", value_name = "TILE_BUDGET", value_parser = mebibytes(), help = with_default(
        "Working memory of the networks per decoded target view, in MiB: views are decoded in \
         tiles that fit it (any budget gives the same targets; 1 to 1048576)",
        BakeConfig::default().tile_budget_mib,
    ))]
    pub tile_budget_mib: Option<u64>,
}

impl BakeOverrides {
    /// Applies the overrides.
    pub fn apply(&self, c: &mut BakeConfig) {
        if let Some(v) = self.iterations {
            c.iterations = v;
        }
        if let Some(v) = self.solve_iterations {
            c.solve_iterations = v;
        }
        if let Some(v) = self.sh_degree {
            c.sh_degree = v;
        }
        if self.adapt_geometry {
            c.adapt_geometry = true;
        }
        if let Some(v) = self.lr {
            c.feature_lr = v;
        }
        if let Some(v) = self.target_views {
            c.target_views = v;
        }
        if let Some(v) = self.held_out {
            c.held_out = v;
        }
        if let Some(v) = self.resolution_scale {
            c.resolution_scale = v;
        }
        if let Some(v) = self.seed {
            c.seed = v;
        }
        if let Some(v) = self.log_every {
            c.log_interval = v;
        }
        if let Some(k) = self.checkpoint_every {
            c.checkpoint_interval = k;
        }
        if let Some(v) = self.tile_budget_mib {
            c.tile_budget_mib = v;
        }
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BakeSettings {
    /// The scene bundle directory whose geometry is baked (the `BUNDLE` argument).
    pub bundle: PathBuf,
    /// The style images (`--style`, repeated).
    pub styles: Vec<PathBuf>,
    /// Mixture weights, one per style (`--mix`; required with several styles).
    pub weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style (`--alpha`).
    pub alpha: f64,
    /// Longest side of the style images after loading (`--style-size`).
    pub style_side: u32,
    /// Network variant; `None` keeps the bundle's (`--variant`).
    pub variant: Option<Variant>,
    /// Replace the bundle's decoder (`--decoder`: `.safetensors` or a PyTorch checkpoint).
    pub decoder: Option<PathBuf>,
    /// TOML file of `train::BakeConfig` keys (`--config`); `None` starts from the defaults.
    pub config: Option<PathBuf>,
    /// Command-line values applied on top of the configuration.
    pub overrides: BakeOverrides,
    /// The output `.ply`.
    pub output: PathBuf,
    /// Continue from this checkpoint of a stopped bake of the same inputs.
    pub resume: Option<PathBuf>,
    /// The whole bake, or the fit of the targets that shards rendered ([`Part::Assemble`];
    /// a shard itself runs through [`render_target_shard`]).
    pub part: Part,
}

/// The name of the shard manifests of `dsgs bake` ([`crate::shard`]).
pub const SHARD_COMMAND: &str = "bake";

/// The folder of a sharded bake's target files and manifests: the output path with the
/// extension `shards` (`baked.ply` -> `baked.shards`).
pub fn shard_dir(ply: &Path) -> PathBuf {
    ply.with_extension("shards")
}

/// The file of target `i` of the target sequence ([`train::bake::target_sequence`]) in a
/// shard folder.
pub fn target_file(shard_dir: &Path, i: usize) -> PathBuf {
    shard_dir.join(format!("target-{i:05}.safetensors"))
}

/// What a shard of the target rendering wrote.
#[derive(Clone, Debug)]
pub struct TargetShard {
    /// The shard.
    pub shard: Shard,
    /// The folder of the shards' target files and manifests ([`shard_dir`]).
    pub dir: PathBuf,
    /// Its block of the target sequence.
    pub range: std::ops::Range<usize>,
    /// Targets in the whole sequence.
    pub targets: usize,
    /// The target files it wrote.
    pub files: Vec<PathBuf>,
    /// Its manifest.
    pub manifest: PathBuf,
}

/// The line of a finished shard: its block of target views and where they were written.
impl std::fmt::Display for TargetShard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "shard {}: target views {} to {} of {} written to {}",
            self.shard,
            self.range.start,
            self.range.end.saturating_sub(1),
            self.targets,
            self.dir.display()
        )
    }
}

/// The JSON report written beside the baked scene.
#[derive(Clone, Debug, Serialize)]
pub struct BakeSummary {
    /// The scene bundle directory, as given.
    pub bundle: String,
    /// The style images, as given.
    pub styles: Vec<String>,
    /// The mixture weights of the styles, if given.
    pub weights: Option<Vec<f64>>,
    /// The style strength.
    pub alpha: f64,
    /// Gaussians in the baked scene.
    pub gaussians: usize,
    /// The iteration the optimisation ended at.
    pub iterations: u64,
    /// Whether a stop request ended the optimisation early.
    pub interrupted: bool,
    /// Training target views.
    pub train_views: usize,
    /// Held-out target views.
    pub held_out_views: usize,
    /// Mean PSNR (dB) of the baked scene against the training targets.
    pub train_psnr: f64,
    /// Mean PSNR (dB) of the baked scene against the held-out targets (`None` without held-out
    /// views).
    pub held_out_psnr: Option<f64>,
    /// Mean PSNR (dB) of the bundle's own colours, before baking, against the training targets.
    pub unbaked_train_psnr: f64,
    /// Mean PSNR (dB) of the bundle's own colours against the held-out targets.
    pub unbaked_held_out_psnr: Option<f64>,
    /// Wall time of the target rendering, in seconds.
    pub target_seconds: f64,
    /// Wall time of the optimisation, in seconds.
    pub optimise_seconds: f64,
    /// The closed-form colour solve that started the bake (`None` when resumed or disabled).
    pub solve: Option<train::bake::BakeSolveReport>,
    /// The effective configuration (file and flags).
    pub config: BakeConfig,
}

/// What a bake did and wrote.
#[derive(Clone, Debug)]
pub struct BakeOutput {
    /// The report, also written as JSON beside the `.ply` when the bake completed.
    pub summary: BakeSummary,
    /// How the optimisation ended (with the stop checkpoint when it was stopped).
    pub run: RunOutcome,
    /// The `.ply` and its report, written when the bake completed.
    pub written: Option<(PathBuf, PathBuf)>,
}

/// The summary of a bake: the targets and, when it completed, the PSNRs and the files written
/// (how the optimisation ended is [`BakeOutput::run`]'s to tell).
impl std::fmt::Display for BakeOutput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = &self.summary;
        writeln!(
            f,
            "{} training and {} held-out target views, targets in {:.1} s",
            s.train_views, s.held_out_views, s.target_seconds
        )?;
        let Some((ply, report)) = &self.written else {
            return Ok(());
        };
        let db = |p: Option<f64>| p.map_or_else(|| "-".to_string(), |v| format!("{v:.3} dB"));
        if let Some(v) = &s.solve {
            writeln!(
                f,
                "colour solve (SH degree {}): {} iterations in {:.1} s (residual {:.1e}, {} \
                 Gaussians unseen), held-out PSNR {}",
                v.degree,
                v.iterations,
                v.seconds,
                v.residual,
                v.unseen,
                db(v.held_out_psnr)
            )?;
        }
        writeln!(
            f,
            "training PSNR: baked {:.3} dB, unbaked {:.3} dB",
            s.train_psnr, s.unbaked_train_psnr
        )?;
        writeln!(
            f,
            "held-out PSNR: baked {}, unbaked {}",
            db(s.held_out_psnr),
            db(s.unbaked_held_out_psnr)
        )?;
        writeln!(
            f,
            "{} Gaussians written to {}, report {}",
            s.gaussians,
            ply.display(),
            report.display()
        )
    }
}

/// The report beside `ply`: the same path with the extension `json`.
pub fn report_path(ply: &Path) -> PathBuf {
    ply.with_extension("json")
}

/// The folder of a bake's checkpoint: the output path with the extension `checkpoint`.
pub fn checkpoint_dir(ply: &Path) -> PathBuf {
    ply.with_extension("checkpoint")
}

/// Checks the size of every target view: each camera of the bundle scaled by
/// `resolution_scale` (rounded as `gaussian::Camera::scaled` rounds) must be within the image
/// size limits. The error names the camera, the bundle and the scale.
pub fn check_target_sizes(info: &runtime::BundleInfo, scale: f64, bundle: &Path) -> Result<()> {
    for (i, c) in info.cameras.iter().enumerate() {
        let w = (c.width as f64 * scale).round().max(1.0);
        let h = (c.height as f64 * scale).round().max(1.0);
        check_image_size(
            &format!(
                "camera {i} ({}) of {} at --resolution-scale (resolution_scale) {scale}",
                c.name,
                bundle.display()
            ),
            // `as u64` saturates: a size beyond it is still reported as too large.
            w as u64,
            h as u64,
        )?;
    }
    Ok(())
}

/// What the bake's parts share: the configuration, the bundle, the style statistics and the
/// target cameras, all checked.
struct Prepared {
    cfg: BakeConfig,
    bundle: runtime::SceneBundle,
    stats: style::ChannelStats<f32>,
    cameras: train::bake::BakeCameras,
    fingerprint: String,
}

fn prepare(settings: &BakeSettings) -> Result<Prepared> {
    let mut cfg: BakeConfig = config::load(settings.config.as_deref())?;
    settings.overrides.apply(&mut cfg);
    cfg.validate().context("checking the bake configuration")?;
    check_style_settings(
        settings.alpha,
        settings.weights.as_deref(),
        settings.styles.len(),
    )?;
    if settings.output.extension().is_none_or(|e| e == "json") {
        bail!(
            "the output {} should be a .ply file",
            settings.output.display()
        );
    }
    if settings.styles.len() > 1 && settings.weights.is_none() {
        bail!(
            "a baked scene holds one style: mix the {} style images with --mix",
            settings.styles.len()
        );
    }
    // Every style image is decoded before the bundle is loaded and long before training.
    let styles = load_styles(&settings.styles, settings.style_side)?;
    let bundle = load_bundle(
        &settings.bundle,
        settings.variant,
        settings.decoder.as_deref(),
    )?;
    check_target_sizes(&bundle.info, cfg.resolution_scale, &settings.bundle)?;
    let targets = style_targets(&bundle, &styles, settings.weights.as_deref(), None)?;
    let target = &targets[0];
    let stats = bundle
        .target_stats(target.stats.deepest(), settings.alpha)
        .context("the style's target statistics")?;
    let cameras = train::bake::bake_cameras(&bundle.cameras(), &cfg)
        .context("choosing the target cameras")?;
    // Every target depends on the bundle, the statistics, its camera and the compositing.
    let mut h = base::Fnv1a::new();
    h.eat_str(SHARD_COMMAND);
    h.eat_str(&bundle.fingerprint());
    stats
        .mean
        .iter()
        .chain(stats.std.iter())
        .for_each(|&v| h.eat_f32(v));
    for c in train::bake::target_sequence(&cameras) {
        h.eat_str(&c.name);
        crate::stylize::hash_camera(&mut h, &c.camera);
    }
    h.eat_u64(cfg.composite_background as u64);
    let fingerprint = h.hex();
    Ok(Prepared {
        cfg,
        bundle,
        stats,
        cameras,
        fingerprint,
    })
}

/// Renders shard `shard` of a bake's stylized targets (a block of
/// [`train::bake::target_sequence`]) into target files in [`shard_dir`] (exact `f32` images,
/// [`train::bake::target_to_bytes`]) and writes the shard's manifest last. `dsgs assemble` of
/// the `.ply` ([`Part::Assemble`]) then fits the targets of every shard, giving the `.ply` of
/// a one-process bake bit for bit.
pub fn render_target_shard(
    settings: &BakeSettings,
    shard: Shard,
    invocation: Option<Invocation>,
    control: &Control,
) -> Result<TargetShard> {
    let started = std::time::Instant::now();
    let p = prepare(settings)?;
    let sequence = train::bake::target_sequence(&p.cameras);
    let range = shard.range(sequence.len());
    let dir = shard_dir(&settings.output);
    let ck_dir = checkpoint_dir(&settings.output);
    let (views, _) = train::bake::render_bake_targets(
        &p.bundle,
        &p.stats,
        &sequence[range.clone()],
        &p.cfg,
        &control.run_in(&ck_dir),
    )
    .with_context(|| format!("rendering the targets of shard {shard}"))?;
    let mut files = Vec::with_capacity(views.len());
    for (i, v) in range.clone().zip(&views) {
        let path = target_file(&dir, i);
        let bytes = train::bake::target_to_bytes(v)?;
        write_atomic(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
        files.push(path);
    }
    let records = files
        .iter()
        .map(|f| crate::shard::record_file(&dir, f))
        .collect::<Result<Vec<_>>>()?;
    let manifest = crate::shard::write_manifest(
        &dir,
        &crate::shard::Manifest {
            format: crate::shard::MANIFEST_FORMAT.into(),
            command: SHARD_COMMAND.into(),
            shard,
            items: sequence.len(),
            range: range.clone(),
            fingerprint: p.fingerprint,
            invocation,
            files: records,
            seconds: started.elapsed().as_secs_f64(),
            data: serde_json::Value::Null,
        },
    )?;
    Ok(TargetShard {
        shard,
        dir,
        range,
        targets: sequence.len(),
        files,
        manifest,
    })
}

/// Runs the bake, reporting to the control's sink, and writes the `.ply` and its report when it
/// completes. A stop request during the optimisation ends it with a checkpoint
/// ([`RunOutcome::stop_checkpoint`]) and writes nothing else; during the target rendering it
/// fails with `train::TrainError::Interrupted`. With [`Part::Assemble`] the targets are read
/// from the files of a finished split ([`render_target_shard`], checked by
/// [`crate::shard::collect`]) instead of rendered.
pub fn run(settings: &BakeSettings, control: &Control) -> Result<BakeOutput> {
    if let Part::Shard { .. } = settings.part {
        bail!("a shard of a bake renders targets only: use render_target_shard");
    }
    let p = prepare(settings)?;
    let ck_dir = checkpoint_dir(&settings.output);
    let run = control.run_in(&ck_dir);
    let resume = settings.resume.as_deref();
    let r: BakeReport = if settings.part == Part::Assemble {
        let dir = shard_dir(&settings.output);
        let sequence = train::bake::target_sequence(&p.cameras);
        let started = std::time::Instant::now();
        let manifests = crate::shard::collect(
            &dir,
            &crate::shard::Expected {
                command: SHARD_COMMAND,
                fingerprint: &p.fingerprint,
                items: sequence.len(),
                root: &dir,
            },
        )?;
        let mut views = Vec::with_capacity(sequence.len());
        for (i, c) in sequence.iter().enumerate() {
            let path = target_file(&dir, i);
            let bytes =
                std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            views.push(train::bake::target_from_bytes(&bytes, &path, c)?);
        }
        let train = views.split_off(p.cameras.held_out.len());
        let targets = train::bake::BakeTargets {
            train,
            held_out: views,
            // The rendering's wall time, summed over the shards, and the reading.
            seconds: manifests.iter().map(|m| m.seconds).sum::<f64>()
                + started.elapsed().as_secs_f64(),
        };
        train::bake::bake_targets(&p.bundle, targets, &p.cfg, resume, &run)
    } else {
        train::bake(&p.bundle, &p.stats, &p.cfg, resume, &run)
    }
    .with_context(|| format!("baking into the bundle {}", settings.bundle.display()))?;
    let cfg = p.cfg;
    let summary = BakeSummary {
        bundle: settings.bundle.display().to_string(),
        styles: settings
            .styles
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        weights: settings.weights.clone(),
        alpha: settings.alpha,
        gaussians: r.scene.len(),
        iterations: r.run.step,
        interrupted: r.run.interrupted,
        train_views: r.train_views,
        held_out_views: r.held_out_views,
        train_psnr: r.train_psnr,
        held_out_psnr: r.held_out_psnr,
        unbaked_train_psnr: r.unbaked_train_psnr,
        unbaked_held_out_psnr: r.unbaked_held_out_psnr,
        target_seconds: r.target_seconds,
        optimise_seconds: r.run.seconds,
        solve: r.solve.clone(),
        config: cfg,
    };
    if r.run.interrupted {
        return Ok(BakeOutput {
            summary,
            run: r.run,
            written: None,
        });
    }
    if let Some(dir) = settings
        .output
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
    {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    save_ply(&settings.output, &r.scene)
        .with_context(|| format!("writing {}", settings.output.display()))?;
    let report = report_path(&settings.output);
    let json = serde_json::to_string_pretty(&summary).context("serialising the bake report")?;
    write_atomic(&report, json.as_bytes())
        .with_context(|| format!("writing {}", report.display()))?;
    Ok(BakeOutput {
        summary,
        run: r.run,
        written: Some((settings.output.clone(), report)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_and_report_path() {
        let mut c = BakeConfig::default();
        BakeOverrides {
            iterations: Some(7),
            sh_degree: Some(1),
            adapt_geometry: true,
            lr: Some(0.01),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!(c.iterations, 7);
        assert_eq!(c.sh_degree, 1);
        assert!(c.adapt_geometry);
        assert_eq!(c.feature_lr, 0.01);
        assert_eq!(
            report_path(Path::new("out/lego.ply")),
            Path::new("out/lego.json")
        );
    }
}
