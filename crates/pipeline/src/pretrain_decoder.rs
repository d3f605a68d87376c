//! `dsgs pretrain-decoder`: AdaIN decoder training on folders of content photographs and style
//! images, against a frozen encoder (`train::decoder_training`).
//!
//! Networks: the encoder comes from `--encoder` (a PyTorch checkpoint or canonical file) or from
//! the canonical `--weights` file; the starting decoder from `--decoder`, from `--weights`, or,
//! with `--from-scratch`, from the seeded initialisation of the encoder's mirror image
//! (`train::decoder_training::init_decoder`). When resuming, the decoder comes from the
//! checkpoint.
//!
//! Configuration: the keys of `train::DecoderTrainConfig` (TOML). The base is `--config FILE`
//! when given, otherwise, when resuming, the `config.toml` of the output directory if there is
//! one, otherwise the defaults; flags override it ([`DecoderOverrides`]) and the effective
//! configuration is written to `OUT/config.toml` before training starts.
//!
//! Inputs are checked before anything is written: every content and style image is decoded
//! once up front (reported as `Stage::Prepare` progress), so a bad file is named in seconds,
//! not when training first draws it.
//!
//! Evaluation: the held-out loss is measured on `eval_pairs` fixed (content, style) pairs,
//! drawn from `--eval-content` and `--eval-style` when given (images training never sees),
//! otherwise from the training images.
//!
//! Outputs: `OUT/decoder.safetensors` (encoder and trained decoder, canonical weights: those of
//! the last checkpoint while training runs, the final ones when it completes),
//! `OUT/checkpoint.safetensors`, written at the checkpoint interval and again at the end, so a
//! finished run can be continued with more iterations, and `OUT/evaluations.tsv`, the held-out
//! curve of the whole run across resumptions.

use std::path::PathBuf;

use crate::cli::{at_least_one, non_negative, with_default};
use crate::error::{bail, Context, Result};
use nets::{Decoder, Encoder};
use train::decoder_training::{init_decoder, DecoderEvaluation, DECODER_CHECKPOINT_FILE};
use train::{DecoderTrainConfig, DecoderTrainer, ImageSet, Variant};

use crate::{config, Control, Stage, Tally};
use train::RunOutcome;

/// Where the networks come from: a canonical file holding both, and/or separate files (either
/// canonical or PyTorch checkpoints) that take precedence over it.
///
/// As [`clap::Args`], the flags `--weights`, `--encoder` and `--decoder` of a command that
/// stylizes with these networks as they are (`dsgs stylize-image`).
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct NetworkFiles {
    /// Canonical weights (`.safetensors`) holding the encoder and decoder (`--weights`).
    #[arg(
        long,
        help = "Canonical network weights (.safetensors) holding the encoder and decoder \
                [default: none: give --encoder and --decoder]"
    )]
    pub weights: Option<PathBuf>,
    /// Encoder file, a PyTorch checkpoint or `.safetensors`, instead of the one in `weights`
    /// (`--encoder`).
    #[arg(
        long,
        help = "Encoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights]"
    )]
    pub encoder: Option<PathBuf>,
    /// Decoder file, a PyTorch checkpoint or `.safetensors`, instead of the one in `weights`
    /// (`--decoder`); with neither, the built-in decoder of the relu4_1 pair
    /// ([`crate::weights::BUILT_IN_DECODER`]).
    #[arg(
        long,
        help = "Decoder file (PyTorch checkpoint or .safetensors) [default: the one in --weights; \
                without --weights, the built-in decoder of the compressed relu4_1 encoder]"
    )]
    pub decoder: Option<PathBuf>,
}

impl NetworkFiles {
    /// The encoder: from `encoder` if given, else from `weights`.
    pub fn load_encoder(&self) -> Result<Encoder<f32>> {
        let path = self
            .encoder
            .as_ref()
            .or(self.weights.as_ref())
            .context("no encoder given: use --weights NETS.safetensors or --encoder FILE")?;
        crate::weights::load_any(path)
            .with_context(|| format!("reading the encoder {}", path.display()))?
            .encoder
            .with_context(|| format!("{} holds no encoder", path.display()))
    }

