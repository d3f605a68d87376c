//! `dsgs run`: the whole pipeline on a capture in one resumable command, from posed photos to a
//! scene bundle, a stylized video along a smooth tour of the capture, a contact sheet and the
//! evaluation; and the stages' runner, which `dsgs demo` drives with the lego scene.
//!
//! A run is a [`Plan`]: the dataset, the schedules, the networks and the paintings. `dsgs run`
//! makes one from a quality preset ([`Quality`]: image size, iterations, frames) and the
//! capture's image size; `dsgs demo` from its own settings. Before anything runs, every input is
//! checked ([`check_inputs`]): missing files are listed with where to get them, and every image
//! a stage will read is decoded, so a bad painting fails at once rather than after the training
//! stages.
//!
//! Stages, each in its own folder of the output directory and each skipped when its result is
//! already there (so an interrupted run continues where it stopped, and a finished one reruns in
//! seconds):
//!
//! 1. `weights.safetensors`: the encoder and its decoder of the chosen [`Pair`] (the encoder
//!    imported from its PyTorch checkpoint, the decoder likewise or built in), or the canonical
//!    weights file given instead.
//! 2. `geometry/`: `dsgs fit-geometry` on the dataset: the 3DGS schedule scaled to the plan's
//!    iterations ([`geometry_config`]).
//! 3. `features/`: `dsgs fit-features` on that geometry with the training paintings: the
//!    alignment-only warm-up, then the full loss (alignment, content and style).
//! 4. `stylized/`: `dsgs stylize` along the plan's cameras with the paintings: PNG frames, a GIF
//!    per painting and `contact_sheet.png` (paintings x views).
//! 5. `eval.json`: `dsgs eval` of the same frames with the per-frame 2D baseline
//!    (short- and long-range consistency, style loss, texture distance, content loss, seconds
//!    per view), its frames under `eval/` and `eval/comparison.png`: colour | 2D per-frame |
//!    dsgs for each painting, the same views.
//!
//! Stages 1 to 3 count as done when their final outputs are there (the geometry's scene and its
//! last checkpoint, the feature stage's bundle); an unfinished training stage resumes from its
//! checkpoint. Stages 4 and 5 write a record `OUT/stylize.done.json` or `OUT/eval.done.json`
//! (atomically, after all their outputs) of what they were made from: the files of the scene
//! bundle, the decoder and the style images (each path with its size and modification time), the
//! variant, the cameras and the rendering settings. A rerun skips such a stage only when its
//! record matches the run and every output it lists is still there; otherwise the stage runs
//! again (e.g. after `--style` changes, or when the features were trained again).
//!
//! Every stage writes its effective configuration beside its outputs.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::error::{bail, Context, Error, Result};
use crate::Control;
use gaussian::dataset::Dataset;
use train::checkpoint::checkpoint_step;
use train::image_folder::collect_images;
use train::{FeatureTrainConfig, GeometryConfig, Variant};

use crate::cameras::{CameraRequest, CameraSource, KnownCameras};
use crate::consistency::WarpOptions;
use crate::eval::{EvalReport, EvalSettings};
use crate::fit_features::{FeatureOverrides, FitFeaturesConfig, FitFeaturesSettings};
use crate::fit_geometry::{FitGeometryConfig, FitSettings, GeometryOverrides};
use crate::pretrain_decoder::NetworkFiles;
use crate::stylize::{StylizeOutput, StylizeSettings};
use crate::weights::Pair;
use crate::{config, image_io, stylize, weights};

/// Where a run's networks come from.
#[derive(Clone, Debug, PartialEq)]
pub enum Networks {
    /// A canonical weights file (encoder and decoder).
    File(PathBuf),
    /// The encoder's PyTorch checkpoint and the decoder's (or the built-in decoder), imported
    /// into `OUT/weights.safetensors` by the first stage.
    Import {
        /// The encoder checkpoint.
        encoder: PathBuf,
        /// The decoder checkpoint; `None`: [`weights::BUILT_IN_DECODER`].
        decoder: Option<PathBuf>,
    },
}

impl Networks {
    /// The weights file given, else the `pair`'s checkpoints under the shared folder.
    pub fn given_or_shared(weights: Option<&PathBuf>, pair: Pair, shared: &Path) -> Networks {
        match weights {
            Some(w) => Networks::File(w.clone()),
            None => Networks::Import {
                encoder: shared.join(pair.encoder()),
                decoder: pair.decoder().map(|d| shared.join(d)),
            },
        }
    }
}

/// Stage 3's settings that depend on the networks: the pair's ([`Pair::supersample`],
/// [`Pair::content_style_weight`]) unless a weights file replaces its networks (then the
/// direct render and the paper's weights).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stage3Choice {
    /// The feature render's supersampling factor (1: direct).
    pub supersample: u32,
    /// The weight of the content and the style term (0: alignment only).
    pub content_style_weight: f64,
}

impl Stage3Choice {
    /// The choice for a run with `pair`, or with the networks of a weights file.
    pub fn of(weights: Option<&PathBuf>, pair: Pair) -> Stage3Choice {
        if weights.is_some() {
            Stage3Choice {
                supersample: 1,
                content_style_weight: 1.0,
            }
        } else {
            Stage3Choice {
                supersample: pair.supersample(),
                content_style_weight: pair.content_style_weight(),
            }
        }
    }
}

