//! What a feature training run starts from ([`FeatureInputs`], [`dataset_views`]) and the steps
//! of its setup ([`FeatureSetup`]): checking the inputs, drawing the initial parameters from the
//! seed, and encoding the training views and style images (through the encoding cache), which
//! also gives the scene statistics and the fixed evaluation samples.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use gaussian::dataset::images::RgbImage;
use gaussian::dataset::Dataset;
use gaussian::{Camera, FeatureGaussians};
use ndarray::Array4;
use nets::{Decoder, Encoder, Lifter};
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use style::{channel_stats, encode_style, FeatureNorm, StyleFeatureStats};

use super::cache::{stats_from_values, stats_values, CacheValues, EncodingCache};
use super::config::FeatureTrainConfig;
use super::evaluation::{eval_indices, EvalSample};
use crate::adam::Adam;
use crate::decoder_training::{
    conv_default_init, init_decoder_with, init_mlp_decoder, mix, register_decoder, INIT_STREAM,
};
use crate::error::TrainError;
use crate::geometry::{load_views, View};
use crate::image_folder::{to_tensor, ImageSet};
use base::event::{Event, Quiet, Sink, Stage, Tally};
use runtime::bundle::{feature_size, CameraRecord, DecoderMode, Variant};

/// The geometry, views, styles and networks feature training starts from.
pub struct FeatureInputs {
    /// Trained geometry; any features it carries are replaced.
    pub geometry: FeatureGaussians<f32>,
    /// The training views (camera and RGB image, at the resolution to train at).
    pub views: Vec<View>,
    /// Every camera of the dataset with its held-out flag, recorded in the bundle (empty: the
    /// training views' cameras).
    pub cameras: Vec<CameraRecord>,
    /// The style images.
    pub styles: ImageSet,
    /// The frozen encoder the features are aligned to.
    pub encoder: Encoder<f32>,
    /// The frozen decoder that turns style-transformed lifted features into images.
    pub decoder: Decoder<f32>,
    /// The RGB background the geometry was trained on (recorded in the bundle).
    pub background: [f32; 3],
    /// Where the inputs came from, recorded in the bundle.
    pub provenance: Vec<(String, String)>,
}

/// The training views of a dataset (every image, or the training part of the every-8th split
/// when `eval_split` is set) and the records of all its cameras with their held-out flags. The
/// images are decoded a few at a time in parallel, reported to `sink` as [`Stage::Prepare`]
/// progress (`decode views`).
pub fn dataset_views(
    dataset: &Dataset,
    eval_split: bool,
    sink: &dyn Sink,
) -> Result<(Vec<View>, Vec<CameraRecord>), TrainError> {
    let held_out: Vec<bool> = if eval_split {
        let test = dataset.split().test;
        (0..dataset.len()).map(|i| test.contains(&i)).collect()
    } else {
        vec![false; dataset.len()]
    };
    let train: Vec<usize> = (0..dataset.len()).filter(|&i| !held_out[i]).collect();
    let mut tally = Tally::start(Stage::Prepare, train.len(), sink);
    let mut views = Vec::with_capacity(train.len());
    for chunk in train.chunks(2 * rayon::current_num_threads().max(1)) {
        views.extend(load_views(dataset, chunk)?);
        tally.advance(chunk.len(), "decode views");
    }
    tally.finish();
    let cameras = (0..dataset.len())
        .map(|i| CameraRecord::new(dataset.names[i].clone(), &dataset.cameras[i], held_out[i]))
        .collect();
    Ok((views, cameras))
}

/// How [`FeatureTrainer::new_with`](super::FeatureTrainer::new_with) reports its setup and
/// where it keeps the encodings it can reuse.
#[derive(Clone, Copy)]
pub struct FeatureSetup<'a> {
    /// Where the setup's [`Stage::Prepare`] progress and its summary line go.
    pub sink: &'a dyn Sink,
    /// The folder of cached encodings to read and fill (see "Encoding cache" in the module
    /// documentation; a run's is `OUT/`[`ENCODINGS_DIR`](super::ENCODINGS_DIR)); `None` encodes
    /// everything and writes nothing.
    pub cache: Option<&'a Path>,
}

