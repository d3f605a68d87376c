//! The `dsgs` command-line program.
//!
//! Flag conventions, the same in every command:
//! * a flag naming several paths (`--style`, `--content`) takes one path per occurrence and is
//!   repeated (`--style a.jpg --style b.jpg`);
//! * `--weights` always names a network weights file; the weights of a style mixture are `--mix`;
//! * `--help` shows every flag's default (for flags overriding a `--config` file, the
//!   configuration's default, taken from its `Default`) and its allowed values; out-of-range
//!   numbers are refused while the arguments are parsed, naming the flag and the range;
//! * every long-running command takes `--no-progress`.

use std::fmt::Display;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};
use clap::builder::{PossibleValuesParser, StyledStr, TypedValueParser};
use clap::error::{ContextKind, ContextValue, ErrorKind};
use clap::{Args, CommandFactory, FromArgMatches, Parser, Subcommand};
use gaussian::camera::MAX_IMAGE_SIDE;
use glam::DVec3;
use pipeline::bake::{BakeOverrides, BakeSettings};
use pipeline::cameras::{CameraRequest, CameraSource, KnownCameras};
use pipeline::consistency::WarpOptions;
use pipeline::fit_features::{FeatureOverrides, FitFeaturesConfig, FitFeaturesSettings};
use pipeline::fit_geometry::{FitGeometryConfig, FitSettings, GeometryOverrides};
use pipeline::pretrain_decoder::{DecoderOverrides, NetworkFiles, PretrainSettings};
use pipeline::render::{DepthStyle, RenderKind, SceneInput};
use pipeline::shard::{Invocation, Part, Shard};
use pipeline::{Control, RunOutcome};
use terminal::Terminal;
use train::bake::STORED_SH_DEGREE;
use train::{BakeConfig, DecoderMode, DecoderTrainConfig, FeatureNorm, Variant};

mod terminal;

/// Large blocks advised for huge pages (`memory`).
#[global_allocator]
static ALLOCATOR: base::memory::HugePageAdvice = base::memory::HugePageAdvice;

/// Zero-shot 3D style transfer on Gaussian splatting (DS-StyleGaussian), exact and CPU-only.
#[derive(Parser)]
#[command(name = "dsgs", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Import PyTorch checkpoints into the canonical weights format, or describe a weights file.
    #[command(subcommand)]
    Weights(WeightsCommand),
    /// Fit 3D Gaussians to a dataset of posed images (the geometry stage).
    FitGeometry(FitGeometryArgs),
    /// Train an AdaIN decoder for a frozen encoder on content and style images.
    PretrainDecoder(PretrainDecoderArgs),
    /// Train per-Gaussian features and the lifter on frozen geometry into a scene bundle.
    FitFeatures(FitFeaturesArgs),
    /// Bake a style into a plain 3DGS .ply (SH colours fitted to stylized views).
    Bake(BakeArgs),
    /// Render a scene (.ply or bundle) as colour, depth, alpha or feature PCA images.
    Render(RenderArgs),
    /// Stylize a scene bundle with one or more style images.
    Stylize(StylizeArgs),
    /// Stylize photographs in 2D (AdaIN) with any networks, standard or fullres: outputs, a
    /// contact sheet and each output's style loss, texture distance and content loss.
    StylizeImage(StylizeImageArgs),
    /// Measure multi-view consistency, style and content losses and stage timings.
    Eval(EvalArgs),
    /// Run the whole pipeline on the lego scene at low resolution: geometry, features, a
    /// stylized orbit with four unseen styles, its evaluation, a contact sheet and GIFs.
    Demo(DemoArgs),
    /// Merge the shards of a `stylize`, `eval` or `bake` run made with `--shard K/N` into what
    /// one process writes (animations and contact sheet, report, or the fitted .ply), after
    /// checking that every shard finished with the same inputs.
    Assemble(AssembleArgs),
    /// Look around a scene (bundle or .ply) in the browser, and stylize the current view with
    /// any painting: starts a local web server and prints its address.
    View(ViewArgs),
}

#[derive(Args)]
struct ViewArgs {
    /// The scene: a scene bundle directory (stylizable) or any 3DGS .ply file.
    scene: PathBuf,
    /// Style image offered in the page; repeat for several (the page can upload more).
    #[arg(long = "style")]
    styles: Vec<PathBuf>,
    /// Port to listen on (0: any free port).
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Address to listen on. The default, 127.0.0.1, is reachable from this machine only.
    /// Another address (e.g. 0.0.0.0) lets every machine that can reach it see the scene and
    /// its cameras, upload images, and spend this machine's CPU on stylizations and bakes.
    #[arg(long, default_value = "127.0.0.1")]
    bind: std::net::IpAddr,
    /// Longest side of the style images after loading, in pixels (at least 1).
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE, value_parser = at_least_one::<u32>())]
    style_size: u32,
    /// Working memory of the networks per stylized view, in MiB (1 to 1048576).
    #[arg(long, default_value_t = train::bundle::DEFAULT_TILE_BUDGET_BYTES >> 20, value_parser = mebibytes())]
    tile_budget: u64,
    /// Most pixels (width x height) of an uploaded style image, read from its header before
    /// decoding (at least 1).
    #[arg(long, default_value_t = viewer::ViewerConfig::new("").max_upload_pixels, value_parser = at_least_one::<u64>())]
    max_upload_pixels: u64,
    /// Memory that the work in flight (uploads being decoded, stylizations running or waiting)
    /// may take by estimate, in MiB; a request beyond it is answered 503 (1 to 1048576).
    #[arg(long, default_value_t = viewer::ViewerConfig::new("").memory_budget >> 20, value_parser = mebibytes())]
    memory_budget: u64,
}

