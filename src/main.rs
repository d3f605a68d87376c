//! The `dsgs` command-line program.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};
use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{Args, Parser, Subcommand};
use glam::DVec3;
use pipeline::bake::{BakeOverrides, BakeSettings};
use pipeline::cameras::{CameraRequest, CameraSource, KnownCameras};
use pipeline::consistency::WarpOptions;
use pipeline::fit_features::{FeatureOverrides, FitFeaturesSettings};
use pipeline::fit_geometry::{FitSettings, GeometryOverrides};
use pipeline::pretrain_decoder::{DecoderOverrides, NetworkFiles, PretrainSettings};
use pipeline::render::{DepthStyle, RenderKind, SceneInput};
use pipeline::{Control, RunOutcome};
use terminal::Terminal;
use train::Variant;

mod terminal;

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
    /// Measure multi-view consistency, style and content losses and stage timings.
    Eval(EvalArgs),
    /// Run the whole pipeline on the lego scene at low resolution: geometry, features, a
    /// stylized orbit with four unseen styles, its evaluation, a contact sheet and GIFs.
    Demo(DemoArgs),
}

/// How a training command runs: resume, checkpoints, logs and bars.
#[derive(Args)]
struct RunArgs {
    /// Continue from the checkpoint of a stopped run (the path it printed).
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Iterations between checkpoints [default: 500; 0: only when stopped].
    #[arg(long)]
    checkpoint_every: Option<u64>,
    /// Print a progress line every N iterations (for logs).
    #[arg(long)]
    log_every: Option<u64>,
    /// No progress bars.
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
    /// Canonical weights (.safetensors, encoder and decoder) instead of importing
    /// SHARED/weights/wct-relu1_1-3_1
    #[arg(long)]
    weights: Option<PathBuf>,
    /// A decoder (PyTorch checkpoint or .safetensors) instead of the one in the weights, e.g.
    /// one fine-tuned by `dsgs pretrain-decoder` for the fullres variant
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Network variant (fullres needs a decoder fine-tuned for it to stylize strongly)
    #[arg(long, default_value = "standard")]
    variant: Variant,
    /// Downscale factor of the 800x800 lego images
    #[arg(long, default_value_t = 8.0)]
    downscale: f64,
    /// Geometry iterations
    #[arg(long, default_value_t = 1000)]
    geometry_iterations: u64,
    /// Alignment-only feature iterations (cheap) before the full loss
    #[arg(long, default_value_t = 1500)]
    align_warmup: u64,
    /// Feature iterations with the full loss (alignment, content, style)
    #[arg(long, default_value_t = 300)]
    feature_iterations: u64,
    /// Style images (default: four paintings of SHARED/data/styles never used in training)
    #[arg(long = "style", num_args = 1..)]
    styles: Vec<PathBuf>,
    /// Frames of the orbit
    #[arg(long, default_value_t = 24)]
    frames: usize,
    /// No progress bars
    #[arg(long)]
    no_progress: bool,
}

#[derive(Subcommand)]
enum WeightsCommand {
    /// Convert PyTorch checkpoints (legacy pickle or zip) to one canonical safetensors file.
    Import {
        /// Encoder checkpoint (e.g. vgg_normalised.pth, vgg_normalised_conv3_1.pth, 4SE.pth).
        #[arg(long)]
        encoder: Option<PathBuf>,
        /// Decoder checkpoint (e.g. decoder.pth, feature_invertor_conv3_1.pth, 4SD.pth).
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

/// A parser accepting exactly `names`, listed in `--help` and in the error for any other value.
fn one_of<T>(names: &'static [&'static str]) -> impl TypedValueParser<Value = T>
where
    T: std::str::FromStr<Err = String> + Clone + Send + Sync + 'static,
{
    PossibleValuesParser::new(names).try_map(|s| s.parse::<T>())
}

fn vector3(s: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f64>()
                .map_err(|_| format!("`{x}` is not a number"))
        })
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [x, y, z] => Ok(DVec3::new(*x, *y, *z)),
        _ => Err(format!("expected three comma-separated numbers, got `{s}`")),
    }
}