impl FeatureSetup<'static> {
    /// No progress, no cache.
    pub fn quiet() -> Self {
        FeatureSetup {
            sink: &Quiet,
            cache: None,
        }
    }
}

/// Checks that the encoder takes RGB and the decoder its deepest width; returns that width.
pub(super) fn check_networks(
    encoder: &Encoder<f32>,
    decoder: &Decoder<f32>,
) -> Result<usize, TrainError> {
    let deepest = *encoder.widths().last().unwrap_or(&0);
    if encoder.in_channels() != 3 || decoder.in_channels() != deepest {
        return Err(TrainError::Config(format!(
            "the encoder takes {} channels and ends with {deepest}, the decoder takes {} \
             (expected 3 and a decoder of the encoder's deepest width)",
            encoder.in_channels(),
            decoder.in_channels()
        )));
    }
    Ok(deepest)
}

/// One encoded training view: its alignment target (normalised or not, [`FeatureNorm`]) and the
/// per-channel mean and std of its unnormalised deepest features.
pub(super) struct ViewEncoding {
    pub(super) target: Array4<f32>,
    pub(super) mean: Vec<f32>,
    pub(super) std: Vec<f32>,
}

/// Encodes one training view (see the module documentation).
pub(super) fn encode_view(
    encoder: &Encoder<f32>,
    variant: Variant,
    normalize: FeatureNorm,
    v: &View,
    deepest: usize,
) -> Result<ViewEncoding, TrainError> {
    let k = v.camera.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let x = Array4::from_shape_fn((1, 3, h, w), |(_, c, y, x)| v.image[(y * w + x) * 3 + c]);
    let mut feats = encoder.forward(x.view())?;
    let deep = feats.pop().expect("encoder depth >= 1");
    let (fw, fh) = feature_size(encoder, variant, k.width, k.height);
    if deep.dim() != (1, deepest, fh as usize, fw as usize) {
        return Err(TrainError::Shape(format!(
            "view `{}`: the encoder gives {:?}, the feature map is {fw}x{fh}",
            v.name,
            deep.shape()
        )));
    }
    let stats = channel_stats(&deep)?;
    let target = normalize.align_target_with_stats(deep, &stats)?;
    Ok(ViewEncoding {
        target: if target.is_standard_layout() {
            target
        } else {
            target.as_standard_layout().into_owned()
        },
        mean: stats.mean.iter().copied().collect(),
        std: stats.std.iter().copied().collect(),
    })
}

/// A training view reduced to what the loss needs.
#[derive(Clone, Debug)]
pub(super) struct CachedView {
    pub(super) camera: Camera,
    /// Shared with the encoding cache's writer while it writes the file.
    pub(super) target: Arc<Array4<f32>>,
}

/// Checks the inputs of a run before anything is computed: the networks fit each other
/// ([`check_networks`]), the geometry has Gaussians, and there are training views, each with an
/// image that fits its camera. Returns the encoder's deepest width.
pub(super) fn check_inputs(inputs: &FeatureInputs) -> Result<usize, TrainError> {
    let deepest = check_networks(&inputs.encoder, &inputs.decoder)?;
    if inputs.geometry.is_empty() {
        return Err(TrainError::Dataset("the geometry has no Gaussians".into()));
    }
    if inputs.views.is_empty() {
        return Err(TrainError::Dataset("no training views".into()));
    }
    for v in &inputs.views {
        v.check()?;
    }
    Ok(deepest)
}

/// The trained parameters of a fresh run, drawn from the seed.
pub(super) struct InitialParameters {
    /// The geometry with its initial features.
    pub(super) scene: FeatureGaussians<f32>,
    /// The initial lifter.
    pub(super) lifter: Lifter<f32>,
    /// The frozen decoder, or the initial one of a decoder ablation.
    pub(super) decoder: Decoder<f32>,
}