#[derive(Args)]
struct AssembleArgs {
    /// The sharded run's output: the folder of `stylize -o`, the report of `eval -o`, or the
    /// .ply of `bake -o`.
    output: PathBuf,
    /// Bake: continue the fit from this checkpoint of a stopped assembly (as `bake --resume`)
    #[arg(long)]
    resume: Option<PathBuf>,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

/// `--shard K/N`, shared by the commands that can be split over processes.
#[derive(Args, Clone)]
struct ShardArgs {
    /// Run only shard K of N (K from 1 to N): a contiguous block of the frames (of a bake: of
    /// its stylized target views), written as the whole run writes them, and a manifest written
    /// last; merge the finished shards with `dsgs assemble OUTPUT` [default: the whole run]
    #[arg(long, value_name = "K/N", value_parser = shard)]
    shard: Option<Shard>,
}

fn shard(s: &str) -> Result<Shard, String> {
    s.parse::<Shard>().map_err(|e| e.to_string())
}

impl ShardArgs {
    /// The part of the run: the whole, or this shard with the command line that made it.
    fn part(&self) -> Result<Part> {
        let Some(shard) = self.shard else {
            return Ok(Part::Whole);
        };
        Ok(Part::Shard {
            shard,
            invocation: Some(invocation()?),
        })
    }
}

/// This process's command line without `--shard`, and its working directory: what
/// `dsgs assemble` runs again.
fn invocation() -> Result<Invocation> {
    let mut args = Vec::new();
    let mut raw = std::env::args_os().skip(1);
    while let Some(a) = raw.next() {
        let Some(a) = a.to_str().map(str::to_string) else {
            bail!("an argument is not valid UTF-8, so the shard's command line cannot be recorded for `dsgs assemble`: {a:?}");
        };
        if a == "--shard" {
            raw.next();
        } else if !a.starts_with("--shard=") {
            args.push(a);
        }
    }
    let cwd = std::env::current_dir().context("reading the working directory")?;
    Ok(Invocation { args, cwd })
}

// ---- Help texts and value parsers ----

/// `text` followed by its default in clap's `[default: VALUE]` form. Flags that override a
/// `--config` file have no clap default (absent, they leave the file's value); their help takes
/// the configuration's default from its `Default` through this, so it cannot drift.
fn with_default(text: &str, default: impl Display) -> String {
    format!("{text} [default: {default}]")
}

/// A comma-separated list, or `none`.
fn list<T: Display>(values: &[T]) -> String {
    if values.is_empty() {
        return "none".into();
    }
    let v: Vec<String> = values.iter().map(T::to_string).collect();
    v.join(",")
}

/// A parser accepting exactly `names`, listed in `--help` and in the error for any other value.
fn one_of<T>(names: impl IntoIterator<Item = &'static str>) -> impl TypedValueParser<Value = T>
where
    T: FromStr<Err = String> + Clone + Send + Sync + 'static,
{
    PossibleValuesParser::new(names).try_map(|s| s.parse::<T>())
}

/// The `--variant` parser: `standard` or `fullres`, listed in `--help`.
fn variant() -> impl TypedValueParser<Value = Variant> {
    // The match makes a new variant fail to compile here until it is listed.
    let listed = |v: Variant| match v {
        Variant::Standard | Variant::Fullres => v.as_str(),
    };
    one_of([listed(Variant::Standard), listed(Variant::Fullres)])
}

/// The `--decoder-mode` parser: `pretrained`, `scratch` or `mlp`, listed in `--help`.
fn decoder_mode() -> impl TypedValueParser<Value = DecoderMode> {
    let listed = |v: DecoderMode| match v {
        DecoderMode::Pretrained | DecoderMode::Scratch | DecoderMode::Mlp => v.as_str(),
    };
    one_of([
        listed(DecoderMode::Pretrained),
        listed(DecoderMode::Scratch),
        listed(DecoderMode::Mlp),
    ])
}

/// The `--normalize` parser: `before-raster` or `after-raster`, listed in `--help`.
fn feature_norm() -> impl TypedValueParser<Value = FeatureNorm> {
    let listed = |v: FeatureNorm| match v {
        FeatureNorm::BeforeRaster | FeatureNorm::AfterRaster => v.as_str(),
    };
    one_of([
        listed(FeatureNorm::BeforeRaster),
        listed(FeatureNorm::AfterRaster),
    ])
}

/// A whole number in `min..=max`; the message names the range (clap adds the flag).
fn whole_in<T>(min: T, max: T) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
where
    T: FromStr + PartialOrd + Display + Copy + Send + Sync + 'static,
{
    move |s: &str| {
        let v: T = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a whole number"))?;
        if v < min || v > max {
            return Err(format!("must be between {min} and {max}"));
        }
        Ok(v)
    }
}

/// A whole number of at least 1 (a count where 0 means nothing: iterations, frames, sizes).
fn at_least_one<T>() -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
where
    T: FromStr + PartialOrd + Display + Copy + From<u8> + Send + Sync + 'static,
{
    |s: &str| {
        let v: T = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a whole number"))?;
        if v < T::from(1) {
            return Err("must be at least 1".into());
        }
        Ok(v)
    }
}

/// A finite number.
fn finite(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    if !v.is_finite() {
        return Err("must be a finite number".into());
    }
    Ok(v)
}

/// A finite number above 0 (a factor, a rate of frames, a tolerance).
fn positive(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v <= 0.0 {
        return Err("must be a finite number above 0".into());
    }
    Ok(v)
}

/// A finite number of 0 or more (a weight, a learning rate).
fn non_negative(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v < 0.0 {
        return Err("must be a finite number, 0 or more".into());
    }
    Ok(v)
}

/// A number in [0, 1] (a strength, an alpha level).
fn fraction(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if !(0.0..=1.0).contains(&v) {
        return Err("must be in [0, 1]".into());
    }
    Ok(v)
}

/// An `x,y,z` direction: three finite numbers, not all zero.
fn direction(s: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f64>()
                .map_err(|_| format!("`{x}` is not a number"))
        })
        .collect::<Result<_, _>>()?;
    let d = match v.as_slice() {
        [x, y, z] => DVec3::new(*x, *y, *z),
        _ => return Err(format!("expected three comma-separated numbers, got `{s}`")),
    };
    if !d.is_finite() || d == DVec3::ZERO {
        return Err(format!("`{s}` is not a direction (finite and not zero)"));
    }
    Ok(d)
}

/// `--weights` where it used to mean the weights of a style mixture (stylize, eval, bake):
/// always refused, pointing to `--mix`.
fn renamed_to_mix(_: &str) -> Result<String, String> {
    Err(
        "the weights of a style mixture are given with --mix (comma-separated, one per \
         --style); --weights names a network weights file, which this command does not take"
            .into(),
    )
}

/// The tip added to an unexpected positional argument: most likely a second value given to a
/// one-value path flag.
const REPEAT_TIP: &str = "a flag takes one path per occurrence: repeat it for several, as in \
                          '--style a.jpg --style b.jpg'";

// ---- Arguments ----

/// How a training command runs: resume, checkpoints, logs and bars. The defaults of
/// `--checkpoint-every` and `--log-every` are each command's configuration's, added to their help
/// by [`command`].
#[derive(Args)]
struct RunArgs {
    /// Continue from the checkpoint of a stopped run (the path it printed) [default: none, a
    /// fresh run]
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Iterations between checkpoints (0: only when stopped)
    #[arg(long)]
    checkpoint_every: Option<u64>,
    /// Print a progress line every N iterations, for logs (0: none)
    #[arg(long)]
    log_every: Option<u64>,
    /// No progress bars (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

#[derive(Args)]
struct DemoArgs {
    /// The shared data folder (scenes, styles, weights)
    #[arg(long, env = "DSGS_SHARED", default_value = "../shared")]
    shared: PathBuf,
    /// Output directory; a rerun skips the stages whose results are there and resumes an
    /// interrupted one
    #[arg(short, long, default_value = "dsgs-demo")]
    output: PathBuf,
    /// Canonical network weights (.safetensors, encoder and decoder) [default: imported from
    /// SHARED/weights/wct-relu1_1-3_1]
    #[arg(long)]
    weights: Option<PathBuf>,
    /// A decoder (PyTorch checkpoint or .safetensors) replacing the one of the weights, e.g. one
    /// fine-tuned by `dsgs pretrain-decoder` for the fullres variant [default: the weights']
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Network variant (fullres needs a decoder fine-tuned for it to stylize strongly)
    #[arg(long, default_value = "standard", value_parser = variant())]
    variant: Variant,
    /// Downscale factor of the 800x800 lego images (above 0)
    #[arg(long, default_value_t = 8.0, value_parser = positive)]
    downscale: f64,
    /// Geometry iterations (at least 1)
    #[arg(long, default_value_t = 1000, value_parser = at_least_one::<u64>())]
    geometry_iterations: u64,
    /// Alignment-only feature iterations (cheap) before the full loss
    #[arg(long, default_value_t = 1500)]
    align_warmup: u64,
    /// Feature iterations with the full loss (alignment, content, style)
    #[arg(long, default_value_t = 300)]
    feature_iterations: u64,
    /// Style image; repeat for several [default: four paintings of SHARED/data/styles never
    /// used in training]
    #[arg(long = "style")]
    styles: Vec<PathBuf>,
    /// Frames of the orbit (at least 1)
    #[arg(long, default_value_t = 24, value_parser = at_least_one::<usize>())]
    frames: usize,
    /// No progress bars (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

#[derive(Subcommand)]
enum WeightsCommand {
    /// Convert PyTorch checkpoints (legacy pickle or zip) to one canonical safetensors file.
    Import {
        /// Encoder checkpoint (e.g. vgg_normalised.pth, vgg_normalised_conv3_1.pth, 4SE.pth)
        /// [default: none]
        #[arg(long)]
        encoder: Option<PathBuf>,
        /// Decoder checkpoint (e.g. decoder.pth, feature_invertor_conv3_1.pth, 4SD.pth)
        /// [default: none]
        #[arg(long)]
        decoder: Option<PathBuf>,
        /// Output file (.safetensors).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Print the layout of a weights file (canonical .safetensors or PyTorch .pth).
    Info {
        /// The weights file.
        path: PathBuf,
    },
}

/// The help of `--config` of the commands that save their configuration as `OUT/config.toml`.
const CONFIG_HELP: &str = "TOML configuration (keys: docs/configuration.md); flags override it \
                           [default: none: the built-in defaults, or OUT/config.toml when resuming]";

/// The help of `bake --config` (a bake records its configuration in its JSON report).
const BAKE_CONFIG_HELP: &str = "TOML configuration (keys: docs/configuration.md); flags override \
                                it [default: none: the built-in defaults]";

#[derive(Args)]
struct FitGeometryArgs {
    /// Dataset directory (COLMAP, NeRF-synthetic or LLFF layout).
    dataset: PathBuf,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
    #[arg(long, help = CONFIG_HELP)]
    config: Option<PathBuf>,
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations (at least 1); the configuration's schedule (learning-rate decay, \
         densification window and interval, opacity resets, SH degree steps, test, save and \
         checkpoint iterations) is stretched or compressed to it, keeping density control at \
         least 50 and opacity resets at least 300 steps apart",
        FitGeometryConfig::default().geometry.iterations,
    ))]
    iterations: Option<u64>,
    #[arg(long, conflicts_with = "resolution", value_parser = positive, help = with_default(
        "Resize the images by 1/F on load (above 0)",
        FitGeometryConfig::default().dataset.downscale,
    ))]
    downscale: Option<f64>,
    /// Read the images from the images_N folder (at least 1) [default: none: the images folder]
    #[arg(long, value_parser = at_least_one::<u32>())]
    resolution: Option<u32>,
    /// White background (NeRF-synthetic scenes).
    #[arg(long)]
    white: bool,
    #[arg(long, value_delimiter = ',', help = with_default(
        "Iterations at which to evaluate the held-out views and save the scene (comma-separated; \
         used as given)",
        format!(
            "{}, scaled with --iterations",
            list(&FitGeometryConfig::default().geometry.test_iterations)
        ),
    ))]
    test_iterations: Option<Vec<u64>>,
    /// Iterations at which to save the scene, when they differ from the test iterations
    /// (comma-separated) [default: the test iterations]
    #[arg(long, value_delimiter = ',')]
    save_iterations: Option<Vec<u64>>,
    #[arg(long, value_delimiter = ',', help = with_default(
        "Iterations at which to write a resumable checkpoint (comma-separated)",
        list(&FitGeometryConfig::default().geometry.checkpoint_iterations),
    ))]
    checkpoint_iterations: Option<Vec<u64>>,
    /// Train on every image (no held-out split).
    #[arg(long)]
    no_eval: bool,
    #[arg(long, help = with_default(
        "Seed of every random choice",
        FitGeometryConfig::default().geometry.seed,
    ))]
    seed: Option<u64>,
    #[arg(long, value_parser = whole_in(0, STORED_SH_DEGREE), help = with_default(
        "Maximum SH degree (0 to 3)",
        FitGeometryConfig::default().geometry.sh_degree,
    ))]
    sh_degree: Option<usize>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Args)]
