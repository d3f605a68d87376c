//! `dsgs demo`: the whole pipeline on the lego scene at low resolution, in one command.
//!
//! Stages, each in its own folder of the output directory and each skipped when its result is
//! already there (so an interrupted demo continues where it stopped):
//!
//! 1. `weights.safetensors`: the relu3_1 encoder and its decoder, imported from the PyTorch
//!    checkpoints in `SHARED/weights/wct-relu1_1-3_1/` (or `--weights FILE`).
//! 2. `geometry/`: `dsgs fit-geometry` on `SHARED/data/scenes/lego` at 1/8 scale (100 x 100),
//!    white background, 1,000 iterations with the learning-rate schedule and densification
//!    compressed to that length.
//! 3. `features/`: `dsgs fit-features` on that geometry, styles from
//!    `SHARED/data/styles/small-set`: 1,500 cheap alignment-only iterations, then 300 with the
//!    full loss (alignment, content and style).
//! 4. `stylized/`: `dsgs stylize` of an orbit with styles never used in training: PNG frames, a
//!    GIF per style and `contact_sheet.png` (styles x views).
//! 5. `eval.json`: `dsgs eval` of the same orbit (short- and long-range consistency, style and
//!    content losses, seconds per view).
//!
//! Every stage writes its effective configuration beside its outputs. `SHARED` is `--shared`,
//! else the `DSGS_SHARED` environment variable, else `../shared`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::error::{bail, Context, Error, Result};
use crate::Control;
use train::checkpoint::checkpoint_step;
use train::{FeatureTrainConfig, Variant};

use crate::cameras::{CameraRequest, CameraSource, KnownCameras};
use crate::consistency::WarpOptions;
use crate::eval::{EvalReport, EvalSettings};
use crate::fit_features::{FeatureOverrides, FitFeaturesConfig, FitFeaturesSettings};
use crate::fit_geometry::{FitGeometryConfig, FitSettings, GeometryOverrides};
use crate::pretrain_decoder::NetworkFiles;
use crate::stylize::{StylizeOutput, StylizeSettings};
use crate::{config, stylize, weights};

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

/// Settings of a demo run.
#[derive(Clone, Debug)]
pub struct DemoSettings {
    /// The shared data folder holding the scene, styles and weights (`--shared`, else the
    /// `DSGS_SHARED` environment variable, else `../shared`).
    pub shared: PathBuf,
    /// Output directory of the stages (`--output`); a rerun skips the stages whose results are
    /// there.
    pub out_dir: PathBuf,
    /// Canonical weights to use instead of importing the shared checkpoints.
    pub weights: Option<PathBuf>,
    /// A decoder to use instead of the one in the weights (e.g. a fine-tuned fullres decoder).
    pub decoder: Option<PathBuf>,
    /// Network variant (`--variant`).
    pub variant: Variant,
    /// Downscale factor of the 800 x 800 lego images.
    pub downscale: f64,
    /// Iterations of the geometry stage (`--geometry-iterations`).
    pub geometry_iterations: u64,
    /// Alignment-only feature iterations before the full loss.
    pub align_warmup: u64,
    /// Feature iterations with the full loss, after the warm-up.
    pub feature_iterations: u64,
    /// Stylization styles (default: [`STYLES`] under `SHARED/data/styles`).
    pub styles: Vec<PathBuf>,
    /// Frames of the orbit.
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
    /// Seconds of each stage run now (`None`: skipped, its output was already there).
    pub seconds: Vec<(&'static str, Option<f64>)>,
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

/// Checks that every input exists before anything runs, naming what is missing.
pub fn check_inputs(s: &DemoSettings) -> Result<()> {
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
    Ok(())
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

/// The geometry configuration of the demo: 3DGS defaults with the schedule compressed to
/// `iterations` (position learning rate decaying over the run, densification from a quarter to
/// the end every `iterations / 10` steps, no opacity reset, an SH degree every quarter).
pub fn geometry_config(s: &DemoSettings) -> FitGeometryConfig {
    let mut c = FitGeometryConfig::default();
    c.dataset.downscale = s.downscale;
    let g = &mut c.geometry;
    let n = s.geometry_iterations.max(1);
    g.iterations = n;
    g.background = [1.0, 1.0, 1.0];
    g.random_init_points = 20_000;
    g.sh_degree_interval = (n / 4).max(1);
    g.learning_rates.position_lr_max_steps = n;
    g.densify.densify_from_iter = n / 4;
    g.densify.densify_until_iter = n;
    g.densify.densification_interval = (n / 10).max(1);
    g.densify.opacity_reset_interval = n + 1;
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
            iterations: s.align_warmup + s.feature_iterations,
            align_warmup: s.align_warmup,
            variant: s.variant,
            checkpoint_interval: ((s.align_warmup + s.feature_iterations) / 6).max(1),
            log_interval: 0,
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
    let geo_dir = s.out_dir.join("geometry");
    let ply = geo_dir.join("point_cloud.ply");
    let mut geometry_psnr = None;
    let finished = geo_dir.join(format!("chkpnt_{}.safetensors", s.geometry_iterations));
    if ply.is_file() && finished.is_file() {
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
    let bundle_dir = feat_dir.join("bundle");
    if bundle_dir.join("bundle.json").is_file() {
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
            networks: NetworkFiles {
                weights: Some(weights.clone()),
                encoder: None,
                decoder: s.decoder.clone(),
            },
            out_dir: feat_dir.clone(),
            config: Some(cfg_path),
            resume: checkpoint.is_file().then_some(checkpoint),
            overrides: FeatureOverrides::default(),
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
    let bundle = stylize::load_bundle(&bundle_dir, Some(s.variant), s.decoder.as_deref())?;
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
        style_side: 256,
        out_dir: s.out_dir.join("stylized"),
        gif: true,
        mp4: false,
        fps: 12.0,
        sheet_views: 6,
    };
    let (stylized, t) = timed(|| stylize::run(&bundle, &cams, &settings, control.sink))?;
    seconds.push(("stylize", Some(t)));

    // 5. evaluate the same orbit
    let eval_settings = EvalSettings {
        styles: s.styles.clone(),
        weights: None,
        alpha: 1.0,
        preserve_colour: false,
        style_side: 256,
        warp: WarpOptions::default(),
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
    let eval_json = s.out_dir.join("eval.json");
    crate::eval::write_report(&eval_json, &eval)?;
    seconds.push(("eval", Some(t)));

    Ok(DemoReport {
        geometry_psnr,
        gaussians: bundle.scene.len(),
        stylized,
        eval,
        eval_json,
        seconds,
    })
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
            feature_iterations: 300,
            styles: styles_or_default(shared, &[]),
            frames: 24,
        }
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
    fn the_geometry_schedule_is_compressed_to_the_run() {
        let c = geometry_config(&settings(Path::new("x")));
        let g = &c.geometry;
        assert_eq!(g.iterations, 1000);
        assert_eq!(g.learning_rates.position_lr_max_steps, 1000);
        assert_eq!(g.densify.densify_from_iter, 250);
        assert_eq!(g.densify.densify_until_iter, 1000);
        assert!(g.densify.opacity_reset_interval > g.iterations);
        assert_eq!(g.checkpoint_iterations, [500, 1000]);
        assert_eq!(c.dataset.downscale, 8.0);
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
