//! The feature trainer ([`FeatureTrainer`]): its setup from the inputs or from a checkpoint,
//! its iteration (see the [module documentation](super)), its evaluations, and what it writes:
//! checkpoints and the scene bundle.

use std::path::{Path, PathBuf};

use gaussian::FeatureGaussians;
use ndarray::Array4;
use nets::{Decoder, Encoder, Lifter, NetWeights};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use style::{encode_style, FeatureNorm, Stage3Weights, StyleFeatureStats};

use super::config::FeatureTrainConfig;
use super::evaluation::{eval_indices, EvalSample, FeatureEvaluation};
use super::objective::{stage3_gradients, CropWindow, Stage3Gradients, Stage3Sample, Stage3Setup};
use super::setup::{
    camera_records, check_inputs, check_networks, encode_inputs, encode_view, init_parameters,
    new_optimiser, CachedView, FeatureInputs, FeatureSetup, InitialParameters,
};
use super::{BUNDLE_DIR, FEATURE_CHECKPOINT_FORMAT};
use crate::adam::Adam;
use crate::checkpoint::{StateReader, StateWriter};
use crate::decoder_training::{
    check_same_params, mix, register_decoder, step_decoder, STEP_STREAM,
};
use crate::driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
use crate::error::TrainError;
use crate::geometry::View;
use crate::image_folder::{to_tensor, ImageSet};
use base::event::{Event, Sink, Stage, Tally};
use base::Fnv1a;
use runtime::bundle::{
    feature_map_camera, weights_fingerprint, BundleInfo, CameraRecord, DecoderMode, SceneBundle,
};

/// What one iteration did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeatureStepReport {
    /// The iteration number (from 1).
    pub step: u64,
    /// Index of the training view used.
    pub view: usize,
    /// Index of the style image used.
    pub style: usize,
    /// The crop window in feature pixels (the whole map when the iteration has no content and
    /// style terms).
    pub window: CropWindow,
    /// The alignment term on the window.
    pub loss_align: f64,
    /// The content term (0 when not evaluated).
    pub loss_content: f64,
    /// The unweighted style term (0 when not evaluated).
    pub loss_style: f64,
    /// The total, `loss_align + lambda_c loss_content + lambda_s loss_style` with the weights of
    /// this iteration.
    pub loss: f64,
}

/// The result of [`FeatureTrainer::train`].
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureTrainSummary {
    /// How the run ended; its output is the scene bundle, when training completed with an
    /// output folder.
    pub run: RunOutcome,
    /// Running averages of the total, align, content and style losses at the end.
    pub running_losses: Option<[f64; 4]>,
    /// The evaluations of this call ([`FeatureTrainer::evaluate_fixed`]), in order: before the
    /// first iteration of a fresh run, every `eval_interval` iterations and at the end.
    pub evaluations: Vec<FeatureEvaluation>,
}

/// A feature training run.
pub struct FeatureTrainer {
    /// The run's settings.
    pub config: FeatureTrainConfig,
    /// Extra provenance entries for the bundle.
    pub provenance: Vec<(String, String)>,
    scene: FeatureGaussians<f32>,
    lifter: Lifter<f32>,
    encoder: Encoder<f32>,
    decoder: Decoder<f32>,
    views: Vec<CachedView>,
    styles: Vec<StyleFeatureStats<f32>>,
    adam: Adam<f32>,
    step: u64,
    ema: Option<[f64; 4]>,
    scene_mean: Vec<f32>,
    scene_std: Vec<f32>,
    cameras: Vec<CameraRecord>,
    background: [f32; 3],
    geometry_fingerprint: String,
    eval: Vec<EvalSample>,
    evaluations: Vec<FeatureEvaluation>,
}

/// FNV-1a (64-bit) over the geometry's parameter bits (not its colours or features): which
/// frozen Gaussians a checkpoint belongs to.
pub fn geometry_fingerprint(scene: &FeatureGaussians<f32>) -> String {
    let mut h = Fnv1a::new();
    h.eat_f32(scene.len() as f32);
    for i in 0..scene.len() {
        let row = scene.means[i]
            .iter()
            .chain(&scene.log_scales[i])
            .chain(&scene.quats[i]);
        row.chain([&scene.opacity_logits[i]])
            .for_each(|&v| h.eat_f32(v));
    }
    h.hex()
}