struct PretrainDecoderArgs {
    /// Content image folder or file; repeat for several (at least one).
    #[arg(long, required = true)]
    content: Vec<PathBuf>,
    /// Style image folder or file; repeat for several (at least one).
    #[arg(long = "style", required = true)]
    styles: Vec<PathBuf>,
    /// Search the image folders recursively.
    #[arg(long)]
    recursive: bool,
    /// Held-out content images for the evaluation curve (folder or file; repeat for several;
    /// with --eval-style) [default: the training images]
    #[arg(long = "eval-content", requires = "eval_styles")]
    eval_content: Vec<PathBuf>,
    /// Held-out style images for the evaluation curve (folder or file; repeat for several;
    /// with --eval-content) [default: the training images]
    #[arg(long = "eval-style", requires = "eval_content")]
    eval_styles: Vec<PathBuf>,
    /// Canonical network weights (.safetensors) holding the encoder and, unless --from-scratch
    /// or --decoder, the starting decoder [default: none: give --encoder and --decoder]
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Encoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long)]
    encoder: Option<PathBuf>,
    /// Starting decoder (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long, conflicts_with = "from_scratch")]
    decoder: Option<PathBuf>,
    /// Start from a seeded initialisation of the encoder's mirror image.
    #[arg(long)]
    from_scratch: bool,
    #[arg(long, value_parser = variant(), help = with_default(
        "Network variant",
        DecoderTrainConfig::default().variant.as_str(),
    ))]
    variant: Option<Variant>,
    #[arg(long, help = CONFIG_HELP)]
    config: Option<PathBuf>,
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations (at least 1)",
        DecoderTrainConfig::default().iterations,
    ))]
    iterations: Option<u64>,
    #[arg(long, value_parser = at_least_one::<usize>(), help = with_default(
        "Content (and style) images per iteration (at least 1)",
        DecoderTrainConfig::default().batch_size,
    ))]
    batch_size: Option<usize>,
    #[arg(long, value_parser = at_least_one::<u32>(), help = with_default(
        "Side of the square random crop, in pixels (at least 1, at most --resize)",
        DecoderTrainConfig::default().crop,
    ))]
    crop: Option<u32>,
    #[arg(long, value_parser = at_least_one::<u32>(), help = with_default(
        "Short side the images are resized to before cropping, in pixels (at least 1)",
        DecoderTrainConfig::default().resize,
    ))]
    resize: Option<u32>,
    #[arg(long, value_parser = non_negative, help = with_default(
        "Weight of the style loss (0 or more)",
        DecoderTrainConfig::default().style_weight,
    ))]
    style_weight: Option<f64>,
    #[arg(long, value_parser = non_negative, help = with_default(
        "Initial learning rate (0 or more)",
        DecoderTrainConfig::default().lr,
    ))]
    lr: Option<f64>,
    #[arg(long, help = with_default(
        "Seed of every random choice",
        DecoderTrainConfig::default().seed,
    ))]
    seed: Option<u64>,
    #[command(flatten)]
    run: RunArgs,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args)]
struct FitFeaturesArgs {
    /// The trained geometry (.ply).
    #[arg(long)]
    geometry: PathBuf,
    /// The dataset the geometry was trained on (COLMAP, NeRF-synthetic or LLFF layout).
    #[arg(long)]
    dataset: PathBuf,
    /// Style image folder or file; repeat for several (at least one).
    #[arg(long = "style", required = true)]
    styles: Vec<PathBuf>,
    /// Paintings never trained on, for the evaluation of held-out views (folder or file; repeat
    /// for several) [default: the --style images]
    #[arg(long = "eval-style")]
    eval_styles: Vec<PathBuf>,
    #[arg(long, help = with_default(
        "Iterations between evaluations of the stage-3 loss on fixed held-out samples (the \
         held-out views with --eval-style paintings; training views with --no-eval), also made \
         before the first iteration and at the end; 0: only those two",
        FitFeaturesConfig::default().features.eval_interval,
    ))]
    eval_every: Option<u64>,
    /// Canonical network weights (.safetensors) holding the encoder and decoder.
    #[arg(long)]
    weights: PathBuf,
    /// A decoder (PyTorch checkpoint or .safetensors) replacing the one in --weights [default:
    /// the one in --weights]
    #[arg(long)]
    decoder: Option<PathBuf>,
    #[arg(long, value_parser = variant(), help = with_default(
        "Network variant",
        FitFeaturesConfig::default().features.variant.as_str(),
    ))]
    variant: Option<Variant>,
    /// The decoder of stage 3, for the paper's decoder ablation: `pretrained` (the frozen 2D
    /// decoder of --weights/--decoder, the paper's design), `scratch` (the same CNN initialised
    /// from --seed and trained here with the features) or `mlp` (a per-pixel MLP, features ->
    /// 256 -> 128 -> RGB, trained here; needs --variant fullres). The bundle keeps the trained
    /// decoder [default: pretrained]
    #[arg(long, value_parser = decoder_mode())]
    decoder_mode: Option<DecoderMode>,
    #[arg(long, value_parser = positive, help = with_default(
        "Adam learning rate of a decoder trained in stage 3 (--decoder-mode scratch or mlp; \
         above 0)",
        FitFeaturesConfig::default().features.lr_decoder,
    ))]
    lr_decoder: Option<f64>,
    /// Where the features are normalised, for the paper's consistency ablation:
    /// `before-raster` (each view's encoder feature is normalised, then distilled into the
    /// Gaussians, so every view gets the same style transform: the paper's design) or
    /// `after-raster` (unnormalised features are distilled, and each rendered view is
    /// normalised with its own statistics before the transform, as 2D AdaIN does). The bundle
    /// records it and stylization follows it [default: before-raster]
    #[arg(long, value_parser = feature_norm())]
    normalize: Option<FeatureNorm>,
    #[arg(long, help = CONFIG_HELP)]
    config: Option<PathBuf>,
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations, the warm-up included (at least 1)",
        FitFeaturesConfig::default().features.iterations,
    ))]
    iterations: Option<u64>,
    #[arg(long, value_parser = at_least_one::<usize>(), help = with_default(
        "Channels of each Gaussian's feature (at least 1)",
        FitFeaturesConfig::default().features.feature_dim,
    ))]
    feature_dim: Option<usize>,
    #[arg(long, value_parser = positive, help = with_default(
        "Resize the images by 1/F on load (above 0)",
        FitFeaturesConfig::default().dataset.downscale,
    ))]
    downscale: Option<f64>,
    /// Train with the alignment loss only (no content and style terms).
    #[arg(long)]
    align_only: bool,
    #[arg(long, help = with_default(
        "Iterations at the start with the alignment loss only (cheap; gives the features the \
         scene's content before the content and style terms join)",
        FitFeaturesConfig::default().features.align_warmup,
    ))]
    align_warmup: Option<u64>,
    #[arg(long, help = with_default(
        "Seed of every random choice",
        FitFeaturesConfig::default().features.seed,
    ))]
    seed: Option<u64>,
    #[arg(long, value_parser = at_least_one::<u32>(), help = feature_crop_help())]
    crop: Option<u32>,
    /// White background (NeRF-synthetic scenes).
    #[arg(long)]
    white: bool,
    /// Train on every image (no held-out split).
    #[arg(long)]
    no_eval: bool,
    /// Do not keep the view and style encodings in OUT/encodings/ (they take about as much disk
    /// as memory; without them a resumed or repeated run encodes everything again).
    #[arg(long)]
    no_encoding_cache: bool,
    #[command(flatten)]
    run: RunArgs,
    /// Output directory (the bundle goes to OUT/bundle).
    #[arg(short, long)]
    output: PathBuf,
}