/// Everything a run does: inputs, schedules and outputs.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The capture: a COLMAP, NeRF-synthetic or LLFF dataset directory.
    pub dataset: PathBuf,
    /// The file of the dataset that must exist (named when missing, e.g.
    /// `transforms_train.json`); `None`: the directory itself.
    pub dataset_marker: Option<PathBuf>,
    /// Background of the geometry and feature stages (white for NeRF-synthetic captures).
    pub background: [f32; 3],
    /// Images resized by `1 / downscale` on load.
    pub downscale: f64,
    /// Random initial points of the geometry (`None`: the configuration's default, used only
    /// when the dataset has no point cloud).
    pub random_init_points: Option<usize>,
    /// Output directory of the stages.
    pub out_dir: PathBuf,
    /// The encoder and decoder.
    pub networks: Networks,
    /// Stage 3's supersampling and loss weights.
    pub stage3: Stage3Choice,
    /// A decoder replacing the networks' (e.g. one fine-tuned for fullres).
    pub decoder: Option<PathBuf>,
    /// Network variant.
    pub variant: Variant,
    /// Geometry iterations.
    pub geometry_iterations: u64,
    /// Alignment-only feature iterations at the start.
    pub align_warmup: u64,
    /// Feature iterations in all, the warm-up included.
    pub feature_iterations: u64,
    /// Paintings the features are trained with (folders or files).
    pub training_styles: Vec<PathBuf>,
    /// Paintings to stylize with.
    pub styles: Vec<PathBuf>,
    /// Frames of the stylized sequence.
    pub frames: usize,
    /// Where the frames' cameras come from (a smooth tour of the capture for `run`).
    pub cameras: CameraSource,
    /// What to tell a user whose files are missing: where the public versions come from.
    pub sources: String,
}

/// The default training paintings, under `SHARED`.
pub const TRAINING_STYLES: &str = "data/styles/small-set";
/// A quality preset of `dsgs run`: the images' size and the stages' lengths.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quality {
    /// A first look in minutes: images at most 160 pixels, short schedules, 24 frames.
    Draft,
    /// Images at most 320 pixels, longer schedules, 48 frames.
    Standard,
    /// Images at most 640 pixels, the 3DGS schedule's 30,000 geometry iterations, 96 frames.
    High,
}

/// What a [`Quality`] sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Preset {
    /// The longest image side the capture is downscaled to (never upscaled).
    pub side: u32,
    /// Geometry iterations.
    pub geometry_iterations: u64,
    /// Alignment-only feature iterations at the start.
    pub align_warmup: u64,
    /// Feature iterations in all, the warm-up included.
    pub feature_iterations: u64,
    /// Frames of the stylized tour.
    pub frames: usize,
}

impl Quality {
    /// Every value, by its command-line name.
    pub const NAMES: &'static [&'static str] = &["draft", "standard", "high"];

    /// The command-line name.
    pub fn as_str(self) -> &'static str {
        match self {
            Quality::Draft => "draft",
            Quality::Standard => "standard",
            Quality::High => "high",
        }
    }

    /// The preset's sizes and schedules.
    pub fn preset(self) -> Preset {
        match self {
            Quality::Draft => Preset {
                side: 160,
                geometry_iterations: 3_000,
                align_warmup: 1_500,
                feature_iterations: 2_000,
                frames: 24,
            },
            Quality::Standard => Preset {
                side: 320,
                geometry_iterations: 7_000,
                align_warmup: 2_000,
                feature_iterations: 3_000,
                frames: 48,
            },
            Quality::High => Preset {
                side: 640,
                geometry_iterations: 30_000,
                align_warmup: 3_000,
                feature_iterations: 6_000,
                frames: 96,
            },
        }
    }
}

impl std::str::FromStr for Quality {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "draft" => Ok(Quality::Draft),
            "standard" => Ok(Quality::Standard),
            "high" => Ok(Quality::High),
            _ => Err(format!(
                "unknown quality `{s}` (expected one of: draft, standard, high)"
            )),
        }
    }
}