    /// The decoder: from `decoder` if given, else from `weights`, else the built-in decoder of
    /// the relu4_1 pair.
    pub fn load_decoder(&self) -> Result<Decoder<f32>> {
        let Some(path) = self.decoder.as_ref().or(self.weights.as_ref()) else {
            return crate::weights::built_in_decoder();
        };
        crate::weights::load_any(path)
            .with_context(|| format!("reading the decoder {}", path.display()))?
            .decoder
            .with_context(|| format!("{} holds no decoder", path.display()))
    }
}

/// Command-line values that override the configuration.
///
/// As [`clap::Args`], the flags from `--iterations` to `--seed`; `--variant`, shown before the
/// configuration file, and the two run intervals (`--checkpoint-every`, `--log-every`) are the
/// program's to declare.
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct DecoderOverrides {
    /// Total iterations (`--iterations`; key `iterations`).
    #[arg(long, value_parser = at_least_one::<u64>(), help = with_default(
        "Total iterations (at least 1)",
        DecoderTrainConfig::default().iterations,
    ))]
    pub iterations: Option<u64>,
    /// Content (and style) images per iteration (`--batch-size`; key `batch_size`).
    #[arg(long, value_parser = at_least_one::<usize>(), help = with_default(
        "Content (and style) images per iteration (at least 1)",
        DecoderTrainConfig::default().batch_size,
    ))]
    pub batch_size: Option<usize>,
    /// Side of the square random crop (`--crop`; key `crop`).
    #[arg(long, value_parser = at_least_one::<u32>(), help = with_default(
        "Side of the square random crop, in pixels (at least 1, at most --resize)",
        DecoderTrainConfig::default().crop,
    ))]
    pub crop: Option<u32>,
    /// Short side the images are resized to before cropping (`--resize`; key `resize`).
    #[arg(long, value_parser = at_least_one::<u32>(), help = with_default(
        "Short side the images are resized to before cropping, in pixels (at least 1)",
        DecoderTrainConfig::default().resize,
    ))]
    pub resize: Option<u32>,
    /// Weight of the style loss (`--style-weight`; key `style_weight`).
    #[arg(long, value_parser = non_negative, help = with_default(
        "Weight of the style loss (0 or more)",
        DecoderTrainConfig::default().style_weight,
    ))]
    pub style_weight: Option<f64>,
    /// Initial learning rate (`--lr`; key `lr`).
    #[arg(long, value_parser = non_negative, help = with_default(
        "Initial learning rate (0 or more)",
        DecoderTrainConfig::default().lr,
    ))]
    pub lr: Option<f64>,
    /// Seed of every random choice (`--seed`; key `seed`).
    #[arg(long, help = with_default(
        "Seed of every random choice",
        DecoderTrainConfig::default().seed,
    ))]
    pub seed: Option<u64>,
    /// Network variant (`--variant`; key `variant`).
    #[arg(skip)]
    pub variant: Option<Variant>,
    /// Iterations between log lines (`--log-every`; key `log_interval`).
    #[arg(skip)]
    pub log_every: Option<u64>,
    /// Iterations between checkpoints, 0 for only when stopped (`--checkpoint-every`; key
    /// `checkpoint_interval`).
    #[arg(skip)]
    pub checkpoint_every: Option<u64>,
}