/// Draws the initial parameters from the seed's initialisation stream, in this order: the
/// features (`N(0, feature_init_std^2)`), the lifter ([`conv_default_init`]), then the decoder of
/// a decoder ablation. `encoder` and `decoder` are at the run's resolution.
pub(super) fn init_parameters(
    config: &FeatureTrainConfig,
    geometry: FeatureGaussians<f32>,
    encoder: &Encoder<f32>,
    decoder: Decoder<f32>,
    deepest: usize,
) -> Result<InitialParameters, TrainError> {
    let res = config.variant.resolution();
    let f = config.feature_dim;
    let mut rng = StdRng::seed_from_u64(mix(config.seed, INIT_STREAM, 0));
    let normal = Normal::new(0.0, config.feature_init_std)
        .map_err(|e| TrainError::Config(format!("feature_init_std: {e}")))?;
    let mut scene = geometry.with_features(f, 0.0);
    for v in scene.features.iter_mut() {
        *v = normal.sample(&mut rng) as f32;
    }
    scene.validate().map_err(|error| TrainError::Scene {
        what: "the geometry".into(),
        error,
    })?;
    let (w, b) = conv_default_init(deepest, f, 1, &mut rng);
    let lifter = Lifter::new(w, b)?;
    // The ablations' decoders draw after the features and the lifter, so the paper's design
    // starts from the same values with or without them.
    let decoder = match config.decoder_mode {
        DecoderMode::Pretrained => decoder,
        DecoderMode::Scratch => init_decoder_with(encoder, &mut rng)?.with_resolution(res),
        DecoderMode::Mlp => init_mlp_decoder(deepest, &mut rng)?.with_resolution(res),
    };
    Ok(InitialParameters {
        scene,
        lifter,
        decoder,
    })
}

/// The camera records of the bundle: `cameras`, or, when there are none, the training views'
/// cameras.
pub(super) fn camera_records(cameras: Vec<CameraRecord>, views: &[View]) -> Vec<CameraRecord> {
    if cameras.is_empty() {
        views
            .iter()
            .map(|v| CameraRecord::new(v.name.clone(), &v.camera, false))
            .collect()
    } else {
        cameras
    }
}

/// What the setup makes of the images: the training views' alignment targets, the scene
/// statistics, the styles' statistics and the fixed evaluation samples.
pub(super) struct Encodings {
    /// The training views, each reduced to its camera and alignment target.
    pub(super) views: Vec<CachedView>,
    /// The mean over the views of the deepest unnormalised features' per-channel mean.
    pub(super) scene_mean: Vec<f32>,
    /// The same of their per-channel std.
    pub(super) scene_std: Vec<f32>,
    /// Each style image's per-level statistics.
    pub(super) styles: Vec<StyleFeatureStats<f32>>,
    /// The fixed evaluation samples drawn from the training views and styles.
    pub(super) eval: Vec<EvalSample>,
}

/// Decodes the style images, then encodes the views and the styles, reading and filling the
/// encoding cache `setup.cache`, draws the evaluation samples, and reports it all to
/// `setup.sink` as [`Stage::Prepare`] progress and a summary line (see the module
/// documentation). `encoder` is at the run's resolution.
pub(super) fn encode_inputs(
    config: &FeatureTrainConfig,
    encoder: &Encoder<f32>,
    views: Vec<View>,
    styles: &ImageSet,
    deepest: usize,
    setup: &FeatureSetup,
) -> Result<Encodings, TrainError> {
    let start = Instant::now();
    let mut tally = Tally::start(Stage::Prepare, 2 * styles.len() + views.len(), setup.sink);
    let style_images = decode_styles(styles, config.style_size, &mut tally)?;
    let mut cache = setup
        .cache
        .and_then(|dir| EncodingCache::new(dir, encoder, config.variant, config.normalize));
    let EncodedViews {
        views,
        scene_mean,
        scene_std,
    } = encode_views(config, encoder, views, deepest, &mut cache, &mut tally)?;
    let styles = encode_styles(encoder, style_images, &mut cache, &mut tally)?;
    let eval = eval_samples(config, &views, &styles);
    if let Some(c) = &mut cache {
        c.finish();
    }
    report_setup(
        (views.len(), styles.len()),
        start,
        cache.as_ref(),
        tally,
        setup.sink,
    );
    Ok(Encodings {
        views,
        scene_mean,
        scene_std,
        styles,
        eval,
    })
}