/// Where the default files of `dsgs run` come from, for the error when they are missing.
const RUN_SOURCES: &str = "\
dsgs run needs, besides the capture and the paintings, under the shared folder (--shared,
DSGS_SHARED or ../shared) unless given otherwise:
  data/styles/small-set/*.jpg        paintings to train the features with (or --training-style)
  weights/compressed-16x-relu4_1/4SE.pth
                                     the 16x-compressed normalised VGG-19 encoder to relu4_1
                                     (the default --networks relu4_1; its decoder is built in)
  weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth
  weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth
                                     the normalised VGG-19 encoder to relu3_1 and its inverting
                                     decoder (--networks wct-relu3_1: the WCT feature invertors
                                     of the universal style transfer code); or --weights
                                     NETS.safetensors made by `dsgs weights import`";

/// Settings of `dsgs run`; as [`clap::Args`], its flags.
#[derive(Clone, Debug, clap::Args)]
pub struct RunSettings {
    /// The capture: a COLMAP, NeRF-synthetic or LLFF dataset directory.
    pub dataset: PathBuf,
    /// Paintings to stylize with.
    #[arg(
        long = "style",
        required = true,
        help = "Painting to stylize with, or a folder of \
        them; repeat for several (at least one)"
    )]
    pub styles: Vec<PathBuf>,
    /// Output directory.
    #[arg(
        short,
        long = "output",
        value_name = "OUTPUT",
        help = "Output directory; run the \
        same command again to continue an interrupted run (finished stages are skipped)"
    )]
    pub out_dir: PathBuf,
    /// The quality preset.
    #[arg(long, default_value = "draft", value_parser = crate::cli::one_of::<Quality>(
        Quality::NAMES.iter().copied()),
        help = "Image size and schedules: draft (images at most 160 pixels, geometry 3,000 \
        iterations, features 2,000, 24 frames), standard (320 pixels, 7,000, 3,000, 48 frames) or \
        high (640 pixels, 30,000, 6,000, 96 frames)")]
    pub quality: Quality,
    /// The shared data folder.
    #[arg(
        long,
        env = "DSGS_SHARED",
        default_value = "../shared",
        help = "The shared data \
        folder holding the default networks and training paintings"
    )]
    pub shared: PathBuf,
    /// The pair of networks by name.
    #[arg(long, default_value = "relu4_1", value_parser = crate::cli::one_of::<Pair>(
        Pair::NAMES.iter().copied()),
        help = crate::cli::NETWORKS_HELP)]
    pub networks: Pair,
    /// Canonical network weights instead of the named pair.
    #[arg(
        long,
        help = "Canonical network weights (.safetensors, encoder and decoder) instead of \
        --networks [default: the --networks pair]"
    )]
    pub weights: Option<PathBuf>,
    /// A decoder replacing the weights'.
    #[arg(
        long,
        help = "A decoder (PyTorch checkpoint or .safetensors) replacing the one of the \
        weights, e.g. one fine-tuned by `dsgs pretrain-decoder` for --variant fullres \
        [default: the weights']"
    )]
    pub decoder: Option<PathBuf>,
    /// Network variant.
    #[arg(long, default_value = "standard", value_parser = crate::cli::variant(),
        help = "Network variant (fullres needs a decoder fine-tuned for it to stylize strongly)")]
    pub variant: Variant,
    /// Paintings the features are trained with.
    #[arg(
        long = "training-style",
        help = "Painting (or folder) the features are trained \
        with; repeat for several [default: SHARED/data/styles/small-set]"
    )]
    pub training_styles: Vec<PathBuf>,
    /// White background.
    #[arg(
        long,
        help = "White background [default: white for NeRF-synthetic captures, else \
        black]"
    )]
    pub white: bool,
    /// Downscale factor instead of the preset's image size.
    #[arg(long, value_parser = crate::cli::positive, help = "Downscale the capture's images by \
        this factor (above 0) [default: to the preset's image size]")]
    pub downscale: Option<f64>,
    /// Frames instead of the preset's.
    #[arg(long, value_parser = crate::cli::at_least_one::<usize>(), help = "Frames of the \
        stylized tour (at least 1) [default: the preset's]")]
    pub frames: Option<usize>,
    /// Geometry iterations instead of the preset's.
    #[arg(long, value_parser = crate::cli::at_least_one::<u64>(), help = "Geometry iterations \
        (at least 1; the 3DGS schedule scaled to them) [default: the preset's]")]
    pub geometry_iterations: Option<u64>,
    /// Alignment-only feature iterations instead of the preset's.
    #[arg(
        long,
        help = "Alignment-only feature iterations at the start of the feature stage \
        [default: the preset's]"
    )]
    pub align_warmup: Option<u64>,
    /// Feature iterations instead of the preset's.
    #[arg(long, value_parser = crate::cli::at_least_one::<u64>(), help = "Feature iterations \
        in all, the warm-up included (at least 1) [default: the preset's]")]
    pub feature_iterations: Option<u64>,
}

/// The plan of `dsgs run`: the preset's schedules, the capture downscaled so that its longest
/// side is at most the preset's (read from the dataset's cameras; never upscaled), white
/// for NeRF-synthetic captures, and a smooth tour of the capture ([`CameraSource::Path`]).
pub fn plan(s: &RunSettings) -> Result<Plan> {
    let p = s.quality.preset();
    let dataset = Dataset::load(&s.dataset, &gaussian::dataset::LoadOptions::default())
        .with_context(|| format!("loading the dataset {}", s.dataset.display()))?;
    let longest = dataset
        .cameras
        .iter()
        .map(|c| c.intrinsics.width.max(c.intrinsics.height))
        .max()
        .unwrap_or(p.side);
    let downscale = s
        .downscale
        .unwrap_or((longest as f64 / p.side as f64).max(1.0));
    let nerf = dataset.kind == gaussian::dataset::DatasetKind::NerfSynthetic;
    Ok(Plan {
        dataset: s.dataset.clone(),
        dataset_marker: None,
        background: if s.white || nerf { [1.0; 3] } else { [0.0; 3] },
        downscale,
        random_init_points: None,
        out_dir: s.out_dir.clone(),
        networks: Networks::given_or_shared(s.weights.as_ref(), s.networks, &s.shared),
        stage3: Stage3Choice::of(s.weights.as_ref(), s.networks),
        decoder: s.decoder.clone(),
        variant: s.variant,
        geometry_iterations: s.geometry_iterations.unwrap_or(p.geometry_iterations),
        align_warmup: s.align_warmup.unwrap_or(p.align_warmup),
        feature_iterations: s.feature_iterations.unwrap_or(p.feature_iterations),
        training_styles: if s.training_styles.is_empty() {
            vec![s.shared.join(TRAINING_STYLES)]
        } else {
            s.training_styles.clone()
        },
        styles: crate::stylize::style_files(&s.styles)?,
        frames: s.frames.unwrap_or(p.frames),
        cameras: CameraSource::Path,
        sources: RUN_SOURCES.to_string(),
    })
}

/// What a plan will do, in a few lines: the stages with their sizes and lengths.
pub fn describe(s: &Plan) -> String {
    let mut d = format!(
        "capture {} at 1/{:.3} of its size; outputs in {}\n",
        s.dataset.display(),
        s.downscale,
        s.out_dir.display()
    );
    let alignment = if s.stage3.content_style_weight == 0.0 {
        "all alignment-only".to_string()
    } else {
        format!(
            "{} alignment-only",
            s.align_warmup.min(s.feature_iterations)
        )
    };
    d += &format!(
        "  geometry: {} iterations\n  features: {} iterations ({alignment}), {} \
         network\n  stylize and evaluate: {} frames along {}, {}\n",
        s.geometry_iterations,
        s.feature_iterations,
        s.variant.as_str(),
        s.frames,
        s.cameras.as_str(),
        count(s.styles.len(), "painting")
    );
    d
}

/// The longest side of the style images in the stylize and eval stages.
pub const STYLE_SIDE: u32 = 256;

/// A duration for people: seconds under two minutes, else minutes.
pub fn human(seconds: f64) -> String {
    if seconds < 120.0 {
        format!("{seconds:.0} s")
    } else {
        format!("{:.1} min", seconds / 60.0)
    }
}

/// `n` and the noun, plural unless `n` is one: `count(1, "painting")` is "1 painting".
pub fn count(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

/// What a run produced.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Held-out PSNR (dB) at the geometry stage's last evaluation (`None` when the stage was
    /// skipped or evaluated nothing).
    pub geometry_psnr: Option<f64>,
    /// Gaussians in the scene bundle.
    pub gaussians: usize,
    /// What the stylization of the orbit wrote.
    pub stylized: StylizeOutput,
    /// The evaluation of the stylized orbit.
    pub eval: EvalReport,
    /// Where the evaluation report was written (`OUT/eval.json`).
    pub eval_json: PathBuf,
    /// The scene bundle the features stage wrote (`OUT/features/bundle`), for `dsgs view`.
    pub bundle: PathBuf,
    /// Seconds of each stage run now (`None`: skipped, its output was already there).
    pub seconds: Vec<(&'static str, Option<f64>)>,
    /// Estimated seconds of stages (e.g. by [`crate::estimate`] before the run), printed beside
    /// their times (`execute` leaves it empty).
    pub estimated: Vec<(&'static str, f64)>,
}

/// The summary of a run: the evaluation table, the geometry's PSNR, the stage times and the
/// outputs (of this run or, for a skipped stage, of the run that made them).
impl std::fmt::Display for RunReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&crate::eval::table(&self.eval))?;
        if let Some(p) = self.geometry_psnr {
            writeln!(f, "geometry: held-out PSNR {p:.2} dB")?;
        }
        writeln!(f, "{} Gaussians", self.gaussians)?;
        for (stage, t) in &self.seconds {
            let estimated = self.estimated.iter().find(|e| e.0 == *stage).map(|e| e.1);
            match (t, estimated) {
                (Some(t), Some(e)) => writeln!(
                    f,
                    "{stage:>9}: {t:.1} s (estimated {}, {:+.0}%)",
                    human(e),
                    100.0 * (e - t) / t
                )?,
                (Some(t), None) => writeln!(f, "{stage:>9}: {t:.1} s")?,
                (None, _) => writeln!(f, "{stage:>9}: done before, skipped")?,
            }
        }
        let s = &self.stylized;
        for p in s.gifs.iter().chain(&s.contact_sheet) {
            writeln!(f, "output {}", p.display())?;
        }
        writeln!(f, "output {}", self.eval_json.display())?;
        if let Some(p) = &self.eval.comparison {
            writeln!(f, "output {} (colour | 2D per-frame | dsgs)", p.display())?;
        }
        writeln!(f, "scene bundle {}", self.bundle.display())?;
        writeln!(
            f,
            "look around it and stylize any view in the browser: dsgs view {}",
            self.bundle.display()
        )
    }
}

/// Checks every input before anything runs, so that a bad file fails the run at once rather
/// than after minutes of training: first that the warm-up fits in the feature stage, then that
/// every input exists (naming all that are missing, with where to get them), then that every
/// image a stage will read decodes: the stylization styles always, and the training styles and
/// the capture's images unless the stages reading them (geometry and features) are already done.
/// Errors name the file (`style image PATH: ...`).
pub fn check_inputs(s: &Plan) -> Result<()> {
    if s.align_warmup > s.feature_iterations {
        bail!(
            "--align-warmup {} is longer than --feature-iterations {}, which counts the warm-up \
             too (as fit-features --iterations does)",
            s.align_warmup,
            s.feature_iterations
        );
    }
    if s.styles.is_empty() {
        bail!("give at least one --style painting to stylize with");
    }
    let mut missing = Vec::new();
    let mut need = |p: PathBuf| {
        if !p.exists() {
            missing.push(p.display().to_string());
        }
    };
    need(
        s.dataset_marker
            .clone()
            .unwrap_or_else(|| s.dataset.clone()),
    );
    for t in &s.training_styles {
        need(t.clone());
    }
    match &s.networks {
        Networks::File(w) => need(w.clone()),
        Networks::Import { encoder, decoder } => {
            need(encoder.clone());
            if let Some(d) = decoder {
                need(d.clone());
            }
        }
    }
    if let Some(d) = &s.decoder {
        need(d.clone());
    }
    for st in &s.styles {
        need(st.clone());
    }
    if !missing.is_empty() {
        bail!(
            "missing input files:\n  {}\n{}",
            missing.join("\n  "),
            s.sources
        );
    }
    for st in &s.styles {
        image_io::load_style_image(st, STYLE_SIDE)?;
    }
    let features_to_run = !features_done(s);
    if features_to_run {
        let training = collect_images(&s.training_styles, false)?;
        for st in &training {
            image_io::load_style_image(st, STYLE_SIDE)?;
        }
    }
    if features_to_run || !geometry_done(s) {
        let dataset = Dataset::load(&s.dataset, &geometry_config(s).load_options()?)
            .with_context(|| format!("loading the dataset {}", s.dataset.display()))?;
        let all: Vec<usize> = (0..dataset.len()).collect();
        dataset
            .load_images(&all)
            .with_context(|| format!("reading the images of {}", s.dataset.display()))?;
    }
    Ok(())
}

/// `OUT/geometry`.
pub(crate) fn geometry_dir(s: &Plan) -> PathBuf {
    s.out_dir.join("geometry")
}

/// `OUT/features/bundle`.
fn bundle_dir(s: &Plan) -> PathBuf {
    s.out_dir.join("features").join("bundle")
}

/// Whether the geometry stage has finished: its scene and its last kept checkpoint are there.
pub(crate) fn geometry_done(s: &Plan) -> bool {
    let dir = geometry_dir(s);
    dir.join("point_cloud.ply").is_file()
        && dir
            .join(format!("chkpnt_{}.safetensors", s.geometry_iterations))
            .is_file()
}

/// Whether the feature stage has finished: the scene bundle is there.
pub(crate) fn features_done(s: &Plan) -> bool {
    bundle_dir(s).join("bundle.json").is_file()
}

/// The iterations the geometry stage has done: those of its latest checkpoint (0 without one).
pub(crate) fn geometry_progress(s: &Plan) -> u64 {
    latest_geometry_checkpoint(&geometry_dir(s))
        .and_then(|p| checkpoint_step(&p).ok())
        .unwrap_or(0)
}

/// Whether the stylize and eval stages have left their records (a rerun may still redo them
/// when their inputs changed).
pub(crate) fn outputs_done(s: &Plan) -> bool {
    ["stylize", "eval"]
        .iter()
        .all(|stage| record::path(&s.out_dir, stage).is_file())
}

fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(T, f64)> {
    let t = Instant::now();
    let v = f()?;
    Ok((v, t.elapsed().as_secs_f64()))
}

/// The checkpoint of a geometry run directory with the most iterations: a kept
/// `chkpnt_N.safetensors` or the periodic and stop `checkpoint.safetensors` (unreadable files
/// are passed over).
fn latest_geometry_checkpoint(dir: &Path) -> Option<PathBuf> {
    let entries = std::fs::read_dir(dir).ok()?;
    entries
        .filter_map(|e| e.ok())
        .filter(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name == train::driver::CHECKPOINT_FILE
                || (name.starts_with("chkpnt_") && name.ends_with(".safetensors"))
        })
        .filter_map(|e| Some((checkpoint_step(&e.path()).ok()?, e.path())))
        .max_by_key(|(step, _)| *step)
        .map(|(_, p)| p)
}

/// The geometry configuration of a run: the 3DGS schedule scaled to `geometry_iterations`
/// ([`GeometryConfig::scaled_to`](train::GeometryConfig::scaled_to), the rule of
/// `fit-geometry --iterations`), on the plan's background, evaluated and saved at the end, with
/// kept checkpoints half-way and at the end (the last one marks the stage as done) and a
/// periodic one every quarter.
pub fn geometry_config(s: &Plan) -> FitGeometryConfig {
    let n = s.geometry_iterations.max(1);
    let mut c = FitGeometryConfig {
        geometry: GeometryConfig::default().scaled_to(n),
        ..FitGeometryConfig::default()
    };
    c.dataset.downscale = s.downscale;
    let g = &mut c.geometry;
    g.background = s.background;
    if let Some(n) = s.random_init_points {
        g.random_init_points = n;
    }
    g.test_iterations = vec![n];
    g.save_iterations = vec![n];
    g.checkpoint_iterations = vec![n / 2, n];
    g.checkpoint_interval = (n / 4).max(1);
    g.log_interval = 0;
    c
}

/// The feature configuration of a run.
pub fn feature_config(s: &Plan) -> FitFeaturesConfig {
    let mut c = FitFeaturesConfig {
        background: s.background,
        features: FeatureTrainConfig {
            iterations: s.feature_iterations,
            align_warmup: s.align_warmup,
            variant: s.variant,
            supersample: s.stage3.supersample,
            lambda_content: s.stage3.content_style_weight,
            lambda_style: s.stage3.content_style_weight,
            checkpoint_interval: (s.feature_iterations / 6).max(1),
            log_interval: 0,
            // A run evaluates its result with `eval`; no loss curve.
            eval_pairs: 0,
            ..FeatureTrainConfig::default()
        },
        ..FitFeaturesConfig::default()
    };
    c.dataset.downscale = s.downscale;
    c
}

/// The settings of the stylize stage of a run, writing into `out_dir`: the plan's paintings at
/// full strength, a GIF per painting and a contact sheet of six views.
pub fn stylize_settings(s: &Plan, out_dir: PathBuf) -> StylizeSettings {
    StylizeSettings {
        styles: s.styles.clone(),
        weights: None,
        alpha: 1.0,
        preserve_colour: false,
        style_side: STYLE_SIDE,
        out_dir,
        gif: true,
        mp4: false,
        fps: 12.0,
        sheet_views: 6,
        tile_budget: runtime::DEFAULT_TILE_BUDGET_BYTES,
        part: Default::default(),
    }
}

/// The settings of the eval stage of a run: those of its stylize stage, with the per-frame 2D
/// baseline, its frames written under `frames_out` with the comparison sheet.
pub fn eval_settings(st: &StylizeSettings, frames_out: PathBuf) -> EvalSettings {
    EvalSettings {
        styles: st.styles.clone(),
        weights: None,
        alpha: st.alpha,
        preserve_colour: st.preserve_colour,
        style_side: st.style_side,
        warp: WarpOptions::default(),
        tile_budget: st.tile_budget,
        baseline: true,
        frames_out: Some(frames_out),
        measure_with: None,
        part: Default::default(),
    }
}

/// Runs the plan's stages. A stop request ends a training stage early with a checkpoint and
/// fails with [`Error::Interrupted`] (run the same command again to continue); every stage
/// reports to the control's sink.
pub fn execute(s: &Plan, control: &Control) -> Result<RunReport> {
    check_inputs(s)?;
    std::fs::create_dir_all(&s.out_dir)
        .with_context(|| format!("creating {}", s.out_dir.display()))?;
    let mut seconds = Vec::new();
    let scene = s.dataset.clone();

    // 1. weights
    let weights = match &s.networks {
        Networks::File(w) => w.clone(),
        Networks::Import { encoder, decoder } => {
            let w = s.out_dir.join("weights.safetensors");
            if w.is_file() {
                seconds.push(("weights", None));
            } else {
                let ((), t) = timed(|| {
                    let mut nets = weights::import(Some(encoder), decoder.as_deref())?;
                    if decoder.is_none() {
                        nets.decoder = Some(weights::built_in_decoder()?);
                    }
                    nets.save(&w)
                        .with_context(|| format!("writing {}", w.display()))
                })?;
                seconds.push(("weights", Some(t)));
            }
            w
        }
    };

    // 2. geometry
    let geo_dir = geometry_dir(s);
    let ply = geo_dir.join("point_cloud.ply");
    let mut geometry_psnr = None;
    if geometry_done(s) {
        seconds.push(("geometry", None));
    } else {
        std::fs::create_dir_all(&geo_dir)
            .with_context(|| format!("creating {}", geo_dir.display()))?;
        let cfg_path = config::save(&geometry_config(s), &geo_dir)?;
        let settings = FitSettings {
            dataset: scene.clone(),
            out_dir: geo_dir.clone(),
            config: Some(cfg_path),
            resume: latest_geometry_checkpoint(&geo_dir),
            overrides: GeometryOverrides::default(),
        };
        let (r, t) = timed(|| crate::fit_geometry::run(&settings, control))?;
        if r.run.interrupted {
            return Err(Error::Interrupted(format!(
                "stopped during the geometry stage at iteration {}; run the same command again to continue",
                r.run.step
            )));
        }
        geometry_psnr = r.evaluations.last().map(|e| e.psnr);
        seconds.push(("geometry", Some(t)));
    }

    // 3. features
    let feat_dir = s.out_dir.join("features");
    let bundle_dir = bundle_dir(s);
    if features_done(s) {
        seconds.push(("features", None));
    } else {
        std::fs::create_dir_all(&feat_dir)
            .with_context(|| format!("creating {}", feat_dir.display()))?;
        let cfg_path = config::save(&feature_config(s), &feat_dir)?;
        let checkpoint = feat_dir.join(train::features::FEATURE_CHECKPOINT_FILE);
        let settings = FitFeaturesSettings {
            geometry: ply.clone(),
            dataset: scene.clone(),
            styles: s.training_styles.clone(),
            eval_styles: Vec::new(),
            networks: NetworkFiles {
                weights: Some(weights.clone()),
                encoder: None,
                decoder: s.decoder.clone(),
            },
            out_dir: feat_dir.clone(),
            config: Some(cfg_path),
            resume: checkpoint.is_file().then_some(checkpoint),
            overrides: FeatureOverrides::default(),
            encoding_cache: true,
        };
        let (r, t) = timed(|| crate::fit_features::run(&settings, control))?;
        if r.run.interrupted {
            return Err(Error::Interrupted(format!(
                "stopped during the feature stage at iteration {}; run the same command again to continue",
                r.run.step
            )));
        }
        seconds.push(("features", Some(t)));
    }

    // 4. stylize along the plan's cameras
    let bundle = crate::open::load_bundle(&bundle_dir, Some(s.variant), s.decoder.as_deref())?;
    let known = KnownCameras::from_bundle(&bundle, &bundle_dir.display().to_string());
    let request = CameraRequest {
        frames: Some(s.frames),
        ..CameraRequest::new(s.cameras)
    };
    let cams = crate::cameras::select(&request, &known, &bundle.scene)?;
    let settings = stylize_settings(s, s.out_dir.join("stylized"));
    let inputs = record::Inputs::new(s, &bundle_dir, &settings)?;
    let stylize_record = record::path(&s.out_dir, "stylize");
    let stylized = match record::finished::<record::Stylized>(&stylize_record, &inputs) {
        Some(done) => {
            seconds.push(("stylize", None));
            done.output()
        }
        None => {
            record::forget(&stylize_record)?;
            let (out, t) = timed(|| stylize::run(&bundle, &cams, &settings, control.sink))?;
            record::write(&stylize_record, &inputs, &record::Stylized::of(&out))?;
            seconds.push(("stylize", Some(t)));
            out
        }
    };

    // 5. evaluate the same frames
    let eval_json = s.out_dir.join("eval.json");
    let eval_record = record::path(&s.out_dir, "eval");
    let finished_eval = record::finished::<record::Evaluated>(&eval_record, &inputs)
        .and_then(|_| record::read_eval_report(&eval_json).ok());
    let eval = match finished_eval {
        Some(report) => {
            seconds.push(("eval", None));
            report
        }
        None => {
            record::forget(&eval_record)?;
            let eval_settings = eval_settings(&settings, s.out_dir.join("eval"));
            let (eval, t) = timed(|| {
                crate::eval::evaluate_bundle(
                    &bundle,
                    &bundle_dir.display().to_string(),
                    &cams,
                    &eval_settings,
                    control.sink,
                )
            })?;
            crate::eval::write_report(&eval_json, &eval)?;
            let evaluated = record::Evaluated {
                report: eval_json.clone(),
                comparison: eval.comparison.clone(),
            };
            record::write(&eval_record, &inputs, &evaluated)?;
            seconds.push(("eval", Some(t)));
            eval
        }
    };

    Ok(RunReport {
        geometry_psnr,
        gaussians: bundle.scene.len(),
        stylized,
        eval,
        eval_json,
        bundle: bundle_dir,
        seconds,
        estimated: Vec::new(),
    })
}

/// The records of the finished stylize and eval stages: `OUT/{stage}.done.json`, written
/// atomically when the stage has written all its outputs and removed before it runs again.
///
/// A record holds the stage's [`Inputs`] (the files of the scene bundle and the decoder, the
/// style images, each with its size and modification time, and the settings) and what the
/// stage wrote. A rerun skips the stage when its record exists, its inputs equal those of the
/// run and every recorded output is still there; otherwise the stage runs again.
mod record {
    use std::path::{Path, PathBuf};
    use std::time::UNIX_EPOCH;

    use serde::de::DeserializeOwned;
    use serde::{Deserialize, Serialize};
    use train::Variant;

    use super::Plan;
    use crate::error::{Context, Result};
    use crate::eval::EvalReport;
    use crate::stylize::{StylizeOutput, StylizeSettings};
    use runtime::StageSeconds;

    /// `OUT/{stage}.done.json`.
    pub fn path(out_dir: &Path, stage: &str) -> PathBuf {
        out_dir.join(format!("{stage}.done.json"))
    }

    /// A file a stage read: its path, size and modification time.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct FileStamp {
        path: PathBuf,
        bytes: u64,
        /// Modification time since the Unix epoch: seconds and nanoseconds.
        modified: (u64, u32),
    }

    impl FileStamp {
        fn of(path: &Path) -> Result<FileStamp> {
            let meta =
                std::fs::metadata(path).with_context(|| format!("reading {}", path.display()))?;
            let modified = meta
                .modified()
                .ok()
                .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
                .map_or((0, 0), |d| (d.as_secs(), d.subsec_nanos()));
            Ok(FileStamp {
                path: path.to_path_buf(),
                bytes: meta.len(),
                modified,
            })
        }
    }

    /// What the stylize and eval stages are made from.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct Inputs {
        /// The files of the scene bundle, sorted by name.
        bundle: Vec<FileStamp>,
        /// The decoder used instead of the bundle's.
        decoder: Option<FileStamp>,
        variant: Variant,
        /// The style images, in order.
        styles: Vec<FileStamp>,
        frames: usize,
        cameras: String,
        style_side: u32,
        alpha: f64,
        preserve_colour: bool,
        gif: bool,
        fps: f64,
        sheet_views: usize,
    }

    impl Inputs {
        /// The inputs of a run's stylize and eval stages.
        pub fn new(s: &Plan, bundle_dir: &Path, st: &StylizeSettings) -> Result<Inputs> {
            let mut bundle = Vec::new();
            for e in std::fs::read_dir(bundle_dir)
                .with_context(|| format!("reading {}", bundle_dir.display()))?
            {
                let p = e
                    .with_context(|| format!("reading {}", bundle_dir.display()))?
                    .path();
                if p.is_file() {
                    bundle.push(FileStamp::of(&p)?);
                }
            }
            bundle.sort_by(|a, b| a.path.cmp(&b.path));
            Ok(Inputs {
                bundle,
                decoder: s.decoder.as_deref().map(FileStamp::of).transpose()?,
                variant: s.variant,
                styles: st
                    .styles
                    .iter()
                    .map(|p| FileStamp::of(p))
                    .collect::<Result<_>>()?,
                frames: s.frames,
                cameras: s.cameras.as_str().to_string(),
                style_side: st.style_side,
                alpha: st.alpha,
                preserve_colour: st.preserve_colour,
                gif: st.gif,
                fps: st.fps,
                sheet_views: st.sheet_views,
            })
        }
    }

    /// What a stage wrote, as its record keeps it.
    pub trait Outputs {
        /// The files that must still be there for the stage to count as done.
        fn files(&self) -> Vec<&Path>;
    }

    #[derive(Serialize, Deserialize)]
    struct Record<T> {
        inputs: Inputs,
        outputs: T,
    }

    /// The outputs of the stage recorded in `record` when it was made from `inputs` and all its
    /// files are still there (`None` otherwise, an unreadable record included).
    pub fn finished<T: Outputs + DeserializeOwned>(record: &Path, inputs: &Inputs) -> Option<T> {
        let bytes = std::fs::read(record).ok()?;
        let r: Record<T> = serde_json::from_slice(&bytes).ok()?;
        (r.inputs == *inputs && r.outputs.files().iter().all(|f| f.is_file())).then_some(r.outputs)
    }

    /// Removes a stage's record before the stage runs, so that a run stopped half-way is never
    /// taken for a finished one.
    pub fn forget(record: &Path) -> Result<()> {
        match std::fs::remove_file(record) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(e).with_context(|| format!("removing {}", record.display()))
            }
            _ => Ok(()),
        }
    }

    /// Writes a stage's record (atomically), once its outputs are all written.
    pub fn write<T: Serialize>(record: &Path, inputs: &Inputs, outputs: &T) -> Result<()> {
        let json = serde_json::to_vec_pretty(&Record {
            inputs: inputs.clone(),
            outputs,
        })
        .context("serialising a stage record")?;
        base::write_atomic(record, &json).with_context(|| format!("writing {}", record.display()))
    }

    /// What the stylize stage wrote ([`StylizeOutput`] without the MP4s a run never makes).
    #[derive(Serialize, Deserialize)]
    pub struct Stylized {
        outputs: Vec<(String, Vec<PathBuf>)>,
        gifs: Vec<PathBuf>,
        contact_sheet: Option<PathBuf>,
        /// Mean seconds per view: raster, lift and transform, decode.
        seconds: [f64; 3],
    }

    impl Stylized {
        pub fn of(o: &StylizeOutput) -> Stylized {
            Stylized {
                outputs: o.outputs.clone(),
                gifs: o.gifs.clone(),
                contact_sheet: o.contact_sheet.clone(),
                seconds: [o.seconds.raster, o.seconds.lift_transform, o.seconds.decode],
            }
        }

        pub fn output(self) -> StylizeOutput {
            let [raster, lift_transform, decode] = self.seconds;
            StylizeOutput {
                outputs: self.outputs,
                gifs: self.gifs,
                mp4s: Vec::new(),
                contact_sheet: self.contact_sheet,
                manifest: None,
                decoded: 0,
                seconds: StageSeconds {
                    raster,
                    lift_transform,
                    decode,
                },
            }
        }
    }

    impl Outputs for Stylized {
        fn files(&self) -> Vec<&Path> {
            self.outputs
                .iter()
                .flat_map(|(_, frames)| frames)
                .chain(&self.gifs)
                .chain(&self.contact_sheet)
                .map(PathBuf::as_path)
                .collect()
        }
    }

    /// What the eval stage wrote: its report and its comparison sheet.
    #[derive(Serialize, Deserialize)]
    pub struct Evaluated {
        pub report: PathBuf,
        #[serde(default)]
        pub comparison: Option<PathBuf>,
    }

    impl Outputs for Evaluated {
        fn files(&self) -> Vec<&Path> {
            std::iter::once(&self.report)
                .chain(&self.comparison)
                .map(PathBuf::as_path)
                .collect()
        }
    }

    /// Reads an evaluation report written by [`crate::eval::write_report`].
    pub fn read_eval_report(path: &Path) -> Result<EvalReport> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        serde_json::from_slice(&bytes)
            .with_context(|| format!("{}: not an evaluation report", path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_take_the_plural_unless_one() {
        assert_eq!(count(1, "painting"), "1 painting");
        assert_eq!(count(0, "frame"), "0 frames");
        assert_eq!(count(24, "frame"), "24 frames");
    }

    #[test]
    fn latest_checkpoint_is_the_highest_iteration() {
        let dir = std::env::temp_dir().join(format!("dsgs-demo-ck-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // A safetensors header holding only the step.
        let header = |step: u64| {
            let json = format!("{{\"__metadata__\":{{\"step\":\"{step}\"}}}}");
            [&(json.len() as u64).to_le_bytes()[..], json.as_bytes()].concat()
        };
        for n in [500, 1000, 90] {
            std::fs::write(dir.join(format!("chkpnt_{n}.safetensors")), header(n)).unwrap();
        }
        std::fs::write(dir.join("chkpnt_x.safetensors"), b"").unwrap();
        std::fs::write(dir.join("checkpoint.safetensors"), header(750)).unwrap();
        assert_eq!(
            latest_geometry_checkpoint(&dir),
            Some(dir.join("chkpnt_1000.safetensors"))
        );
        // A stop checkpoint past the kept ones is the one to resume.
        std::fs::write(dir.join("checkpoint.safetensors"), header(1200)).unwrap();
        assert_eq!(
            latest_geometry_checkpoint(&dir),
            Some(dir.join("checkpoint.safetensors"))
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