impl FeatureTrainer {
    /// A run at step 0: initialises the features and the lifter from the seed, encodes every
    /// training view (alignment targets, scene statistics) and every style image; silent and
    /// without a cache ([`FeatureTrainer::new_with`]).
    pub fn new(config: FeatureTrainConfig, inputs: FeatureInputs) -> Result<Self, TrainError> {
        FeatureTrainer::new_with(config, inputs, &FeatureSetup::quiet())
    }

    /// [`FeatureTrainer::new`], reporting the setup (decoding the styles, encoding the views and
    /// styles) as [`Stage::Prepare`] progress and a summary line to `setup.sink`, and reusing
    /// and filling the encoding cache `setup.cache` (see the module documentation). The result
    /// is the same with or without the cache.
    pub fn new_with(
        config: FeatureTrainConfig,
        inputs: FeatureInputs,
        setup: &FeatureSetup,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        let deepest = check_inputs(&inputs)?;
        let FeatureInputs {
            geometry,
            views,
            cameras,
            styles,
            encoder,
            decoder,
            background,
            provenance,
        } = inputs;
        let res = config.variant.resolution();
        let encoder = encoder.with_resolution(res);
        let decoder = decoder.with_resolution(res);
        let InitialParameters {
            scene,
            lifter,
            decoder,
        } = init_parameters(&config, geometry, &encoder, decoder, deepest)?;
        let geometry_fingerprint = geometry_fingerprint(&scene);
        let cameras = camera_records(cameras, &views);
        let encoded = encode_inputs(&config, &encoder, views, &styles, deepest, setup)?;
        let adam = new_optimiser(&config, scene.len(), deepest, &decoder);
        Ok(FeatureTrainer {
            config,
            provenance,
            scene,
            lifter,
            encoder,
            decoder,
            views: encoded.views,
            styles: encoded.styles,
            adam,
            step: 0,
            ema: None,
            scene_mean: encoded.scene_mean,
            scene_std: encoded.scene_std,
            cameras,
            background,
            geometry_fingerprint,
            eval: encoded.eval,
            evaluations: Vec::new(),
        })
    }

    /// Draws the evaluation samples from held-out views and styles instead of the training
    /// ones (see "Evaluation" in the module documentation): `eval_pairs` (view, style) pairs
    /// from the seed, only the views drawn are encoded, reported to `sink` as
    /// [`Stage::Prepare`] progress. Views must have the training views' kind (RGB images at
    /// the resolution to train at); their feature maps follow
    /// [`feature_size`](runtime::bundle::feature_size).
    pub fn with_held_out(
        self,
        views: &[View],
        styles: &ImageSet,
        sink: &dyn Sink,
    ) -> Result<Self, TrainError> {
        self.held_out_samples(views, Some(styles), sink)
    }

    /// [`FeatureTrainer::with_held_out`] with the training paintings as the evaluation's: the
    /// same samples as `with_held_out(views, training_styles, sink)`, bit for bit, without
    /// encoding the paintings again (their statistics from the setup are reused).
    pub fn with_held_out_views(self, views: &[View], sink: &dyn Sink) -> Result<Self, TrainError> {
        self.held_out_samples(views, None, sink)
    }