#[derive(Args)]
struct FitGeometryArgs {
    /// Dataset directory (COLMAP, NeRF-synthetic or LLFF layout).
    dataset: PathBuf,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
    /// TOML configuration (train::GeometryConfig keys plus a `[dataset]` table); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Total iterations.
    #[arg(long)]
    iterations: Option<u64>,
    /// Resize the images by 1/F on load.
    #[arg(long, conflicts_with = "resolution")]
    downscale: Option<f64>,
    /// Read the images from the images_N folder.
    #[arg(long)]
    resolution: Option<u32>,
    /// White background (NeRF-synthetic scenes).
    #[arg(long)]
    white: bool,
    /// Iterations at which to evaluate the held-out views and save the scene (comma-separated).
    #[arg(long, value_delimiter = ',')]
    test_iterations: Option<Vec<u64>>,
    /// Iterations at which to save the scene, when they differ from the test iterations.
    #[arg(long, value_delimiter = ',')]
    save_iterations: Option<Vec<u64>>,
    /// Iterations at which to write a resumable checkpoint (comma-separated).
    #[arg(long, value_delimiter = ',')]
    checkpoint_iterations: Option<Vec<u64>>,
    /// Train on every image (no held-out split).
    #[arg(long)]
    no_eval: bool,
    /// Seed of every random choice.
    #[arg(long)]
    seed: Option<u64>,
    /// Maximum SH degree (0..=3).
    #[arg(long)]
    sh_degree: Option<usize>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Args)]
