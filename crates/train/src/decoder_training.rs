//! AdaIN decoder training: the decoder learns to invert the frozen encoder's deepest features
//! after their statistics have been replaced by a style's (Huang and Belongie 2017).
//!
//! One iteration `i` (counted from 1) of [`DecoderTrainer::train_step`]:
//! 1. the learning rate is `lr / (1 + lr_decay * (i - 1))`, the inverse-time decay of the AdaIN
//!    code (which adjusts the rate with the 0-based iteration count before each step);
//! 2. `batch_size` content crops and then `batch_size` style crops are drawn
//!    ([`ImageSet::random_crop`]: image index, then row and column offsets, from a generator
//!    that is a function of the seed and `i` only);
//! 3. with `phi` the frozen encoder (features `relu1_1 .. relu_k_1`) and `g` the decoder, the
//!    target is `t = adain(phi_k(c), phi_k(s))` per sample and the loss is
//!    `content(phi_k(g(t)), t) + style_weight * style(phi(g(t)), phi(s))`
//!    ([`style::decoder_training_loss`], `t` a constant as in the AdaIN code);
//! 4. Adam (PyTorch semantics) steps every decoder weight and bias.
//!
//! With a *style network* `psi` ([`DecoderTrainer::with_style_network`]) the style term is
//! `style(psi(g(t)), psi(s))` at every level of `psi` instead
//! ([`style::decoder_training_loss_with_style_network`]); the target and the content term stay
//! on `phi`. This is for encoders too narrow to judge texture on their own: the 16x-compressed
//! relu4_1 encoder (16 to 128 channels a level) trained with the real VGG-19 layers to relu3_1
//! as `psi`, which keeps the compressed encoder's receptive field for the content while the
//! style is measured by the full-width features AdaIN's loss was designed on.
//!
//! Batches: the whole batch runs through the networks at once and every loss term is a mean
//! over all its elements, batch included, exactly as PyTorch's batched `mse_loss`; since all
//! samples have the same size this is the mean of the per-sample losses, and the gradients are
//! the mean of the per-sample gradients.
//!
//! The variant ([`Variant`]) decides whether the networks pool and upsample (standard) or keep
//! the crop's resolution throughout (fullres); the weights are the same.
//!
//! Evaluation ([`DecoderTrainer::evaluate`]) averages the same loss over `eval_pairs` fixed
//! (content, style) pairs drawn once from the seed, on centred crops. By default the pairs come
//! from the training images (a fixed, reproducible yardstick that training never sees in this
//! crop and pairing); [`DecoderTrainer::with_eval_images`] draws them from separate, held-out
//! images instead.
//!
//! Checkpoints are one safetensors file holding the decoder (its canonical [`NetWeights`]
//! bytes, so it reloads bit for bit), the Adam moments and, as metadata, the completed step,
//! the seed, the Adam step counts and the configuration. The random choices of an iteration
//! depend only on the seed and the iteration number, so a resumed run continues exactly as the
//! uninterrupted one would.
//!
//! A decoder can start from imported weights (e.g. a WCT inverter of the same encoder) or from
//! [`init_decoder`], a seeded initialisation of the encoder's mirror image.

use std::path::{Path, PathBuf};

use ndarray::{Array1, Array4};
use nets::{ConvGrad, Decoder, Encoder, NetWeights, StateDict, TensorF32};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use style::{
    adain_with_stats, decoder_training_loss, decoder_training_loss_with_style_network,
    encode_style, StyleFeatureStats,
};

use crate::adam::{Adam, AdamConfig};
use crate::checkpoint::{StateReader, StateWriter};
use crate::driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
use crate::error::TrainError;
use crate::image_folder::{stack, ImageSet};
use base::event::{Event, Metric, Sink, Stage};
use runtime::bundle::{weights_fingerprint, Variant};

/// The checkpoint metadata naming the style network (its weights' fingerprint), or
/// [`NO_STYLE_NETWORK`]; checkpoints written before style networks existed lack it and mean the
/// latter.
const STYLE_NETWORK_KEY: &str = "style_network_fingerprint";
/// The value of [`STYLE_NETWORK_KEY`] for a run whose style term is measured by its encoder.
const NO_STYLE_NETWORK: &str = "none";

/// The `format` metadata of a decoder-training checkpoint.
pub const DECODER_CHECKPOINT_FORMAT: &str = "dsgs-decoder-checkpoint-v1";