    /// The held-out samples of `views` and the paintings of `styles`, or of the training
    /// paintings (their statistics from the setup) without `styles`.
    fn held_out_samples(
        mut self,
        views: &[View],
        styles: Option<&ImageSet>,
        sink: &dyn Sink,
    ) -> Result<Self, TrainError> {
        if self.config.eval_pairs == 0 {
            return Ok(self);
        }
        let style_count = styles.map_or(self.styles.len(), ImageSet::len);
        if views.is_empty() || style_count == 0 {
            return Err(TrainError::Dataset(format!(
                "held-out evaluation needs views and styles ({} views, {style_count} styles)",
                views.len(),
            )));
        }
        let deepest = self.lifter.out_channels();
        let pairs = eval_indices(
            self.config.seed,
            self.config.eval_pairs,
            views.len(),
            style_count,
        );
        let mut view_ids: Vec<usize> = pairs.iter().map(|p| p.0).collect();
        let mut style_ids: Vec<usize> = pairs.iter().map(|p| p.1).collect();
        view_ids.sort_unstable();
        view_ids.dedup();
        style_ids.sort_unstable();
        style_ids.dedup();
        let encoded_styles = if styles.is_some() { style_ids.len() } else { 0 };
        let mut tally = Tally::start(Stage::Prepare, view_ids.len() + encoded_styles, sink);
        let mut targets = Vec::with_capacity(view_ids.len());
        for &v in &view_ids {
            let view = &views[v];
            view.check().map_err(|e| match e {
                TrainError::Dataset(m) => TrainError::Dataset(format!("held-out {m}")),
                e => e,
            })?;
            let e = encode_view(
                &self.encoder,
                self.config.variant,
                self.config.normalize,
                view,
                deepest,
            )?;
            targets.push(e.target);
            tally.advance(1, "encode held-out views");
        }
        let mut stats = Vec::with_capacity(style_ids.len());
        for &st in &style_ids {
            match styles {
                Some(styles) => {
                    let img = styles.load_resized(st, self.config.style_size)?;
                    stats.push(encode_style(&self.encoder, &to_tensor(&img))?);
                    tally.advance(1, "encode held-out styles");
                }
                None => stats.push(self.styles[st].clone()),
            }
        }
        tally.finish();
        let crop = self.config.crop_side() as usize;
        let at = |ids: &[usize], i: usize| ids.binary_search(&i).expect("drawn above");
        self.eval = pairs
            .iter()
            .map(|&(v, st)| {
                EvalSample::new(
                    views[v].camera,
                    &targets[at(&view_ids, v)],
                    stats[at(&style_ids, st)].clone(),
                    crop,
                )
            })
            .collect();
        Ok(self)
    }

    /// The mean loss over the fixed evaluation samples (see "Evaluation" in the module
    /// documentation) with the full loss weights of the configuration; `None` without samples
    /// (`eval_pairs = 0`).
    pub fn evaluate_fixed(&self) -> Result<Option<FeatureEvaluation>, TrainError> {
        if self.eval.is_empty() {
            return Ok(None);
        }
        let bg = vec![0.0f32; self.config.feature_dim];
        let weights = Stage3Weights {
            train_decoder: false,
            ..self.config.weights()
        };
        let setup = self.stage3_setup(&bg, weights);
        let mut sum = [0.0f64; 4];
        for e in &self.eval {
            let camera = feature_map_camera(
                &self.encoder,
                self.config.variant,
                &e.camera,
                e.feature_size,
            );
            let sample = Stage3Sample {
                camera: &camera,
                feature_size: e.feature_size,
                align_target: &e.target,
                style: &e.style,
                window: e.window,
            };
            let g = stage3_gradients(&self.scene, &setup, &sample)?;
            for (acc, x) in sum
                .iter_mut()
                .zip([g.loss_align, g.loss_content, g.loss_style, g.loss])
            {
                *acc += x;
            }
        }
        let n = self.eval.len() as f64;
        Ok(Some(FeatureEvaluation {
            step: self.step,
            pairs: self.eval.len(),
            loss_align: sum[0] / n,
            loss_content: sum[1] / n,
            loss_style: sum[2] / n,
            loss: sum[3] / n,
        }))
    }

    /// The current networks with the feature background `bg` and the loss weights `weights`.
    fn stage3_setup<'a>(&'a self, bg: &'a [f32], weights: Stage3Weights) -> Stage3Setup<'a, f32> {
        Stage3Setup {
            lifter: &self.lifter,
            decoder: &self.decoder,
            encoder: &self.encoder,
            feature_background: bg,
            weights,
            normalize: self.config.normalize,
            supersample: self.config.supersample as usize,
        }
    }