struct PretrainDecoderArgs {
    /// Content image folders or files.
    #[arg(long, required = true, num_args = 1..)]
    content: Vec<PathBuf>,
    /// Style image folders or files.
    #[arg(long = "style", required = true, num_args = 1..)]
    styles: Vec<PathBuf>,
    /// Search the image folders recursively.
    #[arg(long)]
    recursive: bool,
    /// Canonical weights (.safetensors) holding the encoder and, unless --from-scratch or
    /// --decoder, the starting decoder.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Encoder file (PyTorch checkpoint or .safetensors), instead of the one in --weights.
    #[arg(long)]
    encoder: Option<PathBuf>,
    /// Starting decoder (PyTorch checkpoint or .safetensors), instead of the one in --weights.
    #[arg(long, conflicts_with = "from_scratch")]
    decoder: Option<PathBuf>,
    /// Start from a seeded initialisation of the encoder's mirror image.
    #[arg(long)]
    from_scratch: bool,
    /// Network variant.
    #[arg(long)]
    variant: Option<Variant>,
    /// TOML configuration (train::DecoderTrainConfig keys); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Total iterations.
    #[arg(long)]
    iterations: Option<u64>,
    /// Content (and style) images per iteration.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Side of the square random crop.
    #[arg(long)]
    crop: Option<u32>,
    /// Short side the images are resized to before cropping.
    #[arg(long)]
    resize: Option<u32>,
    /// Weight of the style loss.
    #[arg(long)]
    style_weight: Option<f64>,
    /// Initial learning rate.
    #[arg(long)]
    lr: Option<f64>,
    /// Seed of every random choice.
    #[arg(long)]
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
    /// Style image folders or files.
    #[arg(long = "style", required = true, num_args = 1..)]
    styles: Vec<PathBuf>,
    /// Canonical weights (.safetensors) holding the encoder and decoder.
    #[arg(long)]
    weights: PathBuf,
    /// Use this decoder (PyTorch checkpoint or .safetensors) instead of the one in --weights.
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Network variant.
    #[arg(long)]
    variant: Option<Variant>,
    /// TOML configuration (train::FeatureTrainConfig keys, `background` and a `[dataset]` table);
    /// flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Total iterations.
    #[arg(long)]
    iterations: Option<u64>,
    /// Channels of each Gaussian's feature.
    #[arg(long)]
    feature_dim: Option<usize>,
    /// Resize the images by 1/F on load.
    #[arg(long)]
    downscale: Option<f64>,
    /// Train with the alignment loss only (no content and style terms).
    #[arg(long)]
    align_only: bool,
    /// Iterations at the start with the alignment loss only (cheap; gives the features the
    /// scene's content before the content and style terms join).
    #[arg(long)]
    align_warmup: Option<u64>,
    /// Seed of every random choice.
    #[arg(long)]
    seed: Option<u64>,
    /// Side of the feature-map window run through the networks, in feature pixels.
    #[arg(long)]
    crop: Option<u32>,
    /// White background (NeRF-synthetic scenes).
    #[arg(long)]
    white: bool,
    /// Train on every image (no held-out split).
    #[arg(long)]
    no_eval: bool,
    #[command(flatten)]
    run: RunArgs,
    /// Output directory (the bundle goes to OUT/bundle).
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args)]
struct BakeArgs {
    /// Scene bundle directory.
    bundle: PathBuf,
    /// Style image (repeat and give --weights to bake a mixture).
    #[arg(long = "style", required = true)]
    styles: Vec<PathBuf>,
    /// Mix the styles with these weights (comma-separated, one per style).
    #[arg(long, value_delimiter = ',')]
    weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0)]
    alpha: f64,
    /// Longest side of the style images after loading.
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE)]
    style_size: u32,
    /// Network variant (default: the bundle's).
    #[arg(long)]
    variant: Option<Variant>,
    /// Replace the bundle's decoder (.safetensors or a PyTorch checkpoint).
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// TOML configuration (train::BakeConfig keys); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Optimisation iterations.
    #[arg(long)]
    iterations: Option<u64>,
    /// SH degree that is optimised (0..=3; the .ply always stores degree 3).
    #[arg(long)]
    sh_degree: Option<usize>,
    /// Also adapt opacities and scales, within small budgets.
    #[arg(long)]
    adapt_geometry: bool,
    /// Adam rate of the SH DC coefficients.
    #[arg(long)]
    lr: Option<f64>,
    /// Number of training target views (0: all candidates).
    #[arg(long)]
    target_views: Option<usize>,
    /// Interpolated views held out for evaluation.
    #[arg(long)]
    held_out: Option<usize>,
    /// Image size of the targets relative to the bundle's cameras.
    #[arg(long)]
    resolution_scale: Option<f64>,
    /// Seed of the view order.
    #[arg(long)]
    seed: Option<u64>,
    #[command(flatten)]
    run: RunArgs,
    /// Output .ply (a JSON report is written beside it).
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args, Clone)]
struct CameraArgs {
    /// Camera source: the dataset's or bundle's cameras, the held-out ones, a path through
    /// them, or an orbit.
    #[arg(long, default_value = "orbit", value_parser = one_of::<CameraSource>(CameraSource::NAMES))]
    cameras: CameraSource,
    /// Number of frames (path and orbit), or at most this many cameras (dataset and test).
    #[arg(long)]
    frames: Option<usize>,
    /// Image width (alone: keeps the aspect ratio).
    #[arg(long)]
    width: Option<u32>,
    /// Image height (alone: keeps the aspect ratio).
    #[arg(long)]
    height: Option<u32>,
    /// Scale every camera's image by this factor.
    #[arg(long)]
    scale: Option<f64>,
    /// Take the cameras from this directory instead of the scene: a dataset, or a scene bundle
    /// (its cameras at its training size, e.g. to render a baked `.ply` from them).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// World up axis of orbits, as x,y,z (default: from the cameras, else -y).
    #[arg(long, value_parser = vector3, allow_hyphen_values = true)]
    up: Option<DVec3>,
}