/// The checkpoint inside a decoder-training output folder, replaced each time one is written.
pub const DECODER_CHECKPOINT_FILE: &str = crate::driver::CHECKPOINT_FILE;
/// The weights inside a decoder-training output folder (encoder and decoder), written at each
/// checkpoint and when training completes.
pub const DECODER_WEIGHTS_FILE: &str = "decoder.safetensors";
/// The held-out curve inside a decoder-training output folder: one tab-separated row per
/// evaluation (`step pairs loss content style`), rewritten atomically at each evaluation. A
/// resumed run keeps the rows before its checkpoint's step and appends its own, so the file
/// holds the curve of the whole run across sessions.
pub const DECODER_CURVE_FILE: &str = "evaluations.tsv";

/// Settings of a decoder training run. The defaults are the AdaIN paper's, scaled down for a CPU
/// (smaller batch and crops).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DecoderTrainConfig {
    /// Total iterations (AdaIN trains 160,000 with batch 8).
    pub iterations: u64,
    /// Content (and style) images per iteration (AdaIN: 8).
    pub batch_size: usize,
    /// The short side every image is resized to before cropping (AdaIN: 512).
    pub resize: u32,
    /// Side of the square random crop fed to the networks (AdaIN: 256).
    pub crop: u32,
    /// Weight of the style loss.
    pub style_weight: f64,
    /// Initial learning rate.
    pub lr: f64,
    /// Inverse-time decay: iteration `i` uses `lr / (1 + lr_decay * (i - 1))`.
    pub lr_decay: f64,
    /// Standard (pooling) or fullres networks.
    pub variant: Variant,
    /// Seed of every random choice (crops, evaluation pairs, initialisation).
    pub seed: u64,
    /// Number of fixed (content, style) pairs of the held-out evaluation (0: none).
    pub eval_pairs: usize,
    /// Iterations between evaluations (0: only at the end, when `eval_pairs > 0`).
    pub eval_interval: u64,
    /// Iterations between checkpoints (0: none).
    pub checkpoint_interval: u64,
    /// Iterations between log lines (0: none).
    pub log_interval: u64,
    /// Adam hyper-parameters (PyTorch defaults, as the AdaIN code uses).
    pub adam: AdamConfig,
}

impl Default for DecoderTrainConfig {
    fn default() -> Self {
        DecoderTrainConfig {
            iterations: 20_000,
            batch_size: 2,
            resize: 256,
            crop: 128,
            style_weight: 10.0,
            lr: 1e-4,
            lr_decay: 5e-5,
            variant: Variant::Standard,
            seed: 0,
            eval_pairs: 8,
            eval_interval: 1000,
            checkpoint_interval: 1000,
            log_interval: 0,
            adam: AdamConfig::default(),
        }
    }
}

impl DecoderTrainConfig {
    fn validate(&self, encoder_depth: usize) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::Config(m));
        if self.batch_size == 0 {
            return bad("batch_size is 0".into());
        }
        if self.crop == 0 || self.crop > self.resize {
            return bad(format!(
                "crop {} must be positive and at most the resize size {}",
                self.crop, self.resize
            ));
        }
        let min = 1u32 << (encoder_depth.saturating_sub(1)).min(16);
        if self.variant == Variant::Standard && self.crop < min {
            return bad(format!(
                "crop {} is smaller than {min}, the encoder's total pooling",
                self.crop
            ));
        }
        for (name, v) in [
            ("style_weight", self.style_weight),
            ("lr", self.lr),
            ("lr_decay", self.lr_decay),
        ] {
            if !v.is_finite() || v < 0.0 {
                return bad(format!("{name} = {v} must be finite and non-negative"));
            }
        }
        Ok(())
    }

    /// The learning rate of iteration `it` (counted from 1).
    pub fn lr_at(&self, it: u64) -> f64 {
        self.lr / (1.0 + self.lr_decay * it.saturating_sub(1) as f64)
    }
}

/// What one iteration did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DecoderStepReport {
    /// The iteration number (from 1).
    pub step: u64,
    /// The learning rate used.
    pub lr: f64,
    /// The content term: MSE between the deepest encoder features of the decoded image and the
    /// AdaIN target `t`.
    pub loss_content: f64,
    /// The unweighted style term: summed over encoder levels, MSE of the per-channel means plus
    /// MSE of the per-channel standard deviations.
    pub loss_style: f64,
    /// `loss_content + style_weight * loss_style`.
    pub loss: f64,
}

/// The mean loss over the evaluation pairs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DecoderEvaluation {
    /// Completed iterations when evaluated.
    pub step: u64,
    /// Number of (content, style) pairs averaged.
    pub pairs: usize,
    /// Mean content term.
    pub loss_content: f64,
    /// Mean unweighted style term.
    pub loss_style: f64,
    /// Mean total, `loss_content + style_weight * loss_style`.
    pub loss: f64,
}