impl DecoderOverrides {
    /// Applies the overrides.
    pub fn apply(&self, c: &mut DecoderTrainConfig) {
        if let Some(v) = self.iterations {
            c.iterations = v;
        }
        if let Some(v) = self.batch_size {
            c.batch_size = v;
        }
        if let Some(v) = self.crop {
            c.crop = v;
        }
        if let Some(v) = self.resize {
            c.resize = v;
        }
        if let Some(v) = self.style_weight {
            c.style_weight = v;
        }
        if let Some(v) = self.lr {
            c.lr = v;
        }
        if let Some(v) = self.seed {
            c.seed = v;
        }
        if let Some(v) = self.variant {
            c.variant = v;
        }
        if let Some(v) = self.log_every {
            c.log_interval = v;
        }
        if let Some(k) = self.checkpoint_every {
            c.checkpoint_interval = k;
        }
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct PretrainSettings {
    /// Content image folders and/or files.
    pub content: Vec<PathBuf>,
    /// Style image folders and/or files.
    pub styles: Vec<PathBuf>,
    /// Search the folders recursively.
    pub recursive: bool,
    /// Held-out content images for the evaluation (`--eval-content`; empty: the training
    /// images). Given together with `eval_styles`.
    pub eval_content: Vec<PathBuf>,
    /// Held-out style images for the evaluation (`--eval-style`; empty: the training images).
    pub eval_styles: Vec<PathBuf>,
    /// The frozen encoder and the starting decoder (`--weights`, `--encoder`, `--decoder`).
    pub networks: NetworkFiles,
    /// Start from a seeded initialisation instead of a decoder file.
    pub from_scratch: bool,
    /// The encoder that measures the style term instead of the frozen encoder
    /// (`--style-network`; see [`train::DecoderTrainer::with_style_network`]).
    pub style_network: Option<PathBuf>,
    /// Output directory (`--output`).
    pub out_dir: PathBuf,
    /// Base configuration file (`--config`): `train::DecoderTrainConfig` keys.
    pub config: Option<PathBuf>,
    /// Continue from this checkpoint of a stopped run (`--resume`).
    pub resume: Option<PathBuf>,
    /// Command-line values applied on top of the configuration.
    pub overrides: DecoderOverrides,
}

/// What a run did.
#[derive(Clone, Debug)]
pub struct PretrainReport {
    /// The effective configuration, as saved to `OUT/config.toml`.
    pub config: DecoderTrainConfig,
    /// Content images found.
    pub content_images: usize,
    /// Style images found.
    pub style_images: usize,
    /// How the run ended; its output is `OUT/decoder.safetensors` when it completed.
    pub run: RunOutcome,
    /// The held-out evaluations of this run (every `eval_interval` iterations and at the end).
    pub evaluations: Vec<DecoderEvaluation>,
    /// `OUT/checkpoint.safetensors`.
    pub checkpoint: PathBuf,
}

/// The summary of a run, a line each: the images and networks, then every evaluation (how
/// the run ended is [`PretrainReport::run`]'s to tell).
impl std::fmt::Display for PretrainReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} content and {} style images, {} networks, crops of {} px",
            self.content_images,
            self.style_images,
            self.config.variant.as_str(),
            self.config.crop
        )?;
        for e in &self.evaluations {
            writeln!(
                f,
                "iteration {}: evaluation loss {:.5} (content {:.5}, style {:.5}, {} pairs)",
                e.step, e.loss, e.loss_content, e.loss_style, e.pairs
            )?;
        }
        Ok(())
    }
}

/// The effective configuration of a run (base configuration plus overrides).
pub fn effective_config(settings: &PretrainSettings) -> Result<DecoderTrainConfig> {
    config::effective(
        settings.config.as_deref(),
        settings.resume.is_some(),
        &settings.out_dir,
        |c| settings.overrides.apply(c),
    )
}

/// Opens an image set, naming the role (`content` or `style`) in errors.
pub fn open_images(sources: &[PathBuf], recursive: bool, role: &str) -> Result<ImageSet> {
    let list = sources
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    ImageSet::open(sources, recursive)
        .with_context(|| format!("opening the {role} images ({list})"))
}

/// Decodes every image of the sets (each named by its role in errors), reported as
/// `Stage::Prepare` progress.
fn decode_inputs(sets: &[(&ImageSet, &str)], control: &Control) -> Result<()> {
    let total = sets.iter().map(|(s, _)| s.len()).sum();
    let mut tally = Tally::start(Stage::Prepare, total, control.sink);
    for (set, role) in sets {
        let status = format!("decode {role} images");
        let mut decoded = 0;
        set.check_decodes(&mut |done| {
            tally.advance(done - decoded, &status);
            decoded = done;
        })
        .with_context(|| format!("decoding the {role} images"))?;
    }
    tally.finish();
    Ok(())
}