/// Every style image with its short side resized to `style_size`, all decoded before anything
/// is encoded: a bad file stops the run now.
fn decode_styles(
    styles: &ImageSet,
    style_size: u32,
    tally: &mut Tally,
) -> Result<Vec<RgbImage>, TrainError> {
    let mut decoded = 0;
    styles.load_all_resized(style_size, &mut |done| {
        tally.advance(done - decoded, "decode styles");
        decoded = done;
    })
}

/// The training views reduced to what the loss needs, with the scene statistics: the mean over
/// the views of each one's per-channel mean and std.
struct EncodedViews {
    views: Vec<CachedView>,
    scene_mean: Vec<f32>,
    scene_std: Vec<f32>,
}

/// Encodes every training view, or reads its encoding from the cache (and caches the ones
/// encoded).
fn encode_views(
    config: &FeatureTrainConfig,
    encoder: &Encoder<f32>,
    views: Vec<View>,
    deepest: usize,
    cache: &mut Option<EncodingCache<'_>>,
    tally: &mut Tally,
) -> Result<EncodedViews, TrainError> {
    let mut mean_sum = vec![0.0f64; deepest];
    let mut std_sum = vec![0.0f64; deepest];
    let mut cached = Vec::with_capacity(views.len());
    for v in &views {
        let k = v.camera.intrinsics;
        let (fw, fh) = feature_size(encoder, config.variant, k.width, k.height);
        let shape = (1, deepest, fh as usize, fw as usize);
        let len = deepest * (fh as usize * fw as usize + 2);
        let entry = cache
            .as_ref()
            .map(|c| c.entry("view", k.width, k.height, &v.image));
        let stored = match (&mut *cache, &entry) {
            (Some(c), Some((name, key))) => c.read(name, key, len),
            _ => None,
        };
        let (target, mean, std) = match stored {
            Some(mut values) => {
                let std = values.split_off(len - deepest);
                let mean = values.split_off(len - 2 * deepest);
                let target =
                    Array4::from_shape_vec(shape, values).map_err(|error| TrainError::Array {
                        what: format!("cannot rebuild the cached encoding of view `{}`", v.name),
                        error,
                    })?;
                (Arc::new(target), mean, std)
            }
            None => {
                let e = encode_view(encoder, config.variant, config.normalize, v, deepest)?;
                let target = Arc::new(e.target);
                if let (Some(c), Some((name, key))) = (&mut *cache, &entry) {
                    c.write(
                        name,
                        key,
                        vec![
                            CacheValues::Shared(Arc::clone(&target)),
                            CacheValues::Own(e.mean.clone()),
                            CacheValues::Own(e.std.clone()),
                        ],
                    );
                }
                (target, e.mean, e.std)
            }
        };
        for ch in 0..deepest {
            mean_sum[ch] += mean[ch] as f64;
            std_sum[ch] += std[ch] as f64;
        }
        cached.push(CachedView {
            camera: v.camera,
            target,
        });
        tally.advance(1, "encode views");
    }
    drop(views);
    let nv = cached.len() as f64;
    let scene_mean = mean_sum.iter().map(|&s| (s / nv) as f32).collect();
    let scene_std = std_sum.iter().map(|&s| (s / nv) as f32).collect();
    Ok(EncodedViews {
        views: cached,
        scene_mean,
        scene_std,
    })
}