/// The result of [`DecoderTrainer::train`].
#[derive(Clone, Debug, PartialEq)]
pub struct DecoderTrainSummary {
    /// How the run ended; its output is the final weights, when training completed with an
    /// output folder.
    pub run: RunOutcome,
    /// The evaluations made during this call, in order: before the first iteration of a fresh
    /// run, every `eval_interval` iterations and at the end.
    pub evaluations: Vec<DecoderEvaluation>,
}

impl DecoderEvaluation {
    /// The evaluation as event metrics.
    pub fn metrics(&self) -> Vec<Metric> {
        [
            ("loss", self.loss),
            ("content", self.loss_content),
            ("style", self.loss_style),
            ("pairs", self.pairs as f64),
        ]
        .map(|(name, value)| Metric { name, value })
        .to_vec()
    }
}

/// The statistics of a batch of style crops: the encoder's (whose deepest level is the AdaIN
/// target's) and, with a style network, that network's (which the style term measures).
#[derive(Clone, Debug)]
struct StyleBatch {
    encoder: StyleFeatureStats<f32>,
    style_network: Option<StyleFeatureStats<f32>>,
}

/// A fixed evaluation pair: the centred content crop and the style's statistics.
#[derive(Clone, Debug)]
struct EvalPair {
    content: Array4<f32>,
    style: StyleBatch,
}

/// An AdaIN decoder training run.
pub struct DecoderTrainer {
    /// The run's settings.
    pub config: DecoderTrainConfig,
    encoder: Encoder<f32>,
    /// The network the style term is measured with, when not the encoder.
    style_network: Option<Encoder<f32>>,
    decoder: Decoder<f32>,
    adam: Adam<f32>,
    step: u64,
    content: ImageSet,
    styles: ImageSet,
    /// The images the evaluation pairs are drawn from, when not the training images.
    eval_images: Option<(ImageSet, ImageSet)>,
    eval: Vec<EvalPair>,
    ema: Option<[f64; 3]>,
}

/// Parameter names of the decoder in the optimiser: `{layer}.weight` and `{layer}.bias`.
pub(crate) fn register_decoder(adam: &mut Adam<f32>, decoder: &Decoder<f32>, lr: f64) {
    for l in decoder.layers() {
        let (o, c, k, _) = l.weight.dim();
        adam.add_param(&format!("{}.weight", l.name), lr, o, c * k * k);
        adam.add_param(&format!("{}.bias", l.name), lr, 1, o);
    }
}

impl DecoderTrainer {
    /// A run at step 0. `encoder` is frozen; `decoder` (imported weights or [`init_decoder`])
    /// must take the encoder's deepest width and produce 3 channels. Both are set to the
    /// configured variant's resolution.
    pub fn new(
        encoder: Encoder<f32>,
        decoder: Decoder<f32>,
        content_images: ImageSet,
        style_images: ImageSet,
        config: DecoderTrainConfig,
    ) -> Result<Self, TrainError> {
        config.validate(encoder.depth())?;
        let deepest = *encoder.widths().last().unwrap_or(&0);
        if decoder.in_channels() != deepest || decoder.out_channels() != 3 {
            return Err(TrainError::Config(format!(
                "the decoder maps {} channels to {}, the encoder's relu{}_1 has {deepest} \
                 (expected {deepest} to 3)",
                decoder.in_channels(),
                decoder.out_channels(),
                encoder.depth()
            )));
        }
        if encoder.in_channels() != 3 {
            return Err(TrainError::Config(format!(
                "the encoder takes {} channels, expected 3",
                encoder.in_channels()
            )));
        }
        let res = config.variant.resolution();
        let encoder = encoder.with_resolution(res);
        let decoder = decoder.with_resolution(res);
        let mut adam = Adam::new(config.adam);
        register_decoder(&mut adam, &decoder, config.lr);
        let eval = eval_pairs(&encoder, None, &config, &content_images, &style_images)?;
        Ok(DecoderTrainer {
            config,
            encoder,
            style_network: None,
            decoder,
            adam,
            step: 0,
            content: content_images,
            styles: style_images,
            eval_images: None,
            eval,
            ema: None,
        })
    }

    /// Measures the style term with `network` (see the module documentation) from the first
    /// iteration: for a run at step 0 only (a resumed run takes its style network in
    /// [`DecoderTrainer::resume_with_style_network`]). It is set to the configured variant's
    /// resolution and must take 3 channels.
    pub fn with_style_network(self, network: Encoder<f32>) -> Result<Self, TrainError> {
        if self.step != 0 {
            return Err(TrainError::Config(
                "a style network is chosen when the run starts; a resumed run takes the one                  its checkpoint was trained with"
                    .into(),
            ));
        }
        self.set_style_network(Some(network))
    }

