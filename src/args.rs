//! The command line: a struct of arguments per command, the groups that several commands
//! flatten (`#[command(flatten)]`), and the parsing that adds the configurations' defaults to
//! the help of the run flags and a tip to the error of a stray value.
//!
//! The flags that fill a pipeline's settings directly (the configuration overrides, whole
//! settings of some commands, the network files, the camera flags, the warp thresholds) are
//! declared by the pipeline beside those settings ([`pipeline::cli`]); this file declares the
//! rest, in the order `--help` lists them.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, CommandFactory, FromArgMatches, Parser, Subcommand};
use pipeline::bake::BakeOverrides;
use pipeline::cameras::CameraArgs;
use pipeline::cli::{
    at_least_one, background, decoder_mode, feature_norm, fraction, mebibytes, non_negative,
    one_of_or_alias, positive, renamed_to_mix, variant, with_default, BAKE_CONFIG_HELP,
    CONFIG_HELP,
};
use pipeline::consistency::WarpOptions;
use pipeline::demo::DemoSettings;
use pipeline::fit_features::{DatasetArg, FeatureOverrides, FitFeaturesConfig};
use pipeline::fit_geometry::{FitGeometryConfig, FitSettings};
use pipeline::pretrain_decoder::DecoderOverrides;
use pipeline::render::{DepthStyle, RenderKind, SceneArg};
use pipeline::shard::{Invocation, Part, Shard};
use pipeline::stylize_image::StylizeImageSettings;
use train::{BakeConfig, DecoderMode, DecoderTrainConfig, FeatureNorm, Variant};

/// Zero-shot 3D style transfer on Gaussian splatting (DS-StyleGaussian), exact and CPU-only.
#[derive(Parser)]
#[command(name = "dsgs", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
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
    /// From a capture and paintings to a stylized tour in one resumable command: geometry,
    /// features, stylized frames and GIFs along a smooth tour, a contact sheet, the evaluation.
    Run(RunPipelineArgs),
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