    /// Runs [`FeatureTrainer::evaluate_fixed`], reports it and keeps it for the summary.
    fn evaluate_and_report(&mut self, sink: &dyn Sink) -> Result<(), TrainError> {
        if let Some(e) = self.evaluate_fixed()? {
            sink.emit(Event::Evaluation {
                stage: Stage::Features,
                step: e.step,
                metrics: e.metrics(),
            });
            self.evaluations.push(e);
        }
        Ok(())
    }

    /// Continues a run from a checkpoint written by [`FeatureTrainer::save_checkpoint`], with
    /// the same inputs (geometry and encoder are checked by fingerprint; the configuration may
    /// differ, e.g. more iterations); silent and without a cache
    /// ([`FeatureTrainer::resume_with`]).
    pub fn resume(
        checkpoint: &Path,
        config: FeatureTrainConfig,
        inputs: FeatureInputs,
    ) -> Result<Self, TrainError> {
        FeatureTrainer::resume_with(checkpoint, config, inputs, &FeatureSetup::quiet())
    }

    /// [`FeatureTrainer::resume`] with the setup of [`FeatureTrainer::new_with`]. The checkpoint
    /// is read and checked against the inputs before the setup, so a checkpoint that does not
    /// fit is refused at once.
    pub fn resume_with(
        checkpoint: &Path,
        config: FeatureTrainConfig,
        inputs: FeatureInputs,
        setup: &FeatureSetup,
    ) -> Result<Self, TrainError> {
        let bytes = std::fs::read(checkpoint).map_err(|e| TrainError::io(checkpoint, e))?;
        let r = StateReader::new(&bytes, checkpoint, FEATURE_CHECKPOINT_FORMAT)?;
        config.validate()?;
        let c = check_networks(&inputs.encoder, &inputs.decoder)?;
        let check = |key: &str, want: &str, what: &str| -> Result<(), TrainError> {
            let found = r.meta_str(key)?;
            if found != want {
                return Err(r.err(format!(
                    "it belongs to another {what} (fingerprint {found}, this one's is {want})"
                )));
            }
            Ok(())
        };
        // The fingerprint covers the geometry, not the features, which the setup replaces.
        check(
            "geometry_fingerprint",
            &geometry_fingerprint(&inputs.geometry),
            "geometry",
        )?;
        check(
            "encoder_fingerprint",
            &weights_fingerprint(&inputs.encoder),
            "encoder",
        )?;
        let (n, f) = (inputs.geometry.len(), config.feature_dim);
        let features = r.f32s("features", &[n, f])?;
        let w = r.f32s("lifter.weight", &[c, f, 1, 1])?;
        let b = r.f32s("lifter.bias", &[c])?;
        let lifter = Lifter::new(
            Array4::from_shape_vec((c, f, 1, 1), w).expect("checked shape"),
            ndarray::Array1::from_vec(b),
        )?;
        // Checkpoints from before the ablations carry neither entry: the paper's design.
        let design = |key: &str, default: &str| -> Result<String, TrainError> {
            Ok(if r.has_meta(key) {
                r.meta_str(key)?.to_string()
            } else {
                default.to_string()
            })
        };
        for (key, found, want) in [
            (
                "decoder_mode",
                design("decoder_mode", DecoderMode::Pretrained.as_str())?,
                config.decoder_mode.as_str(),
            ),
            (
                "normalize",
                design("normalize", FeatureNorm::BeforeRaster.as_str())?,
                config.normalize.as_str(),
            ),
        ] {
            if found != want {
                return Err(r.err(format!(
                    "it was written by a run with {key} `{found}`, this run asks for `{want}`"
                )));
            }
        }
        let decoder = if config.decoder_mode.trains_decoder() {
            let nets = NetWeights::from_bytes(r.bytes("decoder")?)
                .map_err(|e| r.err(format!("decoder: {e}")))?;
            let d = nets
                .decoder
                .ok_or_else(|| r.err("the trained decoder is missing".into()))?;
            if d.in_channels() != c || d.out_channels() != 3 {
                return Err(r.err(format!(
                    "its decoder maps {} channels to {}, this run needs {c} to 3",
                    d.in_channels(),
                    d.out_channels()
                )));
            }
            Some(d.with_resolution(config.variant.resolution()))
        } else {
            None
        };
        let mut adam = r.adam(config.adam)?;
        let mut fresh = Adam::<f32>::new(config.adam);
        fresh.add_param("features", config.lr_features, n, f);
        fresh.add_param("lifter.weight", config.lr_lifter, c, f);
        fresh.add_param("lifter.bias", config.lr_lifter, 1, c);
        if let Some(d) = &decoder {
            register_decoder(&mut fresh, d, config.lr_decoder);
        }
        check_same_params(&adam, &fresh).map_err(|m| r.err(m))?;
        // The learning rates follow the (possibly new) configuration.
        for (i, p) in fresh.params().iter().enumerate() {
            adam.set_lr(i, p.lr);
        }
        let step = r.meta_parse("step")?;
        let ema = r.ema()?;
        let mut t = FeatureTrainer::new_with(config, inputs, setup)?;
        t.scene.features = features;
        t.lifter = lifter;
        if let Some(d) = decoder {
            t.decoder = d;
        }
        t.adam = adam;
        t.step = step;
        t.ema = ema;
        Ok(t)
    }