    fn set_style_network(mut self, network: Option<Encoder<f32>>) -> Result<Self, TrainError> {
        if let Some(n) = &network {
            if n.in_channels() != 3 {
                return Err(TrainError::Config(format!(
                    "the style network takes {} channels, expected 3",
                    n.in_channels()
                )));
            }
        }
        self.style_network = network.map(|n| n.with_resolution(self.config.variant.resolution()));
        self.redraw_eval_pairs()?;
        Ok(self)
    }

    /// The network the style term is measured with, when not the encoder.
    pub fn style_network(&self) -> Option<&Encoder<f32>> {
        self.style_network.as_ref()
    }

    fn redraw_eval_pairs(&mut self) -> Result<(), TrainError> {
        let (c, s) = match &self.eval_images {
            Some((c, s)) => (c, s),
            None => (&self.content, &self.styles),
        };
        self.eval = eval_pairs(
            &self.encoder,
            self.style_network.as_ref(),
            &self.config,
            c,
            s,
        )?;
        Ok(())
    }

    /// Draws the evaluation pairs from separate (held-out) content and style images instead of
    /// the training images.
    pub fn with_eval_images(
        mut self,
        content_images: &ImageSet,
        style_images: &ImageSet,
    ) -> Result<Self, TrainError> {
        self.eval_images = Some((content_images.clone(), style_images.clone()));
        self.redraw_eval_pairs()?;
        Ok(self)
    }

    /// Continues a run from a checkpoint written by [`DecoderTrainer::save_checkpoint`], with the
    /// same encoder and images (the configuration may differ, e.g. more iterations; the
    /// learning rates follow the new configuration).
    pub fn resume(
        checkpoint: &Path,
        encoder: Encoder<f32>,
        content_images: ImageSet,
        style_images: ImageSet,
        config: DecoderTrainConfig,
    ) -> Result<Self, TrainError> {
        Self::resume_with_style_network(
            checkpoint,
            encoder,
            None,
            content_images,
            style_images,
            config,
        )
    }

    /// [`DecoderTrainer::resume`] for a run whose style term is measured with `style_network`
    /// (`None`: the encoder). It must be the network the checkpoint was trained with.
    pub fn resume_with_style_network(
        checkpoint: &Path,
        encoder: Encoder<f32>,
        style_network: Option<Encoder<f32>>,
        content_images: ImageSet,
        style_images: ImageSet,
        config: DecoderTrainConfig,
    ) -> Result<Self, TrainError> {
        let bytes = std::fs::read(checkpoint).map_err(|e| TrainError::io(checkpoint, e))?;
        let r = StateReader::new(&bytes, checkpoint, DECODER_CHECKPOINT_FORMAT)?;
        let fp = r.meta_str("encoder_fingerprint")?;
        if fp != weights_fingerprint(&encoder) {
            return Err(r.err(format!(
                "it was trained against another encoder (fingerprint {fp}, this encoder's is {})",
                weights_fingerprint(&encoder)
            )));
        }
        let nets = NetWeights::from_bytes(r.bytes("decoder")?)
            .map_err(|e| r.err(format!("decoder: {e}")))?;
        let decoder = nets
            .decoder
            .ok_or_else(|| r.err("the decoder is missing".into()))?;
        let recorded = if r.has_meta(STYLE_NETWORK_KEY) {
            r.meta_str(STYLE_NETWORK_KEY)?
        } else {
            NO_STYLE_NETWORK
        };
        let given = style_network
            .as_ref()
            .map_or(NO_STYLE_NETWORK.to_string(), weights_fingerprint);
        if recorded != given {
            let name = |f: &str| {
                if f == NO_STYLE_NETWORK {
                    "its own encoder".to_string()
                } else {
                    format!("the style network of fingerprint {f}")
                }
            };
            return Err(r.err(format!(
                "its style term was measured with {}, and this run gives {}",
                name(recorded),
                name(&given)
            )));
        }
        let t = DecoderTrainer::new(encoder, decoder, content_images, style_images, config)?;
        let mut t = t.set_style_network(style_network)?;
        let adam = r.adam(t.config.adam)?;
        check_same_params(&adam, &t.adam).map_err(|m| r.err(m))?;
        t.adam = adam;
        t.step = r.meta_parse("step")?;
        t.ema = r.ema()?;
        Ok(t)
    }

    /// Completed iterations.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// The decoder being trained.
    pub fn decoder(&self) -> &Decoder<f32> {
        &self.decoder
    }

    /// The frozen encoder.
    pub fn encoder(&self) -> &Encoder<f32> {
        &self.encoder
    }

    /// The optimiser state.
    pub fn adam(&self) -> &Adam<f32> {
        &self.adam
    }

    /// Running averages (factor 0.4 on the newest value) of the total, content and style loss.
    pub fn running_averages(&self) -> Option<[f64; 3]> {
        self.ema
    }