/// The per-level statistics of every style image, encoded or read from the cache (and cached
/// when encoded).
fn encode_styles(
    encoder: &Encoder<f32>,
    style_images: Vec<RgbImage>,
    cache: &mut Option<EncodingCache<'_>>,
    tally: &mut Tally,
) -> Result<Vec<StyleFeatureStats<f32>>, TrainError> {
    let widths = encoder.widths().to_vec();
    let stats_len = 2 * widths.iter().sum::<usize>();
    let mut style_stats = Vec::with_capacity(style_images.len());
    for img in &style_images {
        let entry = cache
            .as_ref()
            .map(|c| c.entry("style", img.width, img.height, &img.data));
        let stored = match (&mut *cache, &entry) {
            (Some(c), Some((name, key))) => c.read(name, key, stats_len),
            _ => None,
        };
        let stats = match stored {
            Some(values) => stats_from_values(&values, &widths)?,
            None => {
                let stats = encode_style(encoder, &to_tensor(img))?;
                if let (Some(c), Some((name, key))) = (&mut *cache, &entry) {
                    c.write(name, key, vec![CacheValues::Own(stats_values(&stats))]);
                }
                stats
            }
        };
        style_stats.push(stats);
        tally.advance(1, "encode styles");
    }
    Ok(style_stats)
}

/// The fixed evaluation samples of the training views and styles: `eval_pairs` (view, style)
/// pairs from the seed, each on the view's centred window.
fn eval_samples(
    config: &FeatureTrainConfig,
    views: &[CachedView],
    styles: &[StyleFeatureStats<f32>],
) -> Vec<EvalSample> {
    let crop = config.crop_side() as usize;
    eval_indices(config.seed, config.eval_pairs, views.len(), styles.len())
        .into_iter()
        .map(|(v, st)| {
            let view = &views[v];
            EvalSample::new(view.camera, &view.target, styles[st].clone(), crop)
        })
        .collect()
}

/// Ends the setup's report: removes the cache files the run did not use, warns if the cache
/// could not be written, and sends the summary line (views and styles encoded, the time since
/// `start`, and with a cache how many encodings were reused or found unsound).
fn report_setup(
    (views, styles): (usize, usize),
    start: Instant,
    cache: Option<&EncodingCache<'_>>,
    tally: Tally,
    sink: &dyn Sink,
) {
    let mut summary = format!(
        "{} views and {} style images encoded in {:.1} s",
        views,
        styles,
        start.elapsed().as_secs_f64()
    );
    if let Some(c) = cache {
        c.prune();
        summary += &format!(
            " ({} reused from {}{})",
            c.reused,
            c.dir.display(),
            if c.rebuilt > 0 {
                format!(", {} unsound cache files encoded again", c.rebuilt)
            } else {
                String::new()
            }
        );
        if let Some(e) = &c.write_error {
            sink.emit(Event::Warning(format!("encodings not cached: {e}")));
        }
    }
    tally.finish();
    sink.emit(Event::Log {
        stage: Stage::Prepare,
        message: summary,
    });
}

/// The optimiser of a fresh run, its groups in this order: the features, the lifter's weight
/// and bias, and the decoder when this stage trains it (the decoder ablations).
pub(super) fn new_optimiser(
    config: &FeatureTrainConfig,
    n: usize,
    deepest: usize,
    decoder: &Decoder<f32>,
) -> Adam<f32> {
    let f = config.feature_dim;
    let mut adam = Adam::new(config.adam);
    adam.add_param("features", config.lr_features, n, f);
    adam.add_param("lifter.weight", config.lr_lifter, deepest, f);
    adam.add_param("lifter.bias", config.lr_lifter, 1, deepest);
    if config.decoder_mode.trains_decoder() {
        register_decoder(&mut adam, decoder, config.lr_decoder);
    }
    adam
}