#[derive(Subcommand)]
pub enum WeightsCommand {
    /// Convert PyTorch checkpoints (legacy pickle or zip) to one canonical safetensors file.
    Import {
        /// Encoder checkpoint (e.g. vgg_normalised.pth, vgg_normalised_conv3_1.pth, 4SE.pth), or a
        /// canonical .safetensors file whose encoder is taken [default: none]
        #[arg(long)]
        encoder: Option<PathBuf>,
        /// Decoder checkpoint (e.g. decoder.pth, feature_invertor_conv3_1.pth, 4SD.pth), or a
        /// canonical .safetensors file whose decoder is taken [default: none]
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

// ---- Groups shared by several commands ----

/// How a training command runs: resume, checkpoints, logs and bars. The defaults of
/// `--checkpoint-every` and `--log-every` are each command's configuration's, added to their help
/// by [`command`].
#[derive(Args)]
pub struct RunArgs {
    /// Continue from the checkpoint of a stopped run (the path it printed) [default: none, a
    /// fresh run]
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// Iterations between checkpoints (0: only when stopped)
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Print a progress line every N iterations, for logs (0: none)
    #[arg(long)]
    pub log_every: Option<u64>,
    /// No progress bars (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

/// `--shard K/N`, shared by the commands that can be split over processes.
#[derive(Args, Clone)]
pub struct ShardArgs {
    /// Run only shard K of N (K from 1 to N): a contiguous block of the frames (of a bake: of
    /// its stylized target views), written as the whole run writes them, and a manifest written
    /// last; merge the finished shards with `dsgs assemble OUTPUT` [default: the whole run]
    #[arg(long, value_name = "K/N", value_parser = clap::value_parser!(Shard))]
    shard: Option<Shard>,
}

impl ShardArgs {
    /// The part of the run: the whole, or this shard with the command line that made it.
    pub fn part(&self) -> Result<Part> {
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
    let args = pipeline::shard::args_without_shard(std::env::args_os().skip(1))?;
    let cwd = std::env::current_dir().context("reading the working directory")?;
    Ok(Invocation { args, cwd })
}

/// The style images' size and the networks of a scene bundle as a stylization runs them
/// (stylize, eval, bake). The networks are the bundle's: `--weights`, a network weights file
/// elsewhere, is refused, pointing to `--mix` (what it once meant here).
#[derive(Args)]
pub struct BundleStyleArgs {
    #[arg(long = "weights", hide = true, value_parser = renamed_to_mix)]
    _weights: Option<String>,
    /// Longest side of the style images after loading, in pixels (at least 1).
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE, value_parser = at_least_one::<u32>())]
    pub style_size: u32,
    /// Network variant: `standard` (pooling and upsampling) or `fullres` (neither), for the
    /// paper's standard-against-fullres ablation [default: the bundle's]
    #[arg(long, value_parser = variant())]
    pub variant: Option<Variant>,
    /// Replace the bundle's decoder (.safetensors or a PyTorch checkpoint), e.g. the 2D decoder
    /// before fine-tuning; not for bundles whose decoder was trained with their features
    /// (fit-features --decoder-mode scratch or mlp). Where the features are normalised
    /// (fit-features --normalize) is the bundle's [default: the bundle's decoder]
    #[arg(long)]
    pub decoder: Option<PathBuf>,
}

/// The style flags of `stylize` and `eval`.
#[derive(Args)]
pub struct StyleArgs {
    /// Style image or folder of them; repeat for several (at least one).
    #[arg(long = "style")]
    pub styles: Vec<PathBuf>,
    /// Mix the styles into one output with these weights (comma-separated, one per style image,
    /// each 0 or more, not all 0) [default: none: one output per style]
    #[arg(long, value_delimiter = ',', value_parser = non_negative)]
    pub mix: Option<Vec<f64>>,
    /// Style strength, in [0, 1]: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0, value_parser = fraction)]
    pub alpha: f64,
    /// Keep the scene's colours (the style images are colour-matched to the colour renders).
    #[arg(long, alias = "preserve-color")]
    pub preserve_colour: bool,
    #[command(flatten)]
    pub bundle: BundleStyleArgs,
    /// Working memory of the networks per frame, in MiB: frames are decoded in tiles that fit
    /// it (any budget gives the same images; 1 to 1048576).
    #[arg(long, default_value_t = runtime::DEFAULT_TILE_BUDGET_BYTES >> 20, value_parser = mebibytes())]
    pub tile_budget: u64,
}

// ---- Commands ----

#[derive(Args)]
pub struct FitGeometryArgs {
    #[command(flatten)]
    pub settings: FitSettings,
    #[command(flatten)]
    pub run: RunArgs,
}

#[derive(Args)]
pub struct PretrainDecoderArgs {
    /// Content image folder or file; repeat for several (at least one).
    #[arg(long, required = true)]
    pub content: Vec<PathBuf>,
    /// Style image folder or file; repeat for several (at least one).
    #[arg(long = "style", required = true)]
    pub styles: Vec<PathBuf>,
    /// Search the image folders recursively.
    #[arg(long)]
    pub recursive: bool,
    /// Held-out content images for the evaluation curve (folder or file; repeat for several;
    /// with --eval-style) [default: the training images]
    #[arg(long = "eval-content", requires = "eval_styles")]
    pub eval_content: Vec<PathBuf>,
    /// Held-out style images for the evaluation curve (folder or file; repeat for several;
    /// with --eval-content) [default: the training images]
    #[arg(long = "eval-style", requires = "eval_content")]
    pub eval_styles: Vec<PathBuf>,
    /// Canonical network weights (.safetensors) holding the encoder and, unless --from-scratch
    /// or --decoder, the starting decoder [default: none: give --encoder and --decoder]
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Encoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Starting decoder (PyTorch checkpoint or .safetensors) [default: the one in --weights]
    #[arg(long, conflicts_with = "from_scratch")]
    pub decoder: Option<PathBuf>,
    /// Start from a seeded initialisation of the encoder's mirror image.
    #[arg(long)]
    pub from_scratch: bool,
    /// Encoder that measures the style loss at each of its relu_k_1 levels instead of the
    /// encoder (PyTorch checkpoint or .safetensors; e.g. the real VGG-19 to relu3_1 for the
    /// compressed relu4_1 encoder); give it again when resuming [default: the encoder]
    #[arg(long = "style-network", value_name = "ENCODER")]
    pub style_network: Option<PathBuf>,
    #[arg(long, value_parser = variant(), help = with_default(
        "Network variant",
        DecoderTrainConfig::default().variant.as_str(),
    ))]
    pub variant: Option<Variant>,
    #[arg(long, help = CONFIG_HELP)]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: DecoderOverrides,
    #[command(flatten)]
    pub run: RunArgs,
    /// Output directory.
    #[arg(short, long)]
    pub output: PathBuf,
}