    /// The decoder loss of one batch and its gradients, without a step.
    fn batch_loss(
        &self,
        content: &Array4<f32>,
        style: &StyleBatch,
    ) -> Result<style::DecoderLoss<f32>, TrainError> {
        let feats = self.encoder.forward(content.view())?;
        let deepest = feats.last().expect("encoder depth >= 1");
        let t = adain_with_stats(deepest, style.encoder.deepest())?;
        let w = self.config.style_weight;
        match (&self.style_network, &style.style_network) {
            (Some(psi), Some(s)) => decoder_training_loss_with_style_network(
                &self.encoder,
                psi,
                &self.decoder,
                &t,
                &t,
                s,
                w,
            ),
            _ => decoder_training_loss(&self.encoder, &self.decoder, &t, &t, &style.encoder, w),
        }
        .map_err(TrainError::Style)
    }

    /// Runs one iteration.
    pub fn train_step(&mut self) -> Result<DecoderStepReport, TrainError> {
        let it = self.step + 1;
        let cfg = &self.config;
        let mut rng = StdRng::seed_from_u64(mix(cfg.seed, STEP_STREAM, it));
        let mut contents = Vec::with_capacity(cfg.batch_size);
        for _ in 0..cfg.batch_size {
            let i = rng.random_range(0..self.content.len());
            contents.push(
                self.content
                    .random_crop(i, cfg.resize, cfg.crop, &mut rng)?,
            );
        }
        let mut styles = Vec::with_capacity(cfg.batch_size);
        for _ in 0..cfg.batch_size {
            let i = rng.random_range(0..self.styles.len());
            styles.push(self.styles.random_crop(i, cfg.resize, cfg.crop, &mut rng)?);
        }
        let content = stack(&contents)?;
        let style = style_batch(&self.encoder, self.style_network.as_ref(), &stack(&styles)?)?;
        let out = self.batch_loss(&content, &style)?;
        let lr = self.config.lr_at(it);
        for i in 0..self.adam.params().len() {
            self.adam.set_lr(i, lr);
        }
        step_decoder(&mut self.adam, 0, &mut self.decoder, &out.grad_params)?;
        self.step = it;
        let (c, s, l) = (
            out.loss_content as f64,
            out.loss_style as f64,
            out.loss as f64,
        );
        self.ema = Some(match self.ema {
            None => [l, c, s],
            Some(e) => [
                0.4 * l + 0.6 * e[0],
                0.4 * c + 0.6 * e[1],
                0.4 * s + 0.6 * e[2],
            ],
        });
        Ok(DecoderStepReport {
            step: it,
            lr,
            loss_content: c,
            loss_style: s,
            loss: l,
        })
    }

    /// The mean loss over the evaluation pairs (`None` without pairs).
    pub fn evaluate(&self) -> Result<Option<DecoderEvaluation>, TrainError> {
        if self.eval.is_empty() {
            return Ok(None);
        }
        let (mut c, mut s, mut l) = (0.0, 0.0, 0.0);
        for p in &self.eval {
            let out = self.batch_loss(&p.content, &p.style)?;
            c += out.loss_content as f64;
            s += out.loss_style as f64;
            l += out.loss as f64;
        }
        let n = self.eval.len() as f64;
        Ok(Some(DecoderEvaluation {
            step: self.step,
            pairs: self.eval.len(),
            loss_content: c / n,
            loss_style: s / n,
            loss: l / n,
        }))
    }

    /// The checkpoint as safetensors bytes.
    pub fn checkpoint_bytes(&self) -> Result<Vec<u8>, TrainError> {
        let mut w = StateWriter::new(DECODER_CHECKPOINT_FORMAT);
        w.meta("step", self.step);
        w.meta("seed", self.config.seed);
        w.meta("encoder_fingerprint", weights_fingerprint(&self.encoder));
        w.meta(
            STYLE_NETWORK_KEY,
            self.style_network
                .as_ref()
                .map_or(NO_STYLE_NETWORK.to_string(), weights_fingerprint),
        );
        w.meta(
            "config",
            serde_json::to_string(&self.config).map_err(|e| TrainError::Config(e.to_string()))?,
        );
        w.ema(self.ema.as_ref().map(|e| e.as_slice()));
        let nets = NetWeights {
            decoder: Some(self.decoder.clone()),
            ..Default::default()
        };
        w.bytes("decoder", nets.to_bytes()?);
        w.adam(&self.adam);
        w.finish()
    }