/// The help of `fit-features --crop`, with the default of each variant.
fn feature_crop_help() -> String {
    let side = |variant| {
        train::FeatureTrainConfig {
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

#[derive(Args)]
struct BakeArgs {
    /// Scene bundle directory.
    bundle: PathBuf,
    /// Style image; repeat for several, mixed with --mix into one (at least one).
    #[arg(long = "style", required = true)]
    styles: Vec<PathBuf>,
    /// Mix the styles with these weights (comma-separated, one per --style, each 0 or more, not
    /// all 0) [default: none; needed with several styles]
    #[arg(long, value_delimiter = ',', value_parser = non_negative)]
    mix: Option<Vec<f64>>,
    #[arg(long = "weights", hide = true, value_parser = renamed_to_mix)]
    _weights: Option<String>,
    /// Style strength, in [0, 1]: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0, value_parser = fraction)]
    alpha: f64,
    /// Longest side of the style images after loading, in pixels (at least 1).
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE, value_parser = at_least_one::<u32>())]
    style_size: u32,
    /// Network variant: `standard` (pooling and upsampling) or `fullres` (neither), for the
    /// paper's standard-against-fullres ablation [default: the bundle's]
    #[arg(long, value_parser = variant())]
    variant: Option<Variant>,
    /// Replace the bundle's decoder (.safetensors or a PyTorch checkpoint), e.g. the 2D decoder
    /// before fine-tuning; not for bundles whose decoder was trained with their features
    /// (fit-features --decoder-mode scratch or mlp). Where the features are normalised
    /// (fit-features --normalize) is the bundle's [default: the bundle's decoder]
    #[arg(long)]
    decoder: Option<PathBuf>,
    #[arg(long, help = BAKE_CONFIG_HELP)]
    config: Option<PathBuf>,
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Optimisation iterations (at least 1)",
        BakeConfig::default().iterations,
    ))]
    iterations: Option<u64>,
    #[arg(long, value_parser = whole_in(0, STORED_SH_DEGREE), help = with_default(
        "SH degree that is optimised (0 to 3; the .ply always stores degree 3)",
        BakeConfig::default().sh_degree,
    ))]
    sh_degree: Option<usize>,
    /// Also adapt opacities and scales, within small budgets.
    #[arg(long)]
    adapt_geometry: bool,
    #[arg(long, value_parser = non_negative, help = with_default(
        "Adam rate of the SH DC coefficients (0 or more)",
        BakeConfig::default().feature_lr,
    ))]
    lr: Option<f64>,
    #[arg(long, help = with_default(
        "Number of training target views (0: all candidates)",
        BakeConfig::default().target_views,
    ))]
    target_views: Option<usize>,
    #[arg(long, help = with_default(
        "Interpolated views held out for evaluation",
        BakeConfig::default().held_out,
    ))]
    held_out: Option<usize>,
    #[arg(long, value_parser = positive, help = with_default(
        "Image size of the targets relative to the bundle's cameras (above 0)",
        BakeConfig::default().resolution_scale,
    ))]
    resolution_scale: Option<f64>,
    #[arg(long, help = with_default("Seed of the view order", BakeConfig::default().seed))]
    seed: Option<u64>,
    #[arg(long, value_parser = mebibytes(), help = with_default(
        "Working memory of the networks per decoded target view, in MiB: views are decoded in \
         tiles that fit it (any budget gives the same targets; 1 to 1048576)",
        BakeConfig::default().tile_budget_mib,
    ))]
    tile_budget: Option<u64>,
    #[command(flatten)]
    shard: ShardArgs,
    #[command(flatten)]
    run: RunArgs,
    /// Output .ply (a JSON report is written beside it).
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args, Clone)]
struct CameraArgs {
    /// Camera source: the dataset's or bundle's cameras, the held-out ones, a path through
    /// them, an orbit, or a dense arc (frames 1 degree apart around what the cameras look at)
    /// [default: orbit; eval: dense]
    #[arg(long, value_parser = one_of::<CameraSource>(CameraSource::NAMES.iter().copied()))]
    cameras: Option<CameraSource>,
    #[arg(long, value_parser = at_least_one::<usize>(), help = format!(
        "Number of frames (path and orbit), or at most this many cameras (dataset and test); at \
         least 1 [default: {} for path and orbit, every camera for dataset and test]",
        pipeline::cameras::DEFAULT_FRAMES,
    ))]
    frames: Option<usize>,
    #[arg(long, value_parser = whole_in(1, MAX_IMAGE_SIDE), help = format!(
        "Image width, 1 to {MAX_IMAGE_SIDE} (alone: keeps the aspect ratio) [default: the \
         cameras' width; {} for an orbit without cameras]",
        pipeline::cameras::DEFAULT_SIDE,
    ))]
    width: Option<u32>,
    #[arg(long, value_parser = whole_in(1, MAX_IMAGE_SIDE), help = format!(
        "Image height, 1 to {MAX_IMAGE_SIDE} (alone: keeps the aspect ratio) [default: the \
         cameras' height; {} for an orbit without cameras]",
        pipeline::cameras::DEFAULT_SIDE,
    ))]
    height: Option<u32>,
    /// Scale every camera's image by this factor (above 0) [default: 1]
    #[arg(long, value_parser = positive)]
    scale: Option<f64>,
    /// Take the cameras from this directory instead of the scene: a dataset, or a scene bundle
    /// (its cameras at its training size, e.g. to render a baked `.ply` from them) [default:
    /// the scene's own cameras]
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// World up axis of orbits, as x,y,z (finite, not zero) [default: the cameras' mean
    /// image-up, else 0,-1,0]
    #[arg(long, value_parser = direction, allow_hyphen_values = true)]
    up: Option<DVec3>,
}

impl CameraArgs {
    /// The request, with `default` as the source when `--cameras` is not given.
    fn request(&self, default: CameraSource) -> CameraRequest {
        CameraRequest {
            source: self.cameras.unwrap_or(default),
            frames: self.frames,
            width: self.width,
            height: self.height,
            scale: self.scale,
            up: self.up,
        }
    }

    fn known(&self, scene: KnownCameras) -> Result<KnownCameras> {
        match &self.dataset {
            Some(d) => Ok(KnownCameras::from_dir(d)?),
            None => Ok(scene),
        }
    }
}

#[derive(Args)]
struct RenderArgs {
    /// The scene: a .ply file or a scene bundle directory.
    #[arg(long)]
    scene: PathBuf,
    #[command(flatten)]
    cameras: CameraArgs,
    /// What to draw.
    #[arg(long, default_value = "color", value_parser = one_of::<RenderKind>(RenderKind::NAMES.iter().copied()))]
    what: RenderKind,
    /// How depth is drawn.
    #[arg(long, default_value = "colour", value_parser = one_of::<DepthStyle>(DepthStyle::NAMES.iter().copied()))]
    depth_style: DepthStyle,
    /// Output directory (frame_XXXX.png).
    #[arg(short, long)]
    output: PathBuf,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

#[derive(Args)]
struct StyleArgs {
    /// Style image; repeat for several (at least one).
    #[arg(long = "style")]
    styles: Vec<PathBuf>,
    /// Mix the styles into one output with these weights (comma-separated, one per --style,
    /// each 0 or more, not all 0) [default: none: one output per style]
    #[arg(long, value_delimiter = ',', value_parser = non_negative)]
    mix: Option<Vec<f64>>,
    #[arg(long = "weights", hide = true, value_parser = renamed_to_mix)]
    _weights: Option<String>,
    /// Style strength, in [0, 1]: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0, value_parser = fraction)]
    alpha: f64,
    /// Keep the scene's colours (the style images are colour-matched to the colour renders).
    #[arg(long)]
    preserve_colour: bool,
    /// Longest side of the style images after loading, in pixels (at least 1).
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE, value_parser = at_least_one::<u32>())]
    style_size: u32,
    /// Network variant: `standard` (pooling and upsampling) or `fullres` (neither), for the
    /// paper's standard-against-fullres ablation [default: the bundle's]
    #[arg(long, value_parser = variant())]
    variant: Option<Variant>,
    /// Replace the bundle's decoder (.safetensors or a PyTorch checkpoint), e.g. the 2D decoder
    /// before fine-tuning; not for bundles whose decoder was trained with their features
    /// (fit-features --decoder-mode scratch or mlp). Where the features are normalised
    /// (fit-features --normalize) is the bundle's [default: the bundle's decoder]
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Working memory of the networks per frame, in MiB: frames are decoded in tiles that fit
    /// it (any budget gives the same images; 1 to 1048576).
    #[arg(long, default_value_t = train::bundle::DEFAULT_TILE_BUDGET_BYTES >> 20, value_parser = mebibytes())]
    tile_budget: u64,
}