impl CameraArgs {
    fn request(&self) -> CameraRequest {
        CameraRequest {
            source: self.cameras,
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
    #[arg(long, default_value = "color", value_parser = one_of::<RenderKind>(RenderKind::NAMES))]
    what: RenderKind,
    /// How depth is drawn.
    #[arg(long, default_value = "colour", value_parser = one_of::<DepthStyle>(DepthStyle::NAMES))]
    depth_style: DepthStyle,
    /// Output directory (frame_XXXX.png).
    #[arg(short, long)]
    output: PathBuf,
    /// No progress bar.
    #[arg(long)]
    no_progress: bool,
}

#[derive(Args)]
struct StyleArgs {
    /// Style image (repeat for several styles; at least one).
    #[arg(long = "style")]
    styles: Vec<PathBuf>,
    /// Mix the styles with these weights into one output (comma-separated, one per style).
    #[arg(long, value_delimiter = ',')]
    weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0)]
    alpha: f64,
    /// Keep the scene's colours (the style images are colour-matched to the colour renders).
    #[arg(long)]
    preserve_colour: bool,
    /// Longest side of the style images after loading.
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE)]
    style_size: u32,
    /// Network variant (default: the bundle's).
    #[arg(long)]
    variant: Option<Variant>,
    /// Replace the bundle's decoder (.safetensors or a PyTorch checkpoint).
    #[arg(long)]
    decoder: Option<PathBuf>,
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
    /// Frames per second of the animations.
    #[arg(long, default_value_t = 10.0)]
    fps: f64,
    /// Views (columns) in the contact sheet.
    #[arg(long, default_value_t = 4)]
    sheet_views: usize,
    /// No progress bar.
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
    /// the geometry of --scene (or of BUNDLE).
    #[arg(long)]
    frames_dir: Option<PathBuf>,
    /// The geometry for --frames-dir: a .ply file or a bundle directory.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Pixels with alpha at or below this are not compared.
    #[arg(long, default_value_t = 0.5)]
    alpha_threshold: f32,
    /// Relative depth tolerance of the occlusion test.
    #[arg(long, default_value_t = 0.02)]
    depth_tolerance: f64,
    /// Write the report as JSON.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    no_progress: bool,
}