    /// Writes a checkpoint atomically.
    pub fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        base::write_atomic(path, &self.checkpoint_bytes()?).map_err(|e| TrainError::io(path, e))
    }

    /// Writes the encoder and the trained decoder as canonical weights ([`NetWeights`]),
    /// atomically.
    pub fn save_weights(&self, path: &Path) -> Result<(), TrainError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| TrainError::io(dir, e))?;
        }
        let nets = NetWeights {
            encoder: Some(self.encoder.clone()),
            decoder: Some(self.decoder.clone()),
            lifter: None,
        };
        nets.save(path).map_err(|e| TrainError::Checkpoint {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
    }

    /// Trains up to `config.iterations` through the [driver](crate::driver). With an output
    /// folder, the checkpoint is `out_dir/checkpoint.safetensors` and the final weights
    /// `out_dir/decoder.safetensors` (encoder and decoder). Evaluations run before the first
    /// iteration of a fresh run (the starting point of the held-out curve), every
    /// `eval_interval` iterations and at the end.
    pub fn train(&mut self, run: &Run) -> Result<DecoderTrainSummary, TrainError> {
        let cadence = Cadence {
            checkpoint_interval: self.config.checkpoint_interval,
            log_interval: self.config.log_interval,
        };
        let mut l = DecoderLoop {
            t: self,
            evaluations: Vec::new(),
            lr: 0.0,
            curve: run.out_dir.map(|d| d.join(DECODER_CURVE_FILE)),
        };
        let run = drive(&mut l, cadence, run)?;
        Ok(DecoderTrainSummary {
            run,
            evaluations: l.evaluations,
        })
    }
}

/// A decoder run as the driver sees it, collecting this call's evaluations.
struct DecoderLoop<'t> {
    t: &'t mut DecoderTrainer,
    evaluations: Vec<DecoderEvaluation>,
    /// The learning rate of the last iteration.
    lr: f64,
    /// `OUT/evaluations.tsv`, with an output folder.
    curve: Option<PathBuf>,
}

impl DecoderLoop<'_> {
    /// Evaluates, reports and records the held-out loss at the current step.
    fn evaluate(&mut self, sink: &dyn Sink) -> Result<(), TrainError> {
        if let Some(e) = self.t.evaluate()? {
            sink.emit(Event::Evaluation {
                stage: Stage::Decoder,
                step: e.step,
                metrics: e.metrics(),
            });
            if let Some(path) = &self.curve {
                record_evaluation(path, &e)?;
            }
            self.evaluations.push(e);
        }
        Ok(())
    }
}

/// The header line of [`DECODER_CURVE_FILE`].
const CURVE_HEADER: &str = "step\tpairs\tloss\tcontent\tstyle";

/// Rewrites the curve file at `path` with its rows of earlier steps and then `e` (a missing or
/// unreadable file starts a new curve).
fn record_evaluation(path: &Path, e: &DecoderEvaluation) -> Result<(), TrainError> {
    let old = std::fs::read_to_string(path).unwrap_or_default();
    let mut text = format!("{CURVE_HEADER}\n");
    for line in old.lines().skip(1) {
        let step = line.split('\t').next().and_then(|s| s.parse::<u64>().ok());
        if step.is_some_and(|s| s < e.step) {
            text.push_str(line);
            text.push('\n');
        }
    }
    text.push_str(&format!(
        "{}\t{}\t{:.6}\t{:.6}\t{:.6}\n",
        e.step, e.pairs, e.loss, e.loss_content, e.loss_style
    ));
    base::write_atomic(path, text.as_bytes()).map_err(|err| TrainError::io(path, err))
}

impl TrainingLoop for DecoderLoop<'_> {
    const STAGE: Stage = Stage::Decoder;

    fn step(&self) -> u64 {
        self.t.step
    }

    fn iterations(&self) -> u64 {
        self.t.config.iterations
    }

    fn advance(&mut self) -> Result<(), TrainError> {
        self.lr = self.t.train_step()?.lr;
        Ok(())
    }

    fn status(&self) -> String {
        let e = self.t.ema.unwrap_or_default();
        format!(
            "loss {:.5} content {:.5} style {:.5} lr {:.3e}",
            e[0], e[1], e[2], self.lr
        )
    }

    fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        self.t.save_checkpoint(path)?;
        // The weights at this checkpoint beside it, so that a long run's decoder can be tried
        // (e.g. by `dsgs stylize-image`) while it trains; replaced by the final weights.
        if let Some(dir) = path.parent() {
            self.t.save_weights(&dir.join(DECODER_WEIGHTS_FILE))?;
        }
        Ok(())
    }

    fn start(&mut self, sink: &dyn Sink) -> Result<(), TrainError> {
        if self.t.step == 0 && self.t.config.iterations > 0 {
            self.evaluate(sink)?;
        }
        Ok(())
    }

    fn after_step(&mut self, _out_dir: Option<&Path>, sink: &dyn Sink) -> Result<(), TrainError> {
        let (it, k, total) = (
            self.t.step,
            self.t.config.eval_interval,
            self.t.config.iterations,
        );
        if (k > 0 && it.is_multiple_of(k)) || it == total {
            self.evaluate(sink)?;
        }
        Ok(())
    }

    fn finish(&mut self, out_dir: &Path) -> Result<Option<(&'static str, PathBuf)>, TrainError> {
        let p = out_dir.join(DECODER_WEIGHTS_FILE);
        self.t.save_weights(&p)?;
        Ok(Some(("decoder", p)))
    }
}

