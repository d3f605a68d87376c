//! `dsgs demo`: the whole pipeline on the lego scene at low resolution, in one command.
//!
//! Before anything runs, every input is checked ([`check_inputs`]): missing files are listed
//! with where to get them, and every image a stage will read is decoded, so a bad style image
//! fails at once rather than after the training stages.
//!
//! Stages, each in its own folder of the output directory and each skipped when its result is
//! already there (so an interrupted demo continues where it stopped, and a finished one reruns
//! in seconds):
//!
//! 1. `weights.safetensors`: the relu3_1 encoder and its decoder, imported from the PyTorch
//!    checkpoints in `SHARED/weights/wct-relu1_1-3_1/` (or `--weights FILE`).
//! 2. `geometry/`: `dsgs fit-geometry` on `SHARED/data/scenes/lego` at 1/8 scale (100 x 100),
//!    white background, 1,000 iterations of the 3DGS schedule scaled to that length
//!    ([`geometry_config`]).
//! 3. `features/`: `dsgs fit-features` on that geometry, styles from
//!    `SHARED/data/styles/small-set`: 1,800 iterations, the first 1,500 cheap alignment-only
//!    ones, the last 300 with the full loss (alignment, content and style).
//! 4. `stylized/`: `dsgs stylize` of an orbit with styles never used in training: PNG frames, a
//!    GIF per style and `contact_sheet.png` (styles x views).
//! 5. `eval.json`: `dsgs eval` of the same orbit (short- and long-range consistency, style and
//!    content losses, seconds per view).
//!
//! Stages 1 to 3 count as done when their final outputs are there (the geometry's scene and its
//! last checkpoint, the feature stage's bundle); an unfinished training stage resumes from its
//! checkpoint. Stages 4 and 5 write a record `OUT/stylize.done.json` or `OUT/eval.done.json`
//! (atomically, after all their outputs) of what they were made from: the files of the scene
//! bundle, the decoder and the style images (each path with its size and modification time), the
//! variant, the number of frames and the rendering settings. A rerun skips such a stage only when
//! its record matches the run and every output it lists is still there; otherwise the stage runs
//! again (e.g. after `--style` changes, or when the features were trained again).
//!
//! Every stage writes its effective configuration beside its outputs. `SHARED` is `--shared`,
//! else the `DSGS_SHARED` environment variable, else `../shared`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::cli::{at_least_one, positive, variant};
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
use crate::{config, image_io, stylize, weights};

/// The scene of the demo, under `SHARED`.
pub const SCENE: &str = "data/scenes/lego";
/// The encoder checkpoint, under `SHARED`.
pub const ENCODER: &str = "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth";
/// The decoder checkpoint, under `SHARED`.
pub const DECODER: &str = "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth";
/// The training styles, under `SHARED`.
pub const TRAINING_STYLES: &str = "data/styles/small-set";
/// The default stylization styles (never seen in training), under `SHARED/data/styles`.
pub const STYLES: [&str; 4] = [
    "woman_with_hat_matisse.jpg",
    "the_resevoir_at_poitiers.jpg",
    "en_campo_gris.jpg",
    "mondrian.jpg",
];