    /// Completed iterations.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// The Gaussians with their current features.
    pub fn scene(&self) -> &FeatureGaussians<f32> {
        &self.scene
    }

    /// The lifter being trained.
    pub fn lifter(&self) -> &Lifter<f32> {
        &self.lifter
    }

    /// The frozen encoder.
    pub fn encoder(&self) -> &Encoder<f32> {
        &self.encoder
    }

    /// The decoder: frozen, or trained in this stage for the decoder ablation.
    pub fn decoder(&self) -> &Decoder<f32> {
        &self.decoder
    }

    /// The optimiser state.
    pub fn adam(&self) -> &Adam<f32> {
        &self.adam
    }

    /// Number of training views and of style images.
    pub fn counts(&self) -> (usize, usize) {
        (self.views.len(), self.styles.len())
    }

    /// The scene statistics: mean over the training views of the deepest unnormalised encoder
    /// features' per-channel mean and std.
    pub fn scene_stats(&self) -> (&[f32], &[f32]) {
        (&self.scene_mean, &self.scene_std)
    }

    /// Running averages (factor 0.4 on the newest value) of the total, align, content and style
    /// losses.
    pub fn running_averages(&self) -> Option<[f64; 4]> {
        self.ema
    }

    /// The loss and gradients of one (view, style, window) sample at the current parameters,
    /// with the loss weights of the next iteration.
    pub fn sample_gradients(
        &self,
        view: usize,
        style: usize,
        window: Option<CropWindow>,
    ) -> Result<Stage3Gradients<f32>, TrainError> {
        let v = self.views.get(view).ok_or_else(|| {
            TrainError::Config(format!(
                "view {view} out of range ({} views)",
                self.views.len()
            ))
        })?;
        let st = self.styles.get(style).ok_or_else(|| {
            TrainError::Config(format!(
                "style {style} out of range ({} styles)",
                self.styles.len()
            ))
        })?;
        let (_, _, h, w) = v.target.dim();
        let bg = vec![0.0f32; self.config.feature_dim];
        let setup = self.stage3_setup(&bg, self.config.weights_at(self.step + 1));
        let camera = feature_map_camera(
            &self.encoder,
            self.config.variant,
            &v.camera,
            (w as u32, h as u32),
        );
        let sample = Stage3Sample {
            camera: &camera,
            feature_size: (w as u32, h as u32),
            align_target: &v.target,
            style: st,
            window: window.unwrap_or(CropWindow::full(w, h)),
        };
        stage3_gradients(&self.scene, &setup, &sample)
    }