fn main() -> ExitCode {
    keep_freed_memory();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if is_interrupted(&e) => {
            eprintln!("{e}");
            ExitCode::from(INTERRUPTED_EXIT)
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Asks glibc's allocator to serve allocations below 1 GiB from its heap and to keep up to
/// 2 GiB of freed memory there instead of returning it to the system. The stages allocate and
/// free tensors of tens of megabytes many times per iteration (a 256-channel 256x256 activation
/// is 64 MiB); by default each is mapped afresh, and the kernel faults in and clears every page
/// again. Measured on a 256->256 convolution at 256x256: 1.15x to 1.35x faster with this
/// setting, and the munmap calls of a benchmark run fell from 79 to 6 (`docs/performance.md`).
/// The cost is that the process keeps its peak heap until it exits.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; it is called before any other thread
    // exists, and a value it rejects leaves the default in place.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
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
/// [`INTERRUPTED_EXIT`]. A second signal exits at once.
fn stop_flag() -> Option<&'static AtomicBool> {
    static STOP: AtomicBool = AtomicBool::new(false);
    let installed = ctrlc::set_handler(|| {
        if STOP.swap(true, Ordering::SeqCst) {
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

/// Runs `f` with a terminal front end (bars unless `no_progress`) and the stop flag.
fn with_control<T>(no_progress: bool, f: impl FnOnce(&Control) -> Result<T>) -> Result<T> {
    let terminal = Terminal::new(!no_progress);
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
        Command::Bake(a) => bake(a)?,
        Command::Render(a) => render(a)?,
        Command::Stylize(a) => stylize(a)?,
        Command::Eval(a) => eval(a)?,
        Command::Demo(a) => demo(a)?,
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
    let r = with_control(a.run.no_progress, |c| {
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
    let r = with_control(a.run.no_progress, |c| {
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
            white: a.white,
            no_eval: a.no_eval,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
        },
    };
    let r = with_control(a.run.no_progress, |c| {
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
    finish(&r.run, Some(&r.checkpoint))
}

fn bake(a: BakeArgs) -> Result<()> {
    let settings = BakeSettings {
        bundle: a.bundle,
        styles: a.styles,
        weights: a.weights,
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
        },
        output: a.output,
        resume: a.run.resume,
    };
    let out = with_control(a.run.no_progress, |c| {
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
    let cams = pipeline::cameras::select(&a.cameras.request(), &known, scene.gaussians())?;
    let terminal = Terminal::new(!a.no_progress);
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
    let r = with_control(a.no_progress, |c| Ok(pipeline::demo::run(&settings, c)?))?;
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
    for p in r.stylized.gifs.iter().chain(&r.stylized.contact_sheet) {
        println!("wrote {}", p.display());
    }
    println!("wrote {}", r.eval_json.display());
    Ok(())
}

fn stylize(a: StylizeArgs) -> Result<()> {
    if a.style.styles.is_empty() {
        bail!("give at least one --style image to stylize with");
    }
    let bundle = bundle_with(&a.bundle, a.style.variant, a.style.decoder.as_deref())?;
    let known = a.cameras.known(KnownCameras::from_bundle(
        &bundle,
        &a.bundle.display().to_string(),
    ))?;
    let cams = pipeline::cameras::select(&a.cameras.request(), &known, &bundle.scene)?;
    let settings = pipeline::stylize::StylizeSettings {
        styles: a.style.styles,
        weights: a.style.weights,
        alpha: a.style.alpha,
        preserve_colour: a.style.preserve_colour,
        style_side: a.style.style_size,
        out_dir: a.output.clone(),
        gif: a.gif,
        mp4: a.mp4,
        fps: a.fps,
        sheet_views: a.sheet_views,
    };
    let terminal = Terminal::new(!a.no_progress);
    let out = pipeline::stylize::run(&bundle, &cams, &settings, &terminal)?;
    for (name, frames) in &out.outputs {
        println!(
            "{name}: {} frames in {}",
            frames.len(),
            a.output.join(name).display()
        );
    }
    for p in out.gifs.iter().chain(&out.mp4s).chain(&out.contact_sheet) {
        println!("wrote {}", p.display());
    }
    let s = out.seconds;
    println!(
        "seconds per view: raster {:.4}, lift+transform {:.4}, decode {:.4}",
        s.raster, s.lift_transform, s.decode
    );
    Ok(())
}

fn eval(a: EvalArgs) -> Result<()> {
    let warp = WarpOptions {
        alpha_threshold: a.alpha_threshold,
        depth_tolerance: a.depth_tolerance,
    };
    let terminal = Terminal::new(!a.no_progress);
    let report = if let Some(frames_dir) = &a.frames_dir {
        let scene_path = a
            .scene
            .as_ref()
            .or(a.bundle.as_ref())
            .context("--frames-dir needs the geometry: --scene PLY_OR_BUNDLE")?;
        let scene = SceneInput::open(scene_path)?;
        let known = a.cameras.known(scene.known_cameras())?;
        let cams = pipeline::cameras::select(&a.cameras.request(), &known, scene.gaussians())?;
        pipeline::eval::evaluate_frames(&scene, &cams, frames_dir, &warp, &terminal)?
    } else {
        let Some(dir) = &a.bundle else {
            bail!("give a scene bundle to evaluate (or --frames-dir DIR --scene SCENE)");
        };
        if a.style.styles.is_empty() {
            bail!("give at least one --style image to evaluate");
        }
        let bundle = bundle_with(dir, a.style.variant, a.style.decoder.as_deref())?;
        let known = a.cameras.known(KnownCameras::from_bundle(
            &bundle,
            &dir.display().to_string(),
        ))?;
        let cams = pipeline::cameras::select(&a.cameras.request(), &known, &bundle.scene)?;
        let settings = pipeline::eval::EvalSettings {
            styles: a.style.styles,
            weights: a.style.weights,
            alpha: a.style.alpha,
            preserve_colour: a.style.preserve_colour,
            style_side: a.style.style_size,
            warp,
        };
        let name = dir.display().to_string();
        pipeline::eval::evaluate_bundle(&bundle, &name, &cams, &settings, &terminal)?
    };
    print!("{}", pipeline::eval::table(&report));
    if let Some(p) = &a.output {
        pipeline::eval::write_report(p, &report)?;
        println!("report written to {}", p.display());
    }
    Ok(())
}