/// An amount of memory in MiB: 1 to 1048576 (1 TiB).
fn mebibytes() -> impl TypedValueParser<Value = u64> {
    clap::value_parser!(u64).range(1..=1 << 20)
}

#[derive(Args)]
struct StylizeImageArgs {
    /// Content photo (file or folder); several may be given.
    #[arg(required = true)]
    photos: Vec<PathBuf>,
    /// Style image (file or folder); repeat for several (at least one).
    #[arg(long = "style", required = true)]
    styles: Vec<PathBuf>,
    /// Canonical network weights (.safetensors) holding the encoder and decoder [default: none:
    /// give --encoder and --decoder]
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Encoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long)]
    encoder: Option<PathBuf>,
    /// Decoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Network variant: `standard` (pooling and upsampling) or `fullres` (neither).
    #[arg(long, value_parser = variant(), default_value = "standard")]
    variant: Variant,
    /// Style strength, in [0, 1]: 0 reconstructs the photo, 1 is the full style.
    #[arg(long, default_value_t = 1.0, value_parser = fraction)]
    alpha: f64,
    /// Also stylize with the mixture of the styles, with these weights (comma-separated, one
    /// per style image, each 0 or more, not all 0) [default: no mixture]
    #[arg(long, value_delimiter = ',', value_parser = non_negative)]
    mix: Option<Vec<f64>>,
    /// Keep each photo's colours (the style images are colour-matched to it first).
    #[arg(long)]
    preserve_colour: bool,
    /// Longest side of the photos after loading, in pixels (0: as they are).
    #[arg(long, default_value_t = pipeline::stylize_image::DEFAULT_IMAGE_SIDE)]
    content_size: u32,
    /// Longest side of the style images after loading, in pixels (0: as they are).
    #[arg(long, default_value_t = pipeline::stylize_image::DEFAULT_IMAGE_SIDE)]
    style_size: u32,
    /// No progress bar.
    #[arg(long)]
    no_progress: bool,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args)]
struct StylizeArgs {
    /// Scene bundle directory.
    bundle: PathBuf,
    #[command(flatten)]
    style: StyleArgs,
    #[command(flatten)]
    cameras: CameraArgs,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
    /// Also write an animated GIF per style.
    #[arg(long)]
    gif: bool,
    /// Also write an MP4 per style (needs ffmpeg on PATH).
    #[arg(long)]
    mp4: bool,
    /// Frames per second of the animations (above 0).
    #[arg(long, default_value_t = 10.0, value_parser = positive)]
    fps: f64,
    /// Views (columns) in the contact sheet (at least 1).
    #[arg(long, default_value_t = 4, value_parser = at_least_one::<usize>())]
    sheet_views: usize,
    #[command(flatten)]
    shard: ShardArgs,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

#[derive(Args)]
struct EvalArgs {
    /// Scene bundle directory (to render and evaluate stylized sequences).
    bundle: Option<PathBuf>,
    #[command(flatten)]
    style: StyleArgs,
    #[command(flatten)]
    cameras: CameraArgs,
    /// Evaluate the existing frames (*.png in name order) of this directory instead, against
    /// the geometry of --scene (or of BUNDLE) [default: none: render BUNDLE's frames]
    #[arg(long)]
    frames_dir: Option<PathBuf>,
    /// The geometry for --frames-dir: a .ply file or a bundle directory [default: BUNDLE]
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Pixels with alpha at or below this, in [0, 1], are not compared.
    #[arg(long, default_value_t = 0.5, value_parser = fraction.map(|v| v as f32))]
    alpha_threshold: f32,
    /// Relative depth tolerance of the occlusion test (above 0).
    #[arg(long, default_value_t = 0.02, value_parser = positive)]
    depth_tolerance: f64,
    /// Write the report as JSON [default: none: the table only]
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Leave out the per-frame 2D baseline (`2d:STYLE`: each colour render stylized on its own
    /// by the bundle's encoder, AdaIN and decoder), which costs one whole-frame decode per view
    /// and style
    #[arg(long)]
    no_baseline: bool,
    #[command(flatten)]
    shard: ShardArgs,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    no_progress: bool,
}

/// The training commands' run flags whose defaults come from the command's configuration:
/// (subcommand, checkpoint interval, log interval).
fn run_defaults() -> [(&'static str, u64, u64); 4] {
    let g = FitGeometryConfig::default().geometry;
    let d = DecoderTrainConfig::default();
    let f = FitFeaturesConfig::default().features;
    let b = BakeConfig::default();
    [
        ("fit-geometry", g.checkpoint_interval, g.log_interval),
        ("pretrain-decoder", d.checkpoint_interval, d.log_interval),
        ("fit-features", f.checkpoint_interval, f.log_interval),
        ("bake", b.checkpoint_interval, b.log_interval),
    ]
}

/// The command line: the derived one, with each training command's defaults of
/// `--checkpoint-every` and `--log-every` added to their help.
fn command() -> clap::Command {
    let mut cmd = Cli::command();
    for (name, checkpoint, log) in run_defaults() {
        cmd = cmd.mut_subcommand(name, |sub| {
            let add = |arg: clap::Arg, default: u64| {
                let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
                arg.help(with_default(&help, default))
            };
            sub.mut_arg("checkpoint_every", |a| add(a, checkpoint))
                .mut_arg("log_every", |a| add(a, log))
        });
    }
    cmd
}

/// Adds [`REPEAT_TIP`] to an unexpected-argument error about a value (not a flag).
fn with_repeat_tip(mut e: clap::Error) -> clap::Error {
    let about_a_value = matches!(
        e.get(ContextKind::InvalidArg),
        Some(ContextValue::String(a)) if !a.starts_with('-')
    );
    if e.kind() == ErrorKind::UnknownArgument && about_a_value {
        let mut tips = match e.get(ContextKind::Suggested) {
            Some(ContextValue::StyledStrs(t)) => t.clone(),
            _ => Vec::new(),
        };
        tips.push(StyledStr::from(REPEAT_TIP));
        e.insert(ContextKind::Suggested, ContextValue::StyledStrs(tips));
    }
    e
}

/// Parses the process's arguments, or exits with clap's message.
fn parse() -> Cli {
    let parsed = command()
        .try_get_matches()
        .and_then(|m| Cli::from_arg_matches(&m));
    match parsed {
        Ok(cli) => cli,
        Err(e) => with_repeat_tip(e).exit(),
    }
}

fn main() -> ExitCode {
    base::memory::keep_freed_memory();
    let cli = parse();
    // The viewer's server blocks on its socket: it keeps the calling thread. Every other command
    // runs on a thread of rayon's pool, so that its parallel loops start from a worker (a join
    // on the worker's own queue) rather than from outside the pool (a job handed to the pool
    // and the calling thread put to sleep until it is done, at every loop), with the pool's
    // other workers polling for work rather than sleeping between loops.
    let outcome = if matches!(cli.command, Command::View(_)) {
        run(cli)
    } else {
        base::pool::with_workers_awake(|| run(cli))
    };
    match outcome {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if is_interrupted(&e) => {
            eprintln!("{e}");
            ExitCode::from(INTERRUPTED_EXIT)
        }
        Err(e) => {
            eprintln!("error: {}", base::error::chain(&*e));
            ExitCode::FAILURE
        }
    }
}

/// Exit status of a run that a stop request (SIGINT, SIGTERM or SIGHUP) ended early (128 +
/// SIGINT, the shell convention for an interrupted command).
const INTERRUPTED_EXIT: u8 = 130;

/// A training run that a signal stopped after writing its checkpoint: not an error, but not a
/// finished run either; the message says how to resume.
#[derive(Debug)]
struct Interrupted(String);

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Interrupted {}

/// Whether a stop request ended the command: a stopped training run, or a stage that stopped
/// with nothing to resume from.
fn is_interrupted(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.is::<Interrupted>()
            || matches!(c.downcast_ref(), Some(pipeline::Error::Interrupted(_)))
            || matches!(c.downcast_ref(), Some(train::TrainError::Interrupted(_)))
    })
}

/// The stop flag of the training commands, set by the first Ctrl-C, SIGTERM or SIGHUP: the run
/// ends after the current iteration, writes a checkpoint to resume from and exits with status
/// [`INTERRUPTED_EXIT`]. A second signal exits at once, deleting the temporary files of writes in progress.
fn stop_flag() -> Option<&'static AtomicBool> {
    static STOP: AtomicBool = AtomicBool::new(false);
    let installed = ctrlc::set_handler(|| {
        if STOP.swap(true, Ordering::SeqCst) {
            // A checkpoint or output being written is abandoned: delete its temporary file.
            base::fs::remove_unfinished_writes();
            eprintln!("\ninterrupted again: exiting without a checkpoint");
            std::process::exit(INTERRUPTED_EXIT.into());
        }
        eprintln!("\nstop requested: stopping after this iteration and writing a checkpoint (Ctrl-C again to exit at once)");
    });
    match installed {
        Ok(()) => Some(&STOP),
        Err(e) => {
            eprintln!("warning: no stop-signal handler ({e}); an interrupted run resumes from its last periodic checkpoint");
            None
        }
    }
}