#[derive(Args)]
pub struct FitFeaturesArgs {
    #[command(flatten)]
    pub dataset: DatasetArg,
    /// The trained geometry (.ply).
    #[arg(long)]
    pub geometry: PathBuf,
    /// Style image folder or file; repeat for several (at least one).
    #[arg(long = "style", required = true)]
    pub styles: Vec<PathBuf>,
    /// Paintings never trained on, for the evaluation of held-out views (folder or file; repeat
    /// for several) [default: the --style images]
    #[arg(long = "eval-style")]
    pub eval_styles: Vec<PathBuf>,
    #[arg(long, help = with_default(
        "Iterations between evaluations of the stage-3 loss on fixed held-out samples (the \
         held-out views with --eval-style paintings; training views with --no-eval), also made \
         before the first iteration and at the end; 0: only those two",
        FitFeaturesConfig::default().features.eval_interval,
    ))]
    pub eval_every: Option<u64>,
    /// Canonical network weights (.safetensors) holding the encoder and decoder.
    #[arg(long)]
    pub weights: PathBuf,
    /// A decoder (PyTorch checkpoint or .safetensors) replacing the one in --weights [default:
    /// the one in --weights]
    #[arg(long)]
    pub decoder: Option<PathBuf>,
    #[arg(long, value_parser = variant(), help = with_default(
        "Network variant",
        FitFeaturesConfig::default().features.variant.as_str(),
    ))]
    pub variant: Option<Variant>,
    /// The decoder of stage 3, for the paper's decoder ablation: `pretrained` (the frozen 2D
    /// decoder of --weights/--decoder, the paper's design), `scratch` (the same CNN initialised
    /// from --seed and trained here with the features) or `mlp` (a per-pixel MLP, features ->
    /// 256 -> 128 -> RGB, trained here; needs --variant fullres). The bundle keeps the trained
    /// decoder [default: pretrained]
    #[arg(long, value_parser = decoder_mode())]
    pub decoder_mode: Option<DecoderMode>,
    #[arg(long, value_parser = positive, help = with_default(
        "Adam learning rate of a decoder trained in stage 3 (--decoder-mode scratch or mlp; \
         above 0)",
        FitFeaturesConfig::default().features.lr_decoder,
    ))]
    pub lr_decoder: Option<f64>,
    /// Where the features are normalised, for the paper's consistency ablation:
    /// `before-raster` (each view's encoder feature is normalised, then distilled into the
    /// Gaussians, so every view gets the same style transform: the paper's design) or
    /// `after-raster` (unnormalised features are distilled, and each rendered view is
    /// normalised with its own statistics before the transform, as 2D AdaIN does). The bundle
    /// records it and stylization follows it [default: before-raster]
    #[arg(long, value_parser = feature_norm())]
    pub normalize: Option<FeatureNorm>,
    #[arg(long, help = CONFIG_HELP)]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: FeatureOverrides,
    /// Do not keep the view and style encodings in OUT/encodings/ (they take about as much disk
    /// as memory; without them a resumed or repeated run encodes everything again).
    #[arg(long)]
    pub no_encoding_cache: bool,
    #[command(flatten)]
    pub run: RunArgs,
    /// Output directory (the bundle goes to OUT/bundle).
    #[arg(short, long)]
    pub output: PathBuf,
}