/// The fixed evaluation pairs: `eval_pairs` (content, style) index pairs drawn from the seed,
/// centre-cropped, the styles encoded once.
fn eval_pairs(
    encoder: &Encoder<f32>,
    style_network: Option<&Encoder<f32>>,
    cfg: &DecoderTrainConfig,
    content: &ImageSet,
    styles: &ImageSet,
) -> Result<Vec<EvalPair>, TrainError> {
    let mut rng = StdRng::seed_from_u64(mix(cfg.seed, EVAL_STREAM, 0));
    let mut out = Vec::with_capacity(cfg.eval_pairs);
    for _ in 0..cfg.eval_pairs {
        let ci = rng.random_range(0..content.len());
        let si = rng.random_range(0..styles.len());
        let c = content.center_crop(ci, cfg.resize, cfg.crop)?;
        let s = styles.center_crop(si, cfg.resize, cfg.crop)?;
        out.push(EvalPair {
            content: c,
            style: style_batch(encoder, style_network, &s)?,
        });
    }
    Ok(out)
}

/// The statistics of the style crops `s` (N images) for the encoder and the style network.
fn style_batch(
    encoder: &Encoder<f32>,
    style_network: Option<&Encoder<f32>>,
    s: &Array4<f32>,
) -> Result<StyleBatch, TrainError> {
    Ok(StyleBatch {
        encoder: encode_style(encoder, s)?,
        style_network: style_network.map(|n| encode_style(n, s)).transpose()?,
    })
}

/// One Adam step of every decoder conv, whose weight and bias are the optimiser's parameters
/// `first + 2k` and `first + 2k + 1` ([`register_decoder`]).
pub(crate) fn step_decoder(
    adam: &mut Adam<f32>,
    first: usize,
    decoder: &mut Decoder<f32>,
    grads: &[ConvGrad<f32>],
) -> Result<(), TrainError> {
    if grads.len() != decoder.layers().count() {
        return Err(TrainError::Shape(format!(
            "{} decoder gradients for {} convs",
            grads.len(),
            decoder.layers().count()
        )));
    }
    for (k, (layer, grad)) in decoder.layers_mut().zip(grads).enumerate() {
        if layer.name != grad.name {
            return Err(TrainError::Shape(format!(
                "decoder gradient of `{}` returned for layer `{}`",
                grad.name, layer.name
            )));
        }
        let gw = grad.weight.as_standard_layout();
        let w = layer
            .weight
            .as_slice_mut()
            .ok_or_else(|| TrainError::Shape("decoder weight is not contiguous".into()))?;
        adam.step(
            first + 2 * k,
            w,
            gw.as_slice().expect("standard layout is contiguous"),
        )?;
        let b = layer
            .bias
            .as_slice_mut()
            .ok_or_else(|| TrainError::Shape("decoder bias is not contiguous".into()))?;
        let gb = grad.bias.to_vec();
        adam.step(first + 2 * k + 1, b, &gb)?;
    }
    Ok(())
}

/// Checks that a restored optimiser has the parameters (names and sizes) of a fresh one.
pub(crate) fn check_same_params(restored: &Adam<f32>, fresh: &Adam<f32>) -> Result<(), String> {
    let a = restored.params();
    let b = fresh.params();
    if a.len() != b.len() {
        return Err(format!(
            "the optimiser has {} parameter tensors, this run has {}",
            a.len(),
            b.len()
        ));
    }
    for (x, y) in a.iter().zip(b) {
        if x.name != y.name || x.rows() != y.rows() || x.width() != y.width() {
            return Err(format!(
                "optimiser tensor `{}` ({} x {}) does not match `{}` ({} x {})",
                x.name,
                x.rows(),
                x.width(),
                y.name,
                y.rows(),
                y.width()
            ));
        }
    }
    Ok(())
}

/// Random streams derived from the seed.
pub(crate) const STEP_STREAM: u64 = 1;
pub(crate) const EVAL_STREAM: u64 = 2;
pub(crate) const INIT_STREAM: u64 = 3;