/// Runs `f` with a terminal front end for `command` (bars unless `no_progress`) and the stop
/// flag.
fn with_control<T>(
    command: &'static str,
    no_progress: bool,
    f: impl FnOnce(&Control) -> Result<T>,
) -> Result<T> {
    let terminal = Terminal::new(command, !no_progress);
    f(&Control {
        sink: &terminal,
        stop: stop_flag(),
    })
}

/// The closing lines of a training run: iterations and rate, the checkpoint and the output. A
/// run a stop request ended becomes the [`Interrupted`] outcome, which says how to resume.
fn finish(run: &RunOutcome, checkpoint: Option<&Path>) -> Result<()> {
    let done = run.step - run.first_step;
    print!(
        "{done} iterations in {:.1} s ({:.2} it/s)",
        run.seconds,
        run.rate()
    );
    match checkpoint.or(run.stop_checkpoint.as_deref()) {
        Some(p) => println!("; checkpoint {}", p.display()),
        None => println!(),
    }
    if let Some((what, p)) = &run.output {
        println!("{what} written to {}", p.display());
    }
    match (&run.stop_checkpoint, run.interrupted) {
        (Some(p), true) => Err(Interrupted(format!(
            "stopped early at iteration {}; resume with --resume {}",
            run.step,
            p.display()
        ))
        .into()),
        (None, true) => Err(Interrupted(format!("stopped early at iteration {}", run.step)).into()),
        _ => Ok(()),
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Weights(WeightsCommand::Import {
            encoder,
            decoder,
            output,
        }) => {
            let w = pipeline::weights::import(encoder.as_deref(), decoder.as_deref())?;
            w.save(&output)
                .with_context(|| format!("writing {}", output.display()))?;
            print!("{}", pipeline::weights::describe(&output)?);
        }
        Command::Weights(WeightsCommand::Info { path }) => {
            print!("{}", pipeline::weights::describe(&path)?);
        }
        Command::FitGeometry(a) => fit_geometry(a)?,
        Command::PretrainDecoder(a) => pretrain_decoder(a)?,
        Command::FitFeatures(a) => fit_features(a)?,
        Command::Bake(a) => {
            let part = a.shard.part()?;
            bake(a, part)?
        }
        Command::Render(a) => render(a)?,
        Command::Stylize(a) => {
            let part = a.shard.part()?;
            stylize(a, part)?
        }
        Command::Eval(a) => {
            let part = a.shard.part()?;
            eval(a, part)?
        }
        Command::Demo(a) => demo(a)?,
        Command::Assemble(a) => assemble(a)?,
        Command::View(a) => view(a)?,
        Command::StylizeImage(a) => stylize_image(a)?,
    }
    Ok(())
}

fn fit_geometry(a: FitGeometryArgs) -> Result<()> {
    let settings = FitSettings {
        dataset: a.dataset,
        out_dir: a.output,
        config: a.config,
        resume: a.run.resume,
        overrides: GeometryOverrides {
            iterations: a.iterations,
            downscale: a.downscale,
            images_folder: a.resolution,
            white: a.white,
            no_eval: a.no_eval,
            test_iterations: a.test_iterations,
            save_iterations: a.save_iterations,
            checkpoint_iterations: a.checkpoint_iterations,
            seed: a.seed,
            sh_degree: a.sh_degree,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
        },
    };
    let r = with_control("fit-geometry", a.run.no_progress, |c| {
        Ok(pipeline::fit_geometry::run(&settings, c)?)
    })?;
    println!(
        "{} training and {} test views at {}x{}, {} initial Gaussians",
        r.train_views, r.test_views, r.width, r.height, r.initial_gaussians
    );
    for e in &r.evaluations {
        println!(
            "iteration {}: held-out PSNR {:.3} dB, SSIM {:.4}, L1 {:.5}, {} Gaussians",
            e.step, e.psnr, e.ssim, e.l1, e.gaussians
        );
    }
    println!(
        "{} Gaussians; scene written to {}",
        r.gaussians,
        r.ply.display()
    );
    finish(&r.run, None)
}

fn pretrain_decoder(a: PretrainDecoderArgs) -> Result<()> {
    let settings = PretrainSettings {
        content: a.content,
        styles: a.styles,
        recursive: a.recursive,
        eval_content: a.eval_content,
        eval_styles: a.eval_styles,
        networks: NetworkFiles {
            weights: a.weights,
            encoder: a.encoder,
            decoder: a.decoder,
        },
        from_scratch: a.from_scratch,
        out_dir: a.output,
        config: a.config,
        resume: a.run.resume,
        overrides: DecoderOverrides {
            iterations: a.iterations,
            batch_size: a.batch_size,
            crop: a.crop,
            resize: a.resize,
            style_weight: a.style_weight,
            lr: a.lr,
            seed: a.seed,
            variant: a.variant,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
        },
    };
    let r = with_control("pretrain-decoder", a.run.no_progress, |c| {
        Ok(pipeline::pretrain_decoder::run(&settings, c)?)
    })?;
    println!(
        "{} content and {} style images, {} networks, crops of {} px",
        r.content_images,
        r.style_images,
        r.config.variant.as_str(),
        r.config.crop
    );
    for e in &r.evaluations {
        println!(
            "iteration {}: evaluation loss {:.5} (content {:.5}, style {:.5}, {} pairs)",
            e.step, e.loss, e.loss_content, e.loss_style, e.pairs
        );
    }
    finish(&r.run, Some(&r.checkpoint))
}

fn fit_features(a: FitFeaturesArgs) -> Result<()> {
    let settings = FitFeaturesSettings {
        geometry: a.geometry,
        dataset: a.dataset,
        styles: a.styles,
        eval_styles: a.eval_styles,
        networks: NetworkFiles {
            weights: Some(a.weights),
            encoder: None,
            decoder: a.decoder,
        },
        out_dir: a.output,
        config: a.config,
        resume: a.run.resume,
        overrides: FeatureOverrides {
            iterations: a.iterations,
            feature_dim: a.feature_dim,
            downscale: a.downscale,
            align_only: a.align_only,
            align_warmup: a.align_warmup,
            seed: a.seed,
            crop: a.crop,
            variant: a.variant,
            decoder_mode: a.decoder_mode,
            lr_decoder: a.lr_decoder,
            normalize: a.normalize,
            white: a.white,
            no_eval: a.no_eval,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            eval_every: a.eval_every,
        },
        encoding_cache: !a.no_encoding_cache,
    };
    let r = with_control("fit-features", a.run.no_progress, |c| {
        Ok(pipeline::fit_features::run(&settings, c)?)
    })?;
    println!(
        "{} Gaussians, {} training views, {} style images, {}-d features, {} networks",
        r.gaussians,
        r.train_views,
        r.style_images,
        r.config.features.feature_dim,
        r.config.features.variant.as_str()
    );
    if let Some([total, align, content, style]) = r.running_losses {
        println!(
            "running loss {total:.5} (align {align:.5}, content {content:.5}, style {style:.5})"
        );
    }
    let samples = if r.held_out { "held-out" } else { "training" };
    for e in &r.evaluations {
        println!(
            "iteration {}: evaluation loss {:.5} (align {:.5}, content {:.5}, style {:.5}, {} \
             {samples} samples)",
            e.step, e.loss, e.loss_align, e.loss_content, e.loss_style, e.pairs
        );
    }
    finish(&r.run, Some(&r.checkpoint))
}

