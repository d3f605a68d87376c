//! `dsgs demo`: the whole pipeline on the lego scene at low resolution, in one command: a
//! [`Plan`] for the stages' runner of `dsgs run` ([`crate::run`]), which
//! checks every input first, skips the stages already done and resumes an interrupted one.
//!
//! 1. `weights.safetensors`: the networks of `--networks` ([`Pair`]; by default the compressed
//!    relu4_1 encoder of `SHARED/weights/compressed-16x-relu4_1/` with the built-in decoder), or
//!    `--weights FILE`.
//! 2. `geometry/`: `dsgs fit-geometry` on `SHARED/data/scenes/lego` at 1/8 scale (100 x 100),
//!    white background, 1,000 iterations of the 3DGS schedule scaled to that length, from
//!    20,000 random points.
//! 3. `features/`: `dsgs fit-features` on that geometry, styles from
//!    `SHARED/data/styles/small-set`: 1,800 iterations; with the relu4_1 pair all of them
//!    alignment-only, with the WCT pair the first 1,500 alignment-only and the last 300 with
//!    the full loss (alignment, content and style) ([`crate::run::Stage3Choice`]).
//! 4. `stylized/`: `dsgs stylize` of an orbit with styles never used in training: PNG frames, a
//!    GIF per style and `contact_sheet.png` (styles x views).
//! 5. `eval.json`: `dsgs eval` of the same orbit.
//!
//! `SHARED` is `--shared`, else the `DSGS_SHARED` environment variable, else `../shared`.

use std::path::{Path, PathBuf};

use crate::cli::{at_least_one, positive, variant};
use crate::error::Result;
use crate::run::{Networks, Plan, RunReport, Stage3Choice, TRAINING_STYLES};
use crate::weights::Pair;
use crate::Control;
use train::Variant;

use crate::cameras::CameraSource;

/// The scene of the demo, under `SHARED`.
pub const SCENE: &str = "data/scenes/lego";
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
  weights/compressed-16x-relu4_1/4SE.pth
                                     the 16x-compressed normalised VGG-19 encoder to relu4_1
                                     (the default --networks relu4_1; its decoder is built in)
  weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth
  weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth
                                     the normalised VGG-19 encoder to relu3_1 and its inverting
                                     decoder (--networks wct-relu3_1: the WCT feature invertors
                                     of the universal style transfer code); or --weights
                                     NETS.safetensors made by `dsgs weights import`";

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
    /// The pair of networks by name (`--networks`).
    #[arg(long, default_value = "relu4_1", value_parser = crate::cli::one_of::<Pair>(
        Pair::NAMES.iter().copied()),
        help = crate::cli::NETWORKS_HELP)]
    pub networks: Pair,
    /// Canonical weights to use instead of the named pair.
    #[arg(
        long,
        help = "Canonical network weights (.safetensors, encoder and decoder) instead of \
                --networks [default: the --networks pair]"
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

/// The demo's plan: the lego scene at `1 / downscale`, white, from 20,000 random points, the
/// `--networks` pair (or `--weights`), the small set of training paintings and an
/// orbit of `frames` views.
pub fn plan(s: &DemoSettings) -> Plan {
    Plan {
        dataset: s.shared.join(SCENE),
        dataset_marker: Some(s.shared.join(SCENE).join("transforms_train.json")),
        background: [1.0; 3],
        downscale: s.downscale,
        random_init_points: Some(20_000),
        out_dir: s.out_dir.clone(),
        networks: Networks::given_or_shared(s.weights.as_ref(), s.networks, &s.shared),
        stage3: Stage3Choice::of(s.weights.as_ref(), s.networks),
        decoder: s.decoder.clone(),
        variant: s.variant,
        geometry_iterations: s.geometry_iterations,
        align_warmup: s.align_warmup,
        feature_iterations: s.feature_iterations,
        training_styles: vec![s.shared.join(TRAINING_STYLES)],
        styles: styles_or_default(&s.shared, &s.styles),
        frames: s.frames,
        cameras: CameraSource::Orbit,
        sources: SOURCES.to_string(),
    }
}

/// Runs the demo ([`crate::run::execute`] of its [`plan`]). A stop request ends a training
/// stage early with a checkpoint and fails with [`Error::Interrupted`](crate::Error) (run the
/// demo again to continue).
pub fn run(s: &DemoSettings, control: &Control) -> Result<RunReport> {
    crate::run::execute(&plan(s), control)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::{check_inputs, feature_config, geometry_config};
    use train::GeometryConfig;

    fn settings(shared: &Path) -> DemoSettings {
        DemoSettings {
            shared: shared.to_path_buf(),
            out_dir: shared.join("out"),
            networks: Pair::Relu41,
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
        assert_eq!(feature_config(&plan(&s)).features.iterations, 1800);
        assert_eq!(feature_config(&plan(&s)).features.align_warmup, 1500);
        let short = DemoSettings {
            feature_iterations: 1000,
            ..s
        };
        let err = check_inputs(&plan(&short)).unwrap_err().to_string();
        assert!(
            err.contains("--align-warmup 1500") && err.contains("1000"),
            "{err}"
        );
    }

    #[test]
    fn the_networks_choose_stage_3s_render_and_losses() {
        let s = settings(Path::new("x"));
        let relu41 = feature_config(&plan(&s)).features;
        assert_eq!(relu41.supersample, 8);
        assert_eq!((relu41.lambda_content, relu41.lambda_style), (0.0, 0.0));
        let wct = feature_config(&plan(&DemoSettings {
            networks: Pair::WctRelu31,
            ..s.clone()
        }))
        .features;
        assert_eq!(wct.supersample, 1);
        assert_eq!((wct.lambda_content, wct.lambda_style), (1.0, 1.0));
        // Networks from a file: the direct render and the paper's weights.
        let file = plan(&DemoSettings {
            weights: Some(PathBuf::from("nets.safetensors")),
            ..s
        });
        assert_eq!(file.networks, Networks::File("nets.safetensors".into()));
        let f = feature_config(&file).features;
        assert_eq!(
            (f.supersample, f.lambda_content, f.lambda_style),
            (1, 1.0, 1.0)
        );
    }

    #[test]
    fn missing_inputs_are_named_with_their_sources() {
        let dir = std::env::temp_dir().join(format!("dsgs-demo-missing-{}", std::process::id()));
        let err = check_inputs(&plan(&settings(&dir)))
            .unwrap_err()
            .to_string();
        assert!(err.contains("transforms_train.json"), "{err}");
        assert!(err.contains("compressed-16x-relu4_1/4SE.pth"), "{err}");
        assert!(err.contains("mondrian.jpg"), "{err}");
        assert!(err.contains("nerf_synthetic"), "{err}");
    }

    #[test]
    fn the_geometry_schedule_is_the_default_one_scaled_to_the_run() {
        let s = settings(Path::new("x"));
        let c = geometry_config(&plan(&s));
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
}