/// A 64-bit seed for `(seed, stream, index)`: SplitMix64 finalisers chained, so neighbouring
/// iterations and streams get unrelated generators.
pub(crate) fn mix(seed: u64, stream: u64, index: u64) -> u64 {
    splitmix64(seed ^ splitmix64(stream ^ splitmix64(index)))
}

fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// PyTorch's default `Conv2d` initialisation: weight and bias uniform in
/// `[-1/sqrt(fan_in), 1/sqrt(fan_in)]` with `fan_in = in_channels * k * k` (Kaiming uniform with
/// `a = sqrt(5)`, whose bound `sqrt(6 / ((1 + a^2) fan_in))` is `1/sqrt(fan_in)`). Same
/// distribution, not the same numbers: the values come from `rng`, weights first (OIHW order),
/// then biases.
pub fn conv_default_init<R: Rng>(
    out_channels: usize,
    in_channels: usize,
    kernel: usize,
    rng: &mut R,
) -> (Array4<f32>, Array1<f32>) {
    let fan_in = (in_channels * kernel * kernel).max(1) as f64;
    let bound = 1.0 / fan_in.sqrt();
    let mut draw = || rng.random_range(-bound..bound) as f32;
    let w = Array4::from_shape_fn((out_channels, in_channels, kernel, kernel), |_| draw());
    let b = Array1::from_shape_fn(out_channels, |_| draw());
    (w, b)
}

/// A decoder mirroring `encoder`, initialised from `seed` with [`conv_default_init`] (the
/// initialisation the AdaIN decoder is trained from): decoder conv `conv{K}_{J}` maps the
/// output width of encoder `conv{K}_{J}` back to its input width, levels run from the deepest
/// up with nearest 2x upsampling between them, and the last conv has no ReLU.
pub fn init_decoder(encoder: &Encoder<f32>, seed: u64) -> Result<Decoder<f32>, TrainError> {
    let mut rng = StdRng::seed_from_u64(mix(seed, INIT_STREAM, 0));
    init_decoder_with(encoder, &mut rng)
}

/// [`init_decoder`] drawing from `rng`.
pub fn init_decoder_with<R: Rng>(
    encoder: &Encoder<f32>,
    rng: &mut R,
) -> Result<Decoder<f32>, TrainError> {
    // The encoder's 3x3 convs grouped by level (conv0, the 1x1 input conv, is skipped).
    let mut levels: Vec<Vec<(usize, usize)>> = Vec::new();
    let mut convs = encoder.layers().skip(1);
    for n in encoder.convs_per_level() {
        let lv = (0..n)
            .map(|_| {
                let l = convs.next().expect("convs_per_level counts the layers");
                (l.in_channels(), l.out_channels())
            })
            .collect();
        levels.push(lv);
    }
    // Sequential (AdaIN) layout: the first conv at index 1, then 3 apart within a level
    // (pad, conv, ReLU) and 4 apart across an upsampling.
    let mut sd = StateDict::new();
    let mut index = 1usize;
    for (g, lv) in levels.iter().rev().enumerate() {
        if g > 0 {
            index += 1;
        }
        for &(enc_in, enc_out) in lv.iter().rev() {
            let (w, b) = conv_default_init(enc_in, enc_out, 3, rng);
            sd.insert(format!("{index}.weight"), TensorF32::from_array(&w));
            sd.insert(format!("{index}.bias"), TensorF32::from_array(&b));
            index += 3;
        }
    }
    Decoder::from_state_dict(&sd).map_err(TrainError::Net)
}

/// The hidden widths of the MLP decoder of the paper's decoder ablation
/// ([`init_mlp_decoder`]).
pub const MLP_DECODER_HIDDEN: [usize; 2] = [256, 128];

/// An MLP decoder `in_channels -> 256 -> 128 -> 3` (ReLU between layers, none after the last):
/// a pointwise decoder ([`Decoder::pointwise`]) of 1x1 convs named `conv1_3`, `conv1_2`,
/// `conv1_1`, initialised from `rng` with [`conv_default_init`] in that order. It decodes each
/// feature pixel to one image pixel, with no spatial context.
pub fn init_mlp_decoder<R: Rng>(
    in_channels: usize,
    rng: &mut R,
) -> Result<Decoder<f32>, TrainError> {
    let widths: Vec<usize> = std::iter::once(in_channels)
        .chain(MLP_DECODER_HIDDEN)
        .chain([3])
        .collect();
    let n = widths.len() - 1;
    let layers = (0..n)
        .map(|i| {
            let (weight, bias) = conv_default_init(widths[i + 1], widths[i], 1, rng);
            let name = format!("conv1_{}", n - i);
            nets::ConvLayer {
                source: name.clone(),
                name,
                weight,
                bias,
            }
        })
        .collect();
    Decoder::pointwise(layers, false).map_err(TrainError::Net)
}