fn bake(a: BakeArgs, part: Part) -> Result<()> {
    let settings = BakeSettings {
        bundle: a.bundle,
        styles: a.styles,
        weights: a.mix,
        alpha: a.alpha,
        style_side: a.style_size,
        variant: a.variant,
        decoder: a.decoder,
        config: a.config,
        overrides: BakeOverrides {
            iterations: a.iterations,
            sh_degree: a.sh_degree,
            adapt_geometry: a.adapt_geometry,
            lr: a.lr,
            target_views: a.target_views,
            held_out: a.held_out,
            resolution_scale: a.resolution_scale,
            seed: a.seed,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            tile_budget_mib: a.tile_budget,
        },
        output: a.output,
        resume: a.run.resume,
        part: if part == Part::Assemble {
            Part::Assemble
        } else {
            Part::Whole
        },
    };
    if let Part::Shard { shard, invocation } = part {
        let done = with_control("bake", a.run.no_progress, |c| {
            Ok(pipeline::bake::render_target_shard(
                &settings, shard, invocation, c,
            )?)
        })?;
        println!(
            "shard {shard}: target views {} to {} of {} written to {}",
            done.range.start,
            done.range.end.saturating_sub(1),
            done.targets,
            pipeline::bake::shard_dir(&settings.output).display()
        );
        println!(
            "when every shard has finished: dsgs assemble {}",
            settings.output.display()
        );
        return Ok(());
    }
    let out = with_control("bake", a.run.no_progress, |c| {
        Ok(pipeline::bake::run(&settings, c)?)
    })?;
    let s = &out.summary;
    println!(
        "{} training and {} held-out target views, targets in {:.1} s",
        s.train_views, s.held_out_views, s.target_seconds
    );
    if let Some((ply, report)) = &out.written {
        let db = |p: Option<f64>| p.map_or_else(|| "-".to_string(), |v| format!("{v:.3} dB"));
        println!(
            "training PSNR: baked {:.3} dB, unbaked {:.3} dB",
            s.train_psnr, s.unbaked_train_psnr
        );
        println!(
            "held-out PSNR: baked {}, unbaked {}",
            db(s.held_out_psnr),
            db(s.unbaked_held_out_psnr)
        );
        println!(
            "{} Gaussians written to {}, report {}",
            s.gaussians,
            ply.display(),
            report.display()
        );
    }
    finish(&out.run, None)
}

fn render(a: RenderArgs) -> Result<()> {
    let scene = SceneInput::open(&a.scene)?;
    let known = a.cameras.known(scene.known_cameras())?;
    let cams = pipeline::cameras::select(
        &a.cameras.request(CameraSource::Orbit),
        &known,
        scene.gaussians(),
    )?;
    let terminal = Terminal::new("render", !a.no_progress);
    let written =
        pipeline::render::render_views(&scene, &cams, a.what, a.depth_style, &a.output, &terminal)?;
    println!("{} images written to {}", written.len(), a.output.display());
    Ok(())
}

fn bundle_with(
    dir: &Path,
    variant: Option<Variant>,
    decoder: Option<&Path>,
) -> Result<train::SceneBundle> {
    Ok(pipeline::stylize::load_bundle(dir, variant, decoder)?)
}

fn demo(a: DemoArgs) -> Result<()> {
    let settings = pipeline::demo::DemoSettings {
        styles: pipeline::demo::styles_or_default(&a.shared, &a.styles),
        shared: a.shared,
        out_dir: a.output.clone(),
        weights: a.weights,
        decoder: a.decoder,
        variant: a.variant,
        downscale: a.downscale,
        geometry_iterations: a.geometry_iterations,
        align_warmup: a.align_warmup,
        feature_iterations: a.feature_iterations,
        frames: a.frames,
    };
    let r = with_control("demo", a.no_progress, |c| {
        Ok(pipeline::demo::run(&settings, c)?)
    })?;
    print!("{}", pipeline::eval::table(&r.eval));
    if let Some(p) = r.geometry_psnr {
        println!("geometry: held-out PSNR {p:.2} dB");
    }
    println!("{} Gaussians", r.gaussians);
    for (stage, t) in &r.seconds {
        match t {
            Some(t) => println!("{stage:>9}: {t:.1} s"),
            None => println!("{stage:>9}: done before, skipped"),
        }
    }
    // Outputs of this run or, for a skipped stage, of the run that made them.
    for p in r.stylized.gifs.iter().chain(&r.stylized.contact_sheet) {
        println!("output {}", p.display());
    }
    println!("output {}", r.eval_json.display());
    Ok(())
}

fn stylize(a: StylizeArgs, part: Part) -> Result<()> {
    if a.style.styles.is_empty() {
        bail!("give at least one --style image to stylize with");
    }
    let bundle = bundle_with(&a.bundle, a.style.variant, a.style.decoder.as_deref())?;
    let known = a.cameras.known(KnownCameras::from_bundle(
        &bundle,
        &a.bundle.display().to_string(),
    ))?;
    let cams = pipeline::cameras::select(
        &a.cameras.request(CameraSource::Orbit),
        &known,
        &bundle.scene,
    )?;
    let settings = pipeline::stylize::StylizeSettings {
        styles: a.style.styles,
        weights: a.style.mix,
        alpha: a.style.alpha,
        preserve_colour: a.style.preserve_colour,
        style_side: a.style.style_size,
        out_dir: a.output.clone(),
        gif: a.gif,
        mp4: a.mp4,
        fps: a.fps,
        sheet_views: a.sheet_views,
        tile_budget: a.style.tile_budget << 20,
        part: part.clone(),
    };
    let terminal = Terminal::new("stylize", !a.no_progress);
    let out = pipeline::stylize::run(&bundle, &cams, &settings, &terminal)?;
    if let Part::Shard { shard, .. } = &part {
        let r = shard.range(cams.len());
        println!(
            "shard {shard}: frames {} to {} of {} written for {} output(s) in {}",
            r.start,
            r.end.saturating_sub(1),
            cams.len(),
            out.outputs.len(),
            a.output.display()
        );
        if let Some(m) = &out.manifest {
            println!("manifest {}", m.display());
        }
        println!(
            "when every shard has finished: dsgs assemble {}",
            a.output.display()
        );
    } else {
        for (name, _) in &out.outputs {
            println!(
                "{name}: {} frames in {}",
                cams.len(),
                a.output.join(name).display()
            );
        }
    }
    for p in out.gifs.iter().chain(&out.mp4s).chain(&out.contact_sheet) {
        println!("wrote {}", p.display());
    }
    if out.decoded > 0 {
        let s = out.seconds;
        println!(
            "seconds per view: raster {:.4}, lift+transform {:.4}, decode {:.4}",
            s.raster, s.lift_transform, s.decode
        );
    }
    Ok(())
}