/// Trains the decoder, reporting to the control's sink. A stop request ends the run after the
/// current iteration with a checkpoint of it ([`RunOutcome::stop_checkpoint`]).
pub fn run(settings: &PretrainSettings, control: &Control) -> Result<PretrainReport> {
    let cfg = effective_config(settings)?;
    let content = open_images(&settings.content, settings.recursive, "content")?;
    let styles = open_images(&settings.styles, settings.recursive, "style")?;
    let (n_content, n_style) = (content.len(), styles.len());
    let held_out = match (
        settings.eval_content.is_empty(),
        settings.eval_styles.is_empty(),
    ) {
        (true, true) => None,
        (false, false) => Some((
            open_images(
                &settings.eval_content,
                settings.recursive,
                "held-out content",
            )?,
            open_images(&settings.eval_styles, settings.recursive, "held-out style")?,
        )),
        _ => bail!("held-out images need both --eval-content and --eval-style"),
    };
    let mut sets = vec![(&content, "content"), (&styles, "style")];
    if let Some((c, s)) = &held_out {
        sets.extend([(c, "held-out content"), (s, "held-out style")]);
    }
    decode_inputs(&sets, control)?;
    let encoder = settings.networks.load_encoder()?;
    let style_network = match &settings.style_network {
        Some(path) => Some(
            crate::weights::load_any(path)
                .with_context(|| format!("reading the style network {}", path.display()))?
                .encoder
                .with_context(|| format!("{} holds no encoder", path.display()))?,
        ),
        None => None,
    };
    // Every input is read before anything is written.
    let decoder = match (&settings.resume, settings.from_scratch) {
        (Some(_), _) => None,
        (None, true) => Some(
            init_decoder(&encoder, cfg.seed).context("initialising a decoder for the encoder")?,
        ),
        (None, false) => {
            let n = &settings.networks;
            if n.decoder.is_none() && n.weights.is_none() {
                bail!(
                    "no starting decoder: give --decoder FILE, --weights NETS.safetensors or \
                     --from-scratch"
                );
            }
            Some(n.load_decoder()?)
        }
    };
    config::save(&cfg, &settings.out_dir)?;
    let mut trainer = match (decoder, &settings.resume) {
        (Some(decoder), _) => {
            let t = DecoderTrainer::new(encoder, decoder, content, styles, cfg.clone())
                .context("setting up decoder training")?;
            match style_network {
                Some(n) => t
                    .with_style_network(n)
                    .context("setting up the style network")?,
                None => t,
            }
        }
        (None, resume) => {
            let ck = resume.as_ref().context("no starting decoder")?;
            DecoderTrainer::resume_with_style_network(
                ck,
                encoder,
                style_network,
                content,
                styles,
                cfg.clone(),
            )
            .with_context(|| format!("resuming from {}", ck.display()))?
        }
    };
    if let Some((c, s)) = &held_out {
        trainer = trainer
            .with_eval_images(c, s)
            .context("drawing the held-out evaluation pairs")?;
    }
    let summary = trainer.train(&control.run_in(&settings.out_dir))?;
    let checkpoint = settings.out_dir.join(DECODER_CHECKPOINT_FILE);
    if !summary.run.interrupted {
        trainer
            .save_checkpoint(&checkpoint)
            .with_context(|| format!("writing {}", checkpoint.display()))?;
    }
    Ok(PretrainReport {
        config: cfg,
        content_images: n_content,
        style_images: n_style,
        run: summary.run,
        evaluations: summary.evaluations,
        checkpoint,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn overrides_replace_configured_values() {
        let mut c: DecoderTrainConfig =
            config::parse("iterations = 10\ncrop = 64\n", Path::new("d.toml")).unwrap();
        DecoderOverrides {
            crop: Some(32),
            variant: Some(Variant::Fullres),
            checkpoint_every: Some(7),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!(c.iterations, 10);
        assert_eq!(c.crop, 32);
        assert_eq!(c.variant, Variant::Fullres);
        assert_eq!(c.checkpoint_interval, 7);
        assert_eq!(c.resize, DecoderTrainConfig::default().resize);
    }
}