/// Where the public files come from, for the error when they are missing.
const SOURCES: &str = "\
the demo needs, under the shared folder (--shared, DSGS_SHARED or ../shared):
  data/scenes/lego/                  NeRF-synthetic lego: transforms_train.json and train/*.png
                                     (the nerf_synthetic archive of the NeRF authors)
  data/styles/small-set/*.jpg        style images for training (any paintings will do)
  data/styles/<name>                 the stylization styles (or give --style FILE ...)
  weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth
  weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth
                                     the normalised VGG-19 encoder to relu3_1 and its inverting
                                     decoder (the WCT feature invertors of the universal style
                                     transfer code; or give --weights NETS.safetensors made by
                                     `dsgs weights import` from the public pytorch-AdaIN
                                     vgg_normalised.pth and decoder.pth)";

/// Settings of a demo run; as [`clap::Args`], the flags of `dsgs demo` (the styles as given:
/// [`styles_or_default`] adds the default ones).
#[derive(Clone, Debug, clap::Args)]
pub struct DemoSettings {
    /// The shared data folder holding the scene, styles and weights (`--shared`, else the
    /// `DSGS_SHARED` environment variable, else `../shared`).
    #[arg(
        long,
        env = "DSGS_SHARED",
        default_value = "../shared",
        help = "The shared data folder (scenes, styles, weights)"
    )]
    pub shared: PathBuf,
    /// Output directory of the stages (`--output`); a rerun skips the stages whose results are
    /// there.
    #[arg(
        short,
        long = "output",
        value_name = "OUTPUT",
        default_value = "dsgs-demo",
        help = "Output directory; a rerun skips the stages whose results are there and resumes \
                an interrupted one"
    )]
    pub out_dir: PathBuf,
    /// Canonical weights to use instead of importing the shared checkpoints.
    #[arg(
        long,
        help = "Canonical network weights (.safetensors, encoder and decoder) [default: imported \
                from SHARED/weights/wct-relu1_1-3_1]"
    )]
    pub weights: Option<PathBuf>,
    /// A decoder to use instead of the one in the weights (e.g. a fine-tuned fullres decoder).
    #[arg(
        long,
        help = "A decoder (PyTorch checkpoint or .safetensors) replacing the one of the weights, \
                e.g. one fine-tuned by `dsgs pretrain-decoder` for the fullres variant [default: \
                the weights']"
    )]
    pub decoder: Option<PathBuf>,
    /// Network variant (`--variant`).
    #[arg(
        long,
        default_value = "standard",
        value_parser = variant(),
        help = "Network variant (fullres needs a decoder fine-tuned for it to stylize strongly)"
    )]
    pub variant: Variant,
    /// Downscale factor of the 800 x 800 lego images.
    #[arg(
        long,
        default_value_t = 8.0,
        value_parser = positive,
        help = "Downscale factor of the 800x800 lego images (above 0)"
    )]
    pub downscale: f64,
    /// Iterations of the geometry stage (`--geometry-iterations`).
    #[arg(
        long,
        default_value_t = 1000,
        value_parser = at_least_one::<u64>(),
        help = "Geometry iterations (at least 1)"
    )]
    pub geometry_iterations: u64,
    /// Alignment-only feature iterations before the full loss.
    #[arg(
        long,
        default_value_t = 1500,
        help = "Alignment-only feature iterations (cheap) before the full loss"
    )]
    pub align_warmup: u64,
    /// Feature iterations in all, the warm-up included (as `fit-features --iterations` counts
    /// them); those after the warm-up use the full loss.
    #[arg(
        long,
        default_value_t = 1800,
        value_parser = at_least_one::<u64>(),
        help = "Feature iterations in all, the --align-warmup ones included, as fit-features \
                --iterations counts them; those after the warm-up use the full loss (alignment, \
                content, style) (at least 1)"
    )]
    pub feature_iterations: u64,
    /// Stylization styles (default: [`STYLES`] under `SHARED/data/styles`).
    #[arg(
        long = "style",
        help = "Style image; repeat for several [default: four paintings of SHARED/data/styles \
                never used in training]"
    )]
    pub styles: Vec<PathBuf>,
    /// Frames of the orbit.
    #[arg(
        long,
        default_value_t = 24,
        value_parser = at_least_one::<usize>(),
        help = "Frames of the orbit (at least 1)"
    )]
    pub frames: usize,
}

/// What a demo run produced.
#[derive(Clone, Debug)]
pub struct DemoReport {
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
}

/// The summary of a demo: the evaluation table, the geometry's PSNR, the stage times and the
/// outputs (of this run or, for a skipped stage, of the run that made them).
impl std::fmt::Display for DemoReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&crate::eval::table(&self.eval))?;
        if let Some(p) = self.geometry_psnr {
            writeln!(f, "geometry: held-out PSNR {p:.2} dB")?;
        }
        writeln!(f, "{} Gaussians", self.gaussians)?;
        for (stage, t) in &self.seconds {
            match t {
                Some(t) => writeln!(f, "{stage:>9}: {t:.1} s")?,
                None => writeln!(f, "{stage:>9}: done before, skipped")?,
            }
        }
        let s = &self.stylized;
        for p in s.gifs.iter().chain(&s.contact_sheet) {
            writeln!(f, "output {}", p.display())?;
        }
        writeln!(f, "output {}", self.eval_json.display())?;
        writeln!(f, "scene bundle {}", self.bundle.display())?;
        writeln!(
            f,
            "look around it and stylize any view in the browser: dsgs view {}",
            self.bundle.display()
        )
    }
}

/// The stylization styles of a run: `styles`, else the defaults under `shared`.
pub fn styles_or_default(shared: &Path, styles: &[PathBuf]) -> Vec<PathBuf> {
    if styles.is_empty() {
        STYLES
            .iter()
            .map(|s| shared.join("data/styles").join(s))
            .collect()
    } else {
        styles.to_vec()
    }
}

/// The longest side of the style images in the stylize and eval stages.
pub const STYLE_SIDE: u32 = 256;

/// Checks every input before anything runs, so that a bad file fails the demo at once rather
/// than after minutes of training: first that every input exists (naming all that are missing,
/// with where to get them), then that every image a stage will read decodes: the stylization
/// styles always, and the training styles and the scene's images unless the stages reading them
/// (geometry and features) are already done. Errors name the file
/// (`style image PATH: ...`). A warm-up longer than the feature stage is refused first.
pub fn check_inputs(s: &DemoSettings) -> Result<()> {
    if s.align_warmup > s.feature_iterations {
        bail!(
            "--align-warmup {} is longer than --feature-iterations {}, which counts the warm-up \
             too (as fit-features --iterations does)",
            s.align_warmup,
            s.feature_iterations
        );
    }
    let mut missing = Vec::new();
    let mut need = |p: PathBuf| {
        if !p.exists() {
            missing.push(p.display().to_string());
        }
    };
    need(s.shared.join(SCENE).join("transforms_train.json"));
    need(s.shared.join(TRAINING_STYLES));
    match &s.weights {
        Some(w) => need(w.clone()),
        None => {
            need(s.shared.join(ENCODER));
            need(s.shared.join(DECODER));
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
            "missing input files:\n  {}\n{SOURCES}",
            missing.join("\n  ")
        );
    }
    for st in &s.styles {
        image_io::load_style_image(st, STYLE_SIDE)?;
    }
    let features_to_run = !features_done(s);
    if features_to_run {
        let training = collect_images(&[s.shared.join(TRAINING_STYLES)], false)?;
        for st in &training {
            image_io::load_style_image(st, STYLE_SIDE)?;
        }
    }
    if features_to_run || !geometry_done(s) {
        let scene = s.shared.join(SCENE);
        let dataset = Dataset::load(&scene, &geometry_config(s).load_options()?)
            .with_context(|| format!("loading the dataset {}", scene.display()))?;
        let all: Vec<usize> = (0..dataset.len()).collect();
        dataset
            .load_images(&all)
            .with_context(|| format!("reading the images of {}", scene.display()))?;
    }
    Ok(())
}

/// `OUT/geometry`.
fn geometry_dir(s: &DemoSettings) -> PathBuf {
    s.out_dir.join("geometry")
}

/// `OUT/features/bundle`.
fn bundle_dir(s: &DemoSettings) -> PathBuf {
    s.out_dir.join("features").join("bundle")
}

/// Whether the geometry stage has finished: its scene and its last kept checkpoint are there.
fn geometry_done(s: &DemoSettings) -> bool {
    let dir = geometry_dir(s);
    dir.join("point_cloud.ply").is_file()
        && dir
            .join(format!("chkpnt_{}.safetensors", s.geometry_iterations))
            .is_file()
}

/// Whether the feature stage has finished: the scene bundle is there.
fn features_done(s: &DemoSettings) -> bool {
    bundle_dir(s).join("bundle.json").is_file()
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

/// The geometry configuration of the demo: the 3DGS schedule scaled to `geometry_iterations`
/// ([`GeometryConfig::scaled_to`](train::GeometryConfig::scaled_to), the rule of
/// `fit-geometry --iterations`), on a white background from 20,000 random points, evaluated
/// and saved at the end, with kept checkpoints half-way and at the end (the last one marks the
/// stage as done) and a periodic one every quarter.
pub fn geometry_config(s: &DemoSettings) -> FitGeometryConfig {
    let n = s.geometry_iterations.max(1);
    let mut c = FitGeometryConfig {
        geometry: GeometryConfig::default().scaled_to(n),
        ..FitGeometryConfig::default()
    };
    c.dataset.downscale = s.downscale;
    let g = &mut c.geometry;
    g.background = [1.0, 1.0, 1.0];
    g.random_init_points = 20_000;
    g.test_iterations = vec![n];
    g.save_iterations = vec![n];
    g.checkpoint_iterations = vec![n / 2, n];
    g.checkpoint_interval = (n / 4).max(1);
    g.log_interval = 0;
    c
}

/// The feature configuration of the demo.
pub fn feature_config(s: &DemoSettings) -> FitFeaturesConfig {
    let mut c = FitFeaturesConfig {
        background: [1.0, 1.0, 1.0],
        features: FeatureTrainConfig {
            iterations: s.feature_iterations,
            align_warmup: s.align_warmup,
            variant: s.variant,
            checkpoint_interval: (s.feature_iterations / 6).max(1),
            log_interval: 0,
            // The demo evaluates its result with `eval`; no loss curve.
            eval_pairs: 0,
            ..FeatureTrainConfig::default()
        },
        ..FitFeaturesConfig::default()
    };
    c.dataset.downscale = s.downscale;
    c
}

/// Runs the demo. A stop request ends a training stage early with a checkpoint and fails with
/// [`Error::Interrupted`] (run the demo again to continue); every stage reports to the control's
/// sink.
pub fn run(s: &DemoSettings, control: &Control) -> Result<DemoReport> {
    check_inputs(s)?;
    std::fs::create_dir_all(&s.out_dir)
        .with_context(|| format!("creating {}", s.out_dir.display()))?;
    let mut seconds = Vec::new();
    let scene = s.shared.join(SCENE);

    // 1. weights
    let weights = match &s.weights {
        Some(w) => w.clone(),
        None => {
            let w = s.out_dir.join("weights.safetensors");
            if w.is_file() {
                seconds.push(("weights", None));
            } else {
                let ((), t) = timed(|| {
                    let nets = weights::import(
                        Some(&s.shared.join(ENCODER)),
                        Some(&s.shared.join(DECODER)),
                    )?;
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
                "stopped during the geometry stage at iteration {}; run the demo again to continue",
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
            styles: vec![s.shared.join(TRAINING_STYLES)],
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
                "stopped during the feature stage at iteration {}; run the demo again to continue",
                r.run.step
            )));
        }
        seconds.push(("features", Some(t)));
    }

    // 4. stylize an orbit
    let bundle = crate::open::load_bundle(&bundle_dir, Some(s.variant), s.decoder.as_deref())?;
    let known = KnownCameras::from_bundle(&bundle, &bundle_dir.display().to_string());
    let request = CameraRequest {
        frames: Some(s.frames),
        ..CameraRequest::new(CameraSource::Orbit)
    };
    let cams = crate::cameras::select(&request, &known, &bundle.scene)?;
    let settings = StylizeSettings {
        styles: s.styles.clone(),
        weights: None,
        alpha: 1.0,
        preserve_colour: false,
        style_side: STYLE_SIDE,
        out_dir: s.out_dir.join("stylized"),
        gif: true,
        mp4: false,
        fps: 12.0,
        sheet_views: 6,
        tile_budget: runtime::DEFAULT_TILE_BUDGET_BYTES,
        part: Default::default(),
    };
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

    // 5. evaluate the same orbit
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
            let eval_settings = EvalSettings {
                styles: s.styles.clone(),
                weights: None,
                alpha: settings.alpha,
                preserve_colour: settings.preserve_colour,
                style_side: settings.style_side,
                warp: WarpOptions::default(),
                tile_budget: settings.tile_budget,
                baseline: false,
                part: Default::default(),
            };
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
            };
            record::write(&eval_record, &inputs, &evaluated)?;
            seconds.push(("eval", Some(t)));
            eval
        }
    };

    Ok(DemoReport {
        geometry_psnr,
        gaussians: bundle.scene.len(),
        stylized,
        eval,
        eval_json,
        bundle: bundle_dir,
        seconds,
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

    use super::DemoSettings;
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
        style_side: u32,
        alpha: f64,
        preserve_colour: bool,
        gif: bool,
        fps: f64,
        sheet_views: usize,
    }

    impl Inputs {
        /// The inputs of a demo run's stylize and eval stages.
        pub fn new(s: &DemoSettings, bundle_dir: &Path, st: &StylizeSettings) -> Result<Inputs> {
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

    /// What the stylize stage wrote ([`StylizeOutput`] without the MP4s the demo never makes).
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

    /// What the eval stage wrote: its report.
    #[derive(Serialize, Deserialize)]
    pub struct Evaluated {
        pub report: PathBuf,
    }

    impl Outputs for Evaluated {
        fn files(&self) -> Vec<&Path> {
            vec![&self.report]
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

    fn settings(shared: &Path) -> DemoSettings {
        DemoSettings {
            shared: shared.to_path_buf(),
            out_dir: shared.join("out"),
            weights: None,
            decoder: None,
            variant: Variant::Standard,
            downscale: 8.0,
            geometry_iterations: 1000,
            align_warmup: 1500,
            feature_iterations: 1800,
            styles: styles_or_default(shared, &[]),
            frames: 24,
        }
    }

    #[test]
    fn the_feature_iterations_count_the_warm_up() {
        let dir = std::env::temp_dir().join(format!("dsgs-demo-warmup-{}", std::process::id()));
        let s = settings(&dir);
        assert_eq!(feature_config(&s).features.iterations, 1800);
        assert_eq!(feature_config(&s).features.align_warmup, 1500);
        let short = DemoSettings {
            feature_iterations: 1000,
            ..s
        };
        let err = check_inputs(&short).unwrap_err().to_string();
        assert!(
            err.contains("--align-warmup 1500") && err.contains("1000"),
            "{err}"
        );
    }

    #[test]
    fn missing_inputs_are_named_with_their_sources() {
        let dir = std::env::temp_dir().join(format!("dsgs-demo-missing-{}", std::process::id()));
        let err = check_inputs(&settings(&dir)).unwrap_err().to_string();
        assert!(err.contains("transforms_train.json"), "{err}");
        assert!(err.contains("vgg_normalised_conv3_1.pth"), "{err}");
        assert!(err.contains("mondrian.jpg"), "{err}");
        assert!(err.contains("nerf_synthetic"), "{err}");
    }

    #[test]
    fn the_geometry_schedule_is_the_default_one_scaled_to_the_run() {
        let s = settings(Path::new("x"));
        let c = geometry_config(&s);
        let g = &c.geometry;
        let scaled = GeometryConfig::default().scaled_to(s.geometry_iterations);
        assert_eq!(g.iterations, s.geometry_iterations);
        assert_eq!(g.learning_rates, scaled.learning_rates);
        assert_eq!(g.densify, scaled.densify);
        assert_eq!(g.sh_degree_interval, scaled.sh_degree_interval);
        // The last kept checkpoint is the run's end: it marks the stage as done.
        assert_eq!(g.checkpoint_iterations.last(), Some(&g.iterations));
        assert_eq!(c.dataset.downscale, s.downscale);
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