fn eval(a: EvalArgs, part: Part) -> Result<()> {
    let warp = WarpOptions {
        alpha_threshold: a.alpha_threshold,
        depth_tolerance: a.depth_tolerance,
    };
    let terminal = Terminal::new("eval", !a.no_progress);
    if part != Part::Whole && a.frames_dir.is_some() {
        bail!("--shard splits the evaluation of a bundle's stylized frames, not of --frames-dir");
    }
    let report = if let Some(frames_dir) = &a.frames_dir {
        let scene_path = a
            .scene
            .as_ref()
            .or(a.bundle.as_ref())
            .context("--frames-dir needs the geometry: --scene PLY_OR_BUNDLE")?;
        let scene = SceneInput::open(scene_path)?;
        let known = a.cameras.known(scene.known_cameras())?;
        let cams = pipeline::cameras::select(
            &a.cameras.request(CameraSource::Dense),
            &known,
            scene.gaussians(),
        )?;
        pipeline::eval::evaluate_frames(&scene, &cams, frames_dir, &warp, &terminal)?
    } else {
        let Some(dir) = &a.bundle else {
            bail!("give a scene bundle to evaluate (or --frames-dir DIR --scene SCENE)");
        };
        let bundle = bundle_with(dir, a.style.variant, a.style.decoder.as_deref())?;
        let known = a.cameras.known(KnownCameras::from_bundle(
            &bundle,
            &dir.display().to_string(),
        ))?;
        let cams = pipeline::cameras::select(
            &a.cameras.request(CameraSource::Dense),
            &known,
            &bundle.scene,
        )?;
        let settings = pipeline::eval::EvalSettings {
            styles: a.style.styles,
            weights: a.style.mix,
            alpha: a.style.alpha,
            preserve_colour: a.style.preserve_colour,
            style_side: a.style.style_size,
            warp,
            tile_budget: a.style.tile_budget << 20,
            baseline: !a.no_baseline,
            part: part.clone(),
        };
        let name = dir.display().to_string();
        if part == Part::Whole {
            pipeline::eval::evaluate_bundle(&bundle, &name, &cams, &settings, &terminal)?
        } else {
            let Some(report) = &a.output else {
                bail!("--shard needs the report path (-o REPORT.json): the shards' partial results go beside it");
            };
            let done = pipeline::eval::evaluate_sharded(
                &bundle, &name, &cams, &settings, report, &terminal,
            )?;
            let Some(done) = done else {
                let Part::Shard { shard, .. } = part else {
                    unreachable!("only a shard returns no report")
                };
                let r = shard.range(cams.len());
                println!(
                    "shard {shard}: views {} to {} of {} evaluated; partial results in {}",
                    r.start,
                    r.end.saturating_sub(1),
                    cams.len(),
                    pipeline::eval::shard_dir(report).display()
                );
                println!(
                    "when every shard has finished: dsgs assemble {}",
                    report.display()
                );
                return Ok(());
            };
            done
        }
    };
    print!("{}", pipeline::eval::table(&report));
    if let Some(p) = &a.output {
        pipeline::eval::write_report(p, &report)?;
        println!("report written to {}", p.display());
    }
    Ok(())
}

/// `dsgs stylize-image PHOTO... --style STYLE... -o OUT`.
fn stylize_image(a: StylizeImageArgs) -> Result<()> {
    let settings = pipeline::stylize_image::StylizeImageSettings {
        contents: a.photos,
        styles: a.styles,
        networks: NetworkFiles {
            weights: a.weights,
            encoder: a.encoder,
            decoder: a.decoder,
        },
        variant: a.variant,
        alpha: a.alpha,
        mix: a.mix,
        preserve_colour: a.preserve_colour,
        content_side: a.content_size,
        style_side: a.style_size,
        out_dir: a.output.clone(),
    };
    let r = with_control("stylize-image", a.no_progress, |c| {
        Ok(pipeline::stylize_image::run(&settings, c)?)
    })?;
    println!(
        "{:<24} {:<24} {:>10} {:>10} {:>10}",
        "photo", "style", "style", "texture", "content"
    );
    for p in &r.pairs {
        println!(
            "{:<24} {:<24} {:>10.4} {:>10.4} {:>10.4}",
            p.content, p.style, p.style_loss, p.texture_distance, p.content_loss
        );
    }
    println!(
        "mean: style loss {:.4}, texture distance {:.4}, content loss {:.4}; outputs, \
         contact_sheet.png and report.json in {}",
        r.mean_style_loss,
        r.mean_texture_distance,
        r.mean_content_loss,
        a.output.display()
    );
    Ok(())
}

/// `dsgs view SCENE`: serves until the process is stopped.
fn view(a: ViewArgs) -> Result<()> {
    let config = viewer::ViewerConfig {
        styles: a.styles,
        bind: a.bind,
        port: a.port,
        style_side: a.style_size,
        tile_budget: a.tile_budget << 20,
        max_upload_pixels: a.max_upload_pixels,
        memory_budget: a.memory_budget << 20,
        ..viewer::ViewerConfig::new(&a.scene)
    };
    let running = viewer::start(config)
        .with_context(|| format!("starting the viewer of {}", a.scene.display()))?;
    let mut text = format!("dsgs view: {} at {}\n", a.scene.display(), running.url());
    if !running.addr().ip().is_loopback() {
        text += &format!(
            "listening on {}: every machine that reaches it can use this viewer\n",
            running.addr()
        );
    }
    text += "press Ctrl-C to stop\n";
    // A closed standard output (the reader went away) must not stop the server.
    use std::io::Write;
    let mut out = std::io::stdout();
    let _ = out.write_all(text.as_bytes()).and_then(|()| out.flush());
    running.wait();
    Ok(())
}

/// `dsgs assemble OUTPUT`: finds the shard manifests of OUTPUT, runs the recorded command line
/// again (in its working directory) as the assembly of its shards, writing to OUTPUT.
fn assemble(a: AssembleArgs) -> Result<()> {
    let output = std::path::absolute(&a.output)
        .with_context(|| format!("resolving {}", a.output.display()))?;
    let places = [
        (
            pipeline::stylize::shard_dir(&output),
            pipeline::stylize::SHARD_COMMAND,
        ),
        (
            pipeline::eval::shard_dir(&output),
            pipeline::eval::SHARD_COMMAND,
        ),
        (
            pipeline::bake::shard_dir(&output),
            pipeline::bake::SHARD_COMMAND,
        ),
    ];
    let mut found = None;
    for (dir, command) in &places {
        if dir.is_dir() {
            let manifests = pipeline::shard::read_manifests(dir, command)?;
            pipeline::shard::check_one_run(dir, &manifests)?;
            if let Some((path, m)) = manifests.into_iter().next() {
                found = Some((path, m));
                break;
            }
        }
    }
    let Some((path, manifest)) = found else {
        bail!(
            "{}: no shard manifests in {} (stylize) or {} (eval, bake): run the shards with \
             --shard K/N first",
            a.output.display(),
            places[0].0.display(),
            places[1].0.display()
        );
    };
    let Some(inv) = manifest.invocation else {
        bail!(
            "{}: the manifest records no command line to assemble with",
            path.display()
        );
    };
    std::env::set_current_dir(&inv.cwd).with_context(|| {
        format!(
            "entering {}, the working directory of the shards (recorded in {})",
            inv.cwd.display(),
            path.display()
        )
    })?;
    let cli = command()
        .try_get_matches_from(std::iter::once("dsgs".to_string()).chain(inv.args))
        .and_then(|m| Cli::from_arg_matches(&m))
        .map_err(|e| {
            anyhow::anyhow!(
                "{}: the recorded command line does not parse any more: {}",
                path.display(),
                e.render()
            )
        })?;
    match cli.command {
        Command::Stylize(mut s) => {
            s.output = output;
            s.no_progress = a.no_progress;
            stylize(s, Part::Assemble)
        }
        Command::Eval(mut e) => {
            e.output = Some(output);
            e.no_progress = a.no_progress;
            eval(e, Part::Assemble)
        }
        Command::Bake(mut b) => {
            b.output = output;
            b.run.no_progress = a.no_progress;
            if a.resume.is_some() {
                b.run.resume = a.resume;
            }
            bake(b, Part::Assemble)
        }
        _ => bail!(
            "{}: a manifest of `{}`, which is not sharded",
            path.display(),
            manifest.command
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_is_consistent() {
        // clap's own checks: unique names, valid defaults, existing ids in `mut_arg`.
        command().debug_assert();
    }

    #[test]
    fn range_parsers_accept_their_ends_and_refuse_what_lies_outside() {
        assert_eq!(fraction("0"), Ok(0.0));
        assert_eq!(fraction("1"), Ok(1.0));
        for bad in ["-0.01", "1.01", "NaN", "inf", "x"] {
            assert!(fraction(bad).is_err(), "{bad}");
        }
        assert!(positive("1e-9").is_ok());
        for bad in ["0", "-1", "inf", "-inf"] {
            assert!(positive(bad).is_err(), "{bad}");
        }
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("-1e-9").is_err());
        let degree = whole_in(0usize, STORED_SH_DEGREE);
        assert_eq!(degree("0"), Ok(0));
        assert_eq!(degree("3"), Ok(3));
        assert!(degree("4").is_err() && degree("-1").is_err() && degree("1.5").is_err());
        let count = at_least_one::<u64>();
        assert_eq!(count("1"), Ok(1));
        assert!(count("0").is_err());
        assert_eq!(direction("0, 1,-0.5"), Ok(DVec3::new(0.0, 1.0, -0.5)));
        for bad in ["0,0,0", "1,2", "1,nan,0", "1,inf,0"] {
            assert!(direction(bad).is_err(), "{bad}");
        }
    }
}