    /// Runs one iteration.
    pub fn train_step(&mut self) -> Result<FeatureStepReport, TrainError> {
        let it = self.step + 1;
        let mut rng = StdRng::seed_from_u64(mix(self.config.seed, STEP_STREAM, it));
        let view = rng.random_range(0..self.views.len());
        let style = rng.random_range(0..self.styles.len());
        let (_, _, h, w) = self.views[view].target.dim();
        let crop = self.config.crop_side() as usize;
        let side = |n: usize| n.min(crop);
        let (cw, ch) = (side(w), side(h));
        let y = rng.random_range(0..=h - ch);
        let x = rng.random_range(0..=w - cw);
        let weights = self.config.weights_at(it);
        let window = if weights.lambda_content == 0.0 && weights.lambda_style == 0.0 {
            CropWindow::full(w, h)
        } else {
            CropWindow {
                x,
                y,
                width: cw,
                height: ch,
            }
        };
        let g = self.sample_gradients(view, style, Some(window))?;
        self.adam.step(0, &mut self.scene.features, &g.features)?;
        let layer = self.lifter.layer_mut();
        let gw = g.lifter.weight.as_standard_layout();
        let wslice = layer
            .weight
            .as_slice_mut()
            .ok_or_else(|| TrainError::Shape("lifter weight is not contiguous".into()))?;
        self.adam.step(
            1,
            wslice,
            gw.as_slice().expect("standard layout is contiguous"),
        )?;
        let bslice = layer
            .bias
            .as_slice_mut()
            .ok_or_else(|| TrainError::Shape("lifter bias is not contiguous".into()))?;
        self.adam.step(2, bslice, &g.lifter.bias.to_vec())?;
        // A trained decoder (the ablations) steps whenever the networks ran.
        if self.config.decoder_mode.trains_decoder() && !g.decoder.is_empty() {
            step_decoder(&mut self.adam, 3, &mut self.decoder, &g.decoder)?;
        }
        self.step = it;
        let now = [g.loss, g.loss_align, g.loss_content, g.loss_style];
        self.ema = Some(match self.ema {
            None => now,
            Some(e) => std::array::from_fn(|i| 0.4 * now[i] + 0.6 * e[i]),
        });
        Ok(FeatureStepReport {
            step: it,
            view,
            style,
            window,
            loss_align: g.loss_align,
            loss_content: g.loss_content,
            loss_style: g.loss_style,
            loss: g.loss,
        })
    }

    /// Mean loss terms over `(view, style)` pairs, each on the whole feature map.
    pub fn evaluate(&self, pairs: &[(usize, usize)]) -> Result<FeatureEvaluation, TrainError> {
        let mut sum = [0.0f64; 4];
        for &(v, s) in pairs {
            let g = self.sample_gradients(v, s, None)?;
            for (acc, x) in sum
                .iter_mut()
                .zip([g.loss_align, g.loss_content, g.loss_style, g.loss])
            {
                *acc += x;
            }
        }
        let n = pairs.len().max(1) as f64;
        Ok(FeatureEvaluation {
            step: self.step,
            pairs: pairs.len(),
            loss_align: sum[0] / n,
            loss_content: sum[1] / n,
            loss_style: sum[2] / n,
            loss: sum[3] / n,
        })
    }

    /// The scene bundle of the current state.
    pub fn bundle(&self) -> SceneBundle {
        let mut provenance = vec![
            ("stage".to_string(), "feature training".to_string()),
            ("iterations".to_string(), self.step.to_string()),
            ("seed".to_string(), self.config.seed.to_string()),
            (
                "loss weights".to_string(),
                format!(
                    "content {} style {}",
                    self.config.lambda_content, self.config.lambda_style
                ),
            ),
        ];
        if self.config.decoder_mode.trains_decoder() {
            provenance.push((
                "decoder".to_string(),
                format!(
                    "{} decoder trained in stage 3 from the seed",
                    self.config.decoder_mode.as_str()
                ),
            ));
        }
        provenance.extend(self.provenance.iter().cloned());
        SceneBundle {
            scene: self.scene.clone(),
            encoder: self.encoder.clone(),
            decoder: self.decoder.clone(),
            lifter: self.lifter.clone(),
            info: BundleInfo {
                provenance,
                decoder_mode: self.config.decoder_mode,
                normalize: self.config.normalize,
                supersample: self.config.supersample,
                ..BundleInfo::new(
                    &self.encoder,
                    self.config.variant,
                    self.config.feature_dim,
                    self.background,
                    (self.scene_mean.clone(), self.scene_std.clone()),
                    self.cameras.clone(),
                )
            },
        }
    }