#[derive(Args)]
pub struct BakeArgs {
    /// Scene bundle directory.
    pub bundle: PathBuf,
    /// Style image or folder of them; repeat for several, mixed with --mix into one (at least
    /// one).
    #[arg(long = "style", required = true)]
    pub styles: Vec<PathBuf>,
    /// Mix the styles with these weights (comma-separated, one per style image, each 0 or more, not
    /// all 0) [default: none; needed with several styles]
    #[arg(long, value_delimiter = ',', value_parser = non_negative)]
    pub mix: Option<Vec<f64>>,
    /// Style strength, in [0, 1]: 0 reconstructs the scene, 1 is the full style.
    #[arg(long, default_value_t = 1.0, value_parser = fraction)]
    pub alpha: f64,
    #[command(flatten)]
    pub style: BundleStyleArgs,
    #[arg(long, help = BAKE_CONFIG_HELP)]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub overrides: BakeOverrides,
    #[command(flatten)]
    pub shard: ShardArgs,
    #[command(flatten)]
    pub run: RunArgs,
    /// Output .ply (a JSON report is written beside it).
    #[arg(short, long)]
    pub output: PathBuf,
}

#[derive(Args)]
pub struct RenderArgs {
    #[command(flatten)]
    pub scene: SceneArg,
    #[command(flatten)]
    pub cameras: CameraArgs,
    /// What to draw.
    #[arg(long, default_value = "colour", value_parser = one_of_or_alias::<RenderKind>(RenderKind::NAMES, RenderKind::ALIASES))]
    pub what: RenderKind,
    /// How depth is drawn.
    #[arg(long, default_value = "colour", value_parser = one_of_or_alias::<DepthStyle>(DepthStyle::NAMES, DepthStyle::ALIASES))]
    pub depth_style: DepthStyle,
    /// Background of colour renders: white, black or R,G,B in [0, 1] [default: a bundle's
    /// training background; black for a .ply]
    #[arg(long, value_parser = background)]
    pub background: Option<[f32; 3]>,
    /// Output directory (frame_XXXX.png).
    #[arg(short, long)]
    pub output: PathBuf,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

#[derive(Args)]
pub struct StylizeArgs {
    /// Scene bundle directory.
    pub bundle: PathBuf,
    #[command(flatten)]
    pub style: StyleArgs,
    #[command(flatten)]
    pub cameras: CameraArgs,
    /// Output directory.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write an animated GIF per style.
    #[arg(long)]
    pub gif: bool,
    /// Also write an MP4 per style (needs ffmpeg on PATH).
    #[arg(long)]
    pub mp4: bool,
    /// Frames per second of the animations (above 0).
    #[arg(long, default_value_t = 10.0, value_parser = positive)]
    pub fps: f64,
    /// Views (columns) in the contact sheet (at least 1).
    #[arg(long, default_value_t = 4, value_parser = at_least_one::<usize>())]
    pub sheet_views: usize,
    #[command(flatten)]
    pub shard: ShardArgs,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

#[derive(Args)]
pub struct StylizeImageArgs {
    #[command(flatten)]
    pub settings: StylizeImageSettings,
    /// No progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Output directory.
    #[arg(short, long)]
    pub output: PathBuf,
}

#[derive(Args)]
pub struct EvalArgs {
    /// Scene bundle directory (to render and evaluate stylized sequences).
    pub bundle: Option<PathBuf>,
    #[command(flatten)]
    pub style: StyleArgs,
    #[command(flatten)]
    pub cameras: CameraArgs,
    /// Evaluate the existing frames (*.png in name order) of this directory instead, against
    /// the geometry of --scene (or of BUNDLE) [default: none: render BUNDLE's frames]
    #[arg(long)]
    pub frames_dir: Option<PathBuf>,
    /// The geometry for --frames-dir: a .ply file or a bundle directory [default: BUNDLE]
    #[arg(long)]
    pub scene: Option<PathBuf>,
    #[command(flatten)]
    pub warp: WarpOptions,
    /// Write the report as JSON [default: none: the table only]
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Leave out the per-frame 2D baseline (`2d:STYLE`: each colour render stylized on its own
    /// by the bundle's encoder, AdaIN and decoder), which costs one whole-frame decode per view
    /// and style
    #[arg(long)]
    pub no_baseline: bool,
    /// Also write every frame (colour, 2D baseline, dsgs) under this folder, and the sheet
    /// `comparison.png` of them: colour | 2D per-frame | dsgs for each painting, the same views
    /// [default: none: no frames]
    #[arg(long)]
    pub frames_out: Option<PathBuf>,
    /// Measure the losses and perceptual distances with this encoder (weights .safetensors or
    /// PyTorch checkpoint; at standard resolution) instead of the bundle's, so that bundles of
    /// different networks compare [default: the bundle's encoder]
    #[arg(long, value_name = "ENCODER")]
    pub measure_with: Option<PathBuf>,
    #[command(flatten)]
    pub shard: ShardArgs,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

#[derive(Args)]
pub struct RunPipelineArgs {
    #[command(flatten)]
    pub settings: pipeline::run::RunSettings,
    /// No progress bars (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
    /// Start at once, without timing a few steps of each stage to estimate the run's time
    #[arg(long)]
    pub no_estimate: bool,
}

#[derive(Args)]
pub struct DemoArgs {
    #[command(flatten)]
    pub settings: DemoSettings,
    /// No progress bars (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

#[derive(Args)]
pub struct AssembleArgs {
    /// The sharded run's output: the folder of `stylize -o`, the report of `eval -o`, or the
    /// .ply of `bake -o`.
    pub output: PathBuf,
    /// Bake: continue the fit from this checkpoint of a stopped assembly (as `bake --resume`)
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// No progress bar (a plain progress line at least every minute instead)
    #[arg(long)]
    pub no_progress: bool,
}

#[derive(Args)]
pub struct ViewArgs {
    /// The scene: a scene bundle directory (stylizable) or any 3DGS .ply file.
    pub scene: PathBuf,
    /// Style image (or folder of them) offered in the page; repeat for several (the page can
    /// upload more).
    #[arg(long = "style")]
    pub styles: Vec<PathBuf>,
    /// Port to listen on (0: any free port).
    #[arg(long, default_value_t = 8080)]
    pub port: u16,
    /// Address to listen on. The default, 127.0.0.1, is reachable from this machine only.
    /// Another address (e.g. 0.0.0.0) lets every machine that can reach it see the scene and
    /// its cameras, upload images, and spend this machine's CPU on stylizations and bakes.
    #[arg(long, default_value = "127.0.0.1")]
    pub bind: std::net::IpAddr,
    /// Longest side of the style images after loading, in pixels (at least 1).
    #[arg(long, default_value_t = pipeline::stylize::DEFAULT_STYLE_SIDE, value_parser = at_least_one::<u32>())]
    pub style_size: u32,
    /// Working memory of the networks per stylized view, in MiB (1 to 1048576).
    #[arg(long, default_value_t = runtime::DEFAULT_TILE_BUDGET_BYTES >> 20, value_parser = mebibytes())]
    pub tile_budget: u64,
    /// Most pixels (width x height) of an uploaded style image, read from its header before
    /// decoding (at least 1).
    #[arg(long, default_value_t = viewer::ViewerConfig::new("").max_upload_pixels, value_parser = at_least_one::<u64>())]
    pub max_upload_pixels: u64,
    /// Memory that the work in flight (uploads being decoded, stylizations running or waiting)
    /// may take by estimate, in MiB; a request beyond it is answered 503 (1 to 1048576).
    #[arg(long, default_value_t = viewer::ViewerConfig::new("").memory_budget >> 20, value_parser = mebibytes())]
    pub memory_budget: u64,
}

// ---- Parsing ----

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
pub fn command() -> clap::Command {
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
    cmd = pipeline::cameras::with_default_sources(cmd);
    cmd.mut_subcommand("stylize", |sub| sub.mut_arg("styles", |a| a.required(true)))
}

/// Parses the process's arguments, or exits with clap's message.
pub fn parse() -> Cli {
    let parsed = command()
        .try_get_matches()
        .and_then(|m| Cli::from_arg_matches(&m));
    match parsed {
        Ok(cli) => cli,
        Err(e) => {
            let sub = std::env::args()
                .nth(1)
                .and_then(|n| command().find_subcommand(&n).cloned());
            pipeline::cli::with_repeat_tip(e, sub.as_ref()).exit()
        }
    }
}

/// Parses a command line recorded without the program's name (a shard's, for `dsgs assemble`).
pub fn parse_recorded(args: Vec<String>) -> Result<Cli, clap::Error> {
    command()
        .try_get_matches_from(std::iter::once("dsgs".to_string()).chain(args))
        .and_then(|m| Cli::from_arg_matches(&m))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_is_consistent() {
        // clap's own checks: unique names, valid defaults, existing ids in `mut_arg`.
        command().debug_assert();
    }
}