    /// Writes the bundle of the current state into `dir`.
    pub fn save_bundle(&self, dir: &Path) -> Result<(), TrainError> {
        Ok(self.bundle().save(dir)?)
    }

    /// The checkpoint as safetensors bytes.
    pub fn checkpoint_bytes(&self) -> Result<Vec<u8>, TrainError> {
        let mut w = StateWriter::new(FEATURE_CHECKPOINT_FORMAT);
        w.meta("step", self.step);
        w.meta("seed", self.config.seed);
        w.meta("geometry_fingerprint", &self.geometry_fingerprint);
        w.meta("encoder_fingerprint", weights_fingerprint(&self.encoder));
        w.meta(
            "config",
            serde_json::to_string(&self.config).map_err(|e| TrainError::Config(e.to_string()))?,
        );
        w.ema(self.ema.as_ref().map(|e| e.as_slice()));
        let (n, f) = (self.scene.len(), self.config.feature_dim);
        w.f32s("features", vec![n, f], &self.scene.features);
        let l = self.lifter.layer();
        let lw = l.weight.as_standard_layout();
        w.f32s(
            "lifter.weight",
            l.weight.shape().to_vec(),
            lw.as_slice().expect("standard layout"),
        );
        w.f32s("lifter.bias", vec![l.bias.len()], &l.bias.to_vec());
        w.meta("decoder_mode", self.config.decoder_mode.as_str());
        w.meta("normalize", self.config.normalize.as_str());
        if self.config.decoder_mode.trains_decoder() {
            let nets = NetWeights {
                decoder: Some(self.decoder.clone()),
                ..Default::default()
            };
            w.bytes("decoder", nets.to_bytes()?);
        }
        w.adam(&self.adam);
        w.finish()
    }

    /// Writes a checkpoint atomically.
    pub fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        base::write_atomic(path, &self.checkpoint_bytes()?).map_err(|e| TrainError::io(path, e))
    }

    /// Trains up to `config.iterations` through the [driver](crate::driver). With an output
    /// folder, the checkpoint is `out_dir/checkpoint.safetensors` and the scene bundle
    /// `out_dir/bundle/`.
    pub fn train(&mut self, run: &Run) -> Result<FeatureTrainSummary, TrainError> {
        let cadence = Cadence {
            checkpoint_interval: self.config.checkpoint_interval,
            log_interval: self.config.log_interval,
        };
        self.evaluations.clear();
        let run = drive(self, cadence, run)?;
        Ok(FeatureTrainSummary {
            run,
            running_losses: self.ema,
            evaluations: std::mem::take(&mut self.evaluations),
        })
    }
}

impl TrainingLoop for FeatureTrainer {
    const STAGE: Stage = Stage::Features;

    fn step(&self) -> u64 {
        self.step
    }

    fn iterations(&self) -> u64 {
        self.config.iterations
    }

    fn advance(&mut self) -> Result<(), TrainError> {
        self.train_step().map(|_| ())
    }

    fn status(&self) -> String {
        let e = self.ema.unwrap_or_default();
        format!(
            "loss {:.5} align {:.5} content {:.5} style {:.5}",
            e[0], e[1], e[2], e[3]
        )
    }

    fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
        FeatureTrainer::save_checkpoint(self, path)
    }

    fn start(&mut self, sink: &dyn Sink) -> Result<(), TrainError> {
        if self.step == 0 && self.config.iterations > 0 {
            self.evaluate_and_report(sink)?;
        }
        Ok(())
    }

    fn after_step(&mut self, _out_dir: Option<&Path>, sink: &dyn Sink) -> Result<(), TrainError> {
        let (it, k) = (self.step, self.config.eval_interval);
        if (k > 0 && it.is_multiple_of(k)) || it == self.config.iterations {
            self.evaluate_and_report(sink)?;
        }
        Ok(())
    }

    fn finish(&mut self, out_dir: &Path) -> Result<Option<(&'static str, PathBuf)>, TrainError> {
        let p = out_dir.join(BUNDLE_DIR);
        self.save_bundle(&p)?;
        Ok(Some(("bundle", p)))
    }
}
