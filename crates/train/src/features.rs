//! Feature training (the third stage): learnable features on frozen Gaussians, and the lifter
//! that maps them to the encoder's deepest feature space, trained so that decoding the
//! style-transformed lifted features gives stylized views.
//!
//! Geometry, encoder and decoder are frozen. Per Gaussian there is a feature of `F` channels
//! (initialised `N(0, feature_init_std^2)` from the seed); the lifter `l = relu(W r + b)` is
//! initialised like PyTorch's default `Conv2d` (uniform in `+-1/sqrt(F)`, see
//! [`conv_default_init`]). Feature maps follow the bundle's convention ([`runtime::frame`]):
//! features are rasterized at the variant's feature resolution ([`feature_size`]) with the
//! camera's intrinsics rescaled to it, over a zero feature background.
//!
//! Iteration `i` (counted from 1; the random choices come from a generator that is a function
//! of the seed and `i` only, so a resumed run continues exactly):
//! 1. draw a training view, then a style image, then a crop window of `crop x crop` feature
//!    pixels (row offset, then column; the whole map when it is smaller). Iterations without
//!    the content and style terms (the alignment warm-up, or the alignment-only ablation) use
//!    the whole map instead: the window only bounds the cost of the decoder and encoder
//!    passes, and a window drawn at random over-weights the object against the background;
//! 2. rasterize the window of the view's feature map, `r` (only its pixels; the Gaussians are
//!    projected for the whole map, [`raster::render_window`]), and cut the window out of the
//!    view's cached alignment target;
//! 3. evaluate the 3D stylization loss on the window ([`style::stage3_loss`]):
//!    `L = align(l(r), target) + lambda_c content(phi_k(g(t)), t) + lambda_s style(phi(g(t)), S)`
//!    with `t = std_s l(r) + mean_s`; with both lambdas zero (the alignment-only ablation) the
//!    decoder and encoder are not run at all and the content and style terms are reported as 0;
//! 4. run the rasterizer's backward pass from `dL/dr` on the window
//!    ([`raster::render_backward_features`], feature channels) to per-Gaussian feature gradients;
//! 5. Adam steps the features and the lifter's weight and bias (nothing else changes).
//!
//! [`stage3_gradients`] is steps 2-4 for any precision, so the same code is checked against
//! central differences in `f64`.
//!
//! Caches. Before training ([`FeatureTrainer::new_with`], reported as [`Stage::Prepare`]
//! progress), every style image is decoded (short side resized to `style_size`), so a bad file
//! stops the run at once, not after the views are encoded. Then every training view is encoded
//! once: its alignment target (the instance-normalised `relu_k_1`, [`style::align_target`]) is
//! kept at the feature resolution, `C x h x w` `f32` values per view (`C` the encoder's deepest
//! width), i.e. `4 C h w` bytes per view: for the standard variant with `C = 512` and
//! 400 x 400 views (50 x 50 features) 5 MB per view; for fullres, where `h x w` is the image
//! size, 328 MB per 400 x 400 view, so fullres runs want small images. The unnormalised
//! features' per-channel mean and std are averaged over the views into the scene statistics of
//! the bundle. Every style image is encoded once and only its per-level statistics are kept.
//!
//! Encoding cache. Given a cache folder ([`FeatureSetup::cache`], [`ENCODINGS_DIR`] of the
//! output folder), each view's target and statistics and each style's statistics are also
//! written there, one file per view or style, named by a hash (FNV-1a) of everything the
//! encoding depends on: the program (its version and its executable's size and modification
//! time), the encoder's weights, the variant, and the decoded pixels and size of the image. A
//! rerun or resume with the same inputs reads them back instead of encoding: the values are the
//! ones the encoder gives, bit for bit, so training continues exactly as without the cache. A
//! file is used only if its format, key, length and checksum all match; anything else is
//! encoded afresh and rewritten, and files no longer used by the run are removed. The files are
//! written atomically but not synced to disk ([`base::write_atomic_unsynced_with`]): a file
//! that a system crash left empty or partial fails its checksum and is rebuilt. They are
//! written by a thread of their own while encoding goes on, from the same target arrays as
//! training uses (no second copy in memory), around the page cache where the system allows it
//! (so a run does not pay the kernel's copy of gigabytes into it, nor fill memory with them), and
//! the setup waits for the last one before it reports.
//!
//! Ablations (the paper's Fig. 4 and 5), chosen by [`FeatureTrainConfig::decoder_mode`] and
//! [`FeatureTrainConfig::normalize`] and recorded in the bundle:
//! - [`DecoderMode::Scratch`] and [`DecoderMode::Mlp`] replace the frozen pre-trained decoder
//!   by one initialised from the seed (the encoder's mirror CNN, or a per-pixel MLP) whose
//!   weights Adam steps in every iteration with content and style terms, at
//!   [`FeatureTrainConfig::lr_decoder`];
//! - [`FeatureNorm::AfterRaster`] aligns the lifted features with the unnormalised `relu_k_1`
//!   and normalises each lifted window over its own pixels before the transform (stylization
//!   then normalises over the whole view, see [`runtime::frame`]).
//!
//! Evaluation ([`FeatureTrainer::evaluate_fixed`]): the mean loss, with the full loss weights
//! (content and style terms included, also during the warm-up), over `eval_pairs` fixed samples
//! drawn once from the seed, each a view, a style and the centred `crop x crop` window of the
//! view's feature map. By default the views and styles are the training ones (a fixed
//! yardstick of how the training loss moves); [`FeatureTrainer::with_held_out`] draws them from
//! held-out views and styles never trained on instead, so the curve measures generalisation to
//! new views and paintings ([`FeatureTrainer::with_held_out_views`]: held-out views with the
//! training paintings, whose statistics the setup already has). The run evaluates before its
//! first iteration, every `eval_interval` iterations and at the end, and reports each as an
//! [`Event::Evaluation`]; an evaluation changes nothing, so it does not affect training or
//! resuming.
//!
//! Checkpoints hold the features, the lifter, a trained decoder, the Adam state and the step;
//! they name the geometry and encoder they belong to by fingerprints, which resuming checks.

use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc};
use std::time::{Instant, UNIX_EPOCH};

use gaussian::dataset::Dataset;
use gaussian::{Camera, FeatureGaussians, Real};
use ndarray::{s, Array4};
use nets::{ConvGrad, Decoder, Encoder, Lifter, NetWeights};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use raster::{render_backward_features, render_window, Channels, PixelWindow, RenderOptions};
use serde::{Deserialize, Serialize};
use style::{
    align_loss, align_loss_backward, channel_stats, encode_style, stage3_loss, ChannelStats,
    FeatureNorm, Stage3Weights, StyleFeatureStats,
};

use crate::adam::{Adam, AdamConfig};
use crate::checkpoint::{StateReader, StateWriter};
use crate::decoder_training::{
    check_same_params, conv_default_init, init_decoder_with, init_mlp_decoder, mix,
    register_decoder, step_decoder, EVAL_STREAM, INIT_STREAM, STEP_STREAM,
};
use crate::driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
use crate::error::TrainError;
use crate::geometry::{load_views, View};
use crate::image_folder::{to_tensor, ImageSet};
use base::event::{Event, Metric, Quiet, Sink, Stage, Tally};
use base::Fnv1a;
use runtime::bundle::{
    feature_size, weights_fingerprint, BundleInfo, CameraRecord, DecoderMode, SceneBundle, Variant,
};

/// The `format` metadata of a feature-training checkpoint.
pub const FEATURE_CHECKPOINT_FORMAT: &str = "dsgs-feature-checkpoint-v1";

/// The checkpoint inside a feature-training output folder, replaced each time one is written.
pub const FEATURE_CHECKPOINT_FILE: &str = crate::driver::CHECKPOINT_FILE;
/// The scene bundle folder inside a feature-training output folder, written when training
/// completes.
pub const BUNDLE_DIR: &str = "bundle";
/// The folder of cached view and style encodings inside a feature-training output folder (see
/// "Encoding cache" in the module documentation).
pub const ENCODINGS_DIR: &str = "encodings";

/// Settings of a feature training run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FeatureTrainConfig {
    /// Total iterations.
    pub iterations: u64,
    /// Channels `F` of each Gaussian's feature (the lifter's input width).
    pub feature_dim: usize,
    /// Standard deviation of the initial features.
    pub feature_init_std: f64,
    /// Adam learning rate of the features. Adam moves a parameter by about the learning rate per
    /// step, and the features must grow from about 0.01 to values of order 1 (the lifted
    /// features match unit-variance targets through a lifter with weights of order
    /// `1/sqrt(F)`) within a few thousand iterations; 3DGS uses 2.5e-3 for colour coefficients
    /// of order 0.5, and the features span a wider range, hence 1e-2.
    pub lr_features: f64,
    /// Adam learning rate of the lifter (PyTorch's default Adam rate; the lifter is one small
    /// layer seeing every pixel of every view).
    pub lr_lifter: f64,
    /// Weight of the content term (0 together with `lambda_style = 0`: alignment only).
    pub lambda_content: f64,
    /// Weight of the style term.
    pub lambda_style: f64,
    /// Iterations at the start that train with the alignment loss only, on the whole feature
    /// map (0: none). They cost a tenth of a full iteration (no decoder and encoder passes) and
    /// give the lifted features
    /// the scene's content before the content and style terms join, which matters for short
    /// runs.
    pub align_warmup: u64,
    /// Standard or fullres networks (decides the feature resolution).
    pub variant: Variant,
    /// Side of the random window of the feature map that runs through the networks, in feature
    /// pixels (a map smaller than the window is taken whole). It bounds the cost of an
    /// iteration. `None` picks [`FeatureTrainConfig::crop_side`]'s default for the variant:
    /// 32 for standard networks (whose decoder turns it into a 256 x 256 image) and 64 for
    /// fullres ones (a 64 x 64 image), windows of similar cost on 2 cores.
    pub crop: Option<u32>,
    /// The short side style images are resized to before they are encoded.
    pub style_size: u32,
    /// Seed of every random choice (initialisation, views, styles, windows).
    pub seed: u64,
    /// Iterations between checkpoints (0: none).
    pub checkpoint_interval: u64,
    /// Iterations between log lines (0: none).
    pub log_interval: u64,
    /// Adam hyper-parameters (PyTorch defaults).
    pub adam: AdamConfig,
    /// Which decoder stage 3 trains against: the frozen pre-trained one (the paper's design),
    /// or, for the decoder ablation, a CNN or a per-pixel MLP trained here from random
    /// initialisation ([`DecoderMode`]).
    pub decoder_mode: DecoderMode,
    /// Adam learning rate of a decoder trained in this stage (AdaIN's decoder rate).
    pub lr_decoder: f64,
    /// Where the features are normalised: before rasterization (the paper's design) or per view
    /// after it (the ablation, [`FeatureNorm`]).
    pub normalize: FeatureNorm,
    /// Number of fixed (view, style) samples of the periodic evaluation (0: none; see
    /// "Evaluation" in the module documentation).
    pub eval_pairs: usize,
    /// Iterations between evaluations (0: only before the first iteration and at the end, when
    /// `eval_pairs > 0`).
    pub eval_interval: u64,
}

impl Default for FeatureTrainConfig {
    fn default() -> Self {
        FeatureTrainConfig {
            iterations: 3000,
            feature_dim: 32,
            feature_init_std: 0.01,
            lr_features: 1e-2,
            lr_lifter: 1e-3,
            lambda_content: 1.0,
            lambda_style: 1.0,
            align_warmup: 0,
            variant: Variant::Standard,
            crop: None,
            style_size: 256,
            seed: 0,
            checkpoint_interval: 500,
            log_interval: 0,
            adam: AdamConfig::default(),
            decoder_mode: DecoderMode::Pretrained,
            lr_decoder: 1e-4,
            normalize: FeatureNorm::BeforeRaster,
            eval_pairs: 8,
            eval_interval: 500,
        }
    }
}

impl FeatureTrainConfig {
    fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::Config(m));
        if self.feature_dim == 0 {
            return bad("feature_dim is 0".into());
        }
        if self.style_size == 0 {
            return bad("style_size is 0".into());
        }
        if self.crop == Some(0) {
            return bad("crop is 0".into());
        }
        if self.decoder_mode == DecoderMode::Mlp && self.variant != Variant::Fullres {
            return bad(
                "the MLP decoder decodes each feature pixel to one image pixel, so it needs the \
                 fullres variant (--variant fullres)"
                    .into(),
            );
        }
        if self.decoder_mode.trains_decoder()
            && self.lambda_content == 0.0
            && self.lambda_style == 0.0
        {
            return bad(format!(
                "the {} decoder is trained by the content and style terms, which the \
                 alignment-only setting leaves out",
                self.decoder_mode.as_str()
            ));
        }
        for (name, v) in [
            ("feature_init_std", self.feature_init_std),
            ("lr_features", self.lr_features),
            ("lr_lifter", self.lr_lifter),
            ("lambda_content", self.lambda_content),
            ("lambda_style", self.lambda_style),
            ("lr_decoder", self.lr_decoder),
        ] {
            if !v.is_finite() || v < 0.0 {
                return bad(format!("{name} = {v} must be finite and non-negative"));
            }
        }
        Ok(())
    }

    /// The window side in feature pixels: `crop`, or the variant's default.
    pub fn crop_side(&self) -> u32 {
        self.crop.unwrap_or(match self.variant {
            Variant::Standard => 32,
            Variant::Fullres => 64,
        })
    }

    /// The loss weights after the warm-up.
    pub fn weights(&self) -> Stage3Weights {
        Stage3Weights {
            lambda_content: self.lambda_content,
            lambda_style: self.lambda_style,
            train_decoder: self.decoder_mode.trains_decoder(),
            ..Stage3Weights::default()
        }
    }

    /// The loss weights of iteration `it` (1-based): alignment only during the warm-up.
    pub fn weights_at(&self, it: u64) -> Stage3Weights {
        if it <= self.align_warmup {
            Stage3Weights {
                lambda_content: 0.0,
                lambda_style: 0.0,
                ..Stage3Weights::default()
            }
        } else {
            self.weights()
        }
    }
}

/// A window of a feature map, in feature pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CropWindow {
    /// Left column of the window.
    pub x: usize,
    /// Top row of the window.
    pub y: usize,
    /// Width of the window.
    pub width: usize,
    /// Height of the window.
    pub height: usize,
}

impl CropWindow {
    /// The whole `width x height` map.
    pub fn full(width: usize, height: usize) -> Self {
        CropWindow {
            x: 0,
            y: 0,
            width,
            height,
        }
    }
}

/// The frozen networks and fixed settings of the 3D stylization loss.
#[derive(Clone, Copy, Debug)]
pub struct Stage3Setup<'a, T: Real> {
    /// The lifter being trained, from `F` feature channels to the encoder's deepest width.
    pub lifter: &'a Lifter<T>,
    /// The frozen decoder.
    pub decoder: &'a Decoder<T>,
    /// The frozen encoder that measures the content and style terms.
    pub encoder: &'a Encoder<T>,
    /// The feature-map background, one value per feature channel.
    pub feature_background: &'a [T],
    /// The loss weights `lambda_c`, `lambda_s` and the alignment penalty.
    pub weights: Stage3Weights,
    /// Where the features are normalised ([`FeatureNorm`]); the alignment target must match.
    pub normalize: FeatureNorm,
}

/// One sample of the loss: a view, its alignment target, a style and a window.
#[derive(Clone, Copy, Debug)]
pub struct Stage3Sample<'a, T> {
    /// The view's camera (any resolution; it is rescaled to `feature_size`).
    pub camera: &'a Camera,
    /// `(width, height)` of the feature map.
    pub feature_size: (u32, u32),
    /// The alignment target: the whole view's, `[1, C, height, width]`, or the window's alone,
    /// `[1, C, window.height, window.width]`.
    pub align_target: &'a Array4<T>,
    /// The style's per-level encoder statistics (per-channel mean and standard deviation).
    pub style: &'a StyleFeatureStats<T>,
    /// The part of the feature map the loss is evaluated on.
    pub window: CropWindow,
}

/// The loss terms of one sample and the gradients of the total.
#[derive(Clone, Debug)]
pub struct Stage3Gradients<T: Real> {
    /// The alignment term `align(l(r), target)` on the window.
    pub loss_align: f64,
    /// The content term; 0 when both lambdas are 0 (the networks are then not run).
    pub loss_content: f64,
    /// The unweighted style term; 0 when both lambdas are 0.
    pub loss_style: f64,
    /// `loss_align + lambda_c loss_content + lambda_s loss_style`.
    pub loss: f64,
    /// `dL/d(features)`, laid out like the scene's features (`N * F`).
    pub features: Vec<T>,
    /// `dL/d(W, b)` of the lifter.
    pub lifter: ConvGrad<T>,
    /// `dL/d(weight, bias)` of every decoder conv; empty when the networks were not run (both
    /// lambdas 0).
    pub decoder: Vec<ConvGrad<T>>,
}

/// Rasterizes the scene's features for `sample`, evaluates the 3D stylization loss on the
/// sample's window and returns the loss terms with the gradients with respect to the
/// per-Gaussian features and the lifter (steps 2-4 of the module documentation).
pub fn stage3_gradients<T: Real>(
    scene: &FeatureGaussians<T>,
    setup: &Stage3Setup<'_, T>,
    sample: &Stage3Sample<'_, T>,
) -> Result<Stage3Gradients<T>, TrainError> {
    let f = scene.feature_dim;
    if setup.lifter.in_channels() != f {
        return Err(TrainError::Shape(format!(
            "the lifter takes {} channels, the Gaussians carry {f}",
            setup.lifter.in_channels()
        )));
    }
    let (fw, fh) = (
        sample.feature_size.0 as usize,
        sample.feature_size.1 as usize,
    );
    let c = setup.lifter.out_channels();
    let win = sample.window;
    if win.width == 0 || win.height == 0 || win.x + win.width > fw || win.y + win.height > fh {
        return Err(TrainError::Shape(format!(
            "window {}x{} at ({}, {}) does not fit a {fw}x{fh} feature map",
            win.width, win.height, win.x, win.y
        )));
    }
    let target = if sample.align_target.dim() == (1, c, fh, fw) {
        sample
            .align_target
            .slice(s![
                ..,
                ..,
                win.y..win.y + win.height,
                win.x..win.x + win.width
            ])
            .to_owned()
    } else if sample.align_target.dim() == (1, c, win.height, win.width) {
        sample.align_target.clone()
    } else {
        return Err(TrainError::Shape(format!(
            "alignment target is {:?}, expected [1, {c}, {fh}, {fw}] (the view) or \
             [1, {c}, {}, {}] (the window)",
            sample.align_target.shape(),
            win.height,
            win.width
        )));
    };
    let cam = sample
        .camera
        .resized(sample.feature_size.0, sample.feature_size.1);
    let opts = RenderOptions::new(Channels::Features, setup.feature_background.to_vec());
    // Only the window's pixels are rasterized (the Gaussians are projected for the whole map).
    let pixels = PixelWindow {
        x: win.x as u32,
        y: win.y as u32,
        width: win.width as u32,
        height: win.height as u32,
    };
    let fwd = render_window(&cam, scene, &opts, pixels)?;
    let img = &fwd.raster.image;
    let r = Array4::from_shape_fn((1, f, win.height, win.width), |(_, ch, y, x)| {
        img[(y * win.width + x) * f + ch]
    });
    let w = setup.weights;
    let (terms, grad_r, grad_lifter, grad_decoder) =
        if w.lambda_content == 0.0 && w.lambda_style == 0.0 {
            let (lifted, tape) = setup.lifter.forward_with_tape(r.view())?;
            let la = align_loss(&lifted, &target, w.align)?;
            let g = align_loss_backward(&lifted, &target, w.align, <T as Real>::lit(1.0))?;
            let grads = setup.lifter.backward(&tape, g.view())?;
            let la = Real::to_f64_exact(la);
            ([la, 0.0, 0.0, la], grads.input, grads.params, Vec::new())
        } else {
            let out = stage3_loss(
                setup.lifter,
                setup.decoder,
                setup.encoder,
                &r,
                &target,
                sample.style,
                w,
                setup.normalize,
            )?;
            (
                [
                    Real::to_f64_exact(out.loss_align),
                    Real::to_f64_exact(out.loss_content),
                    Real::to_f64_exact(out.loss_style),
                    Real::to_f64_exact(out.loss),
                ],
                out.grad_raster_features,
                out.grad_lifter,
                out.grad_decoder,
            )
        };
    // The window's cotangent, HWC.
    let mut v_image = vec![<T as Real>::lit(0.0); win.height * win.width * f];
    for ((_, ch, y, x), &g) in grad_r.indexed_iter() {
        v_image[(y * win.width + x) * f + ch] = g;
    }
    // The geometry is frozen: only the features' gradient is formed.
    let features = render_backward_features(&cam, scene, &opts, &fwd, &v_image)?;
    Ok(Stage3Gradients {
        loss_align: terms[0],
        loss_content: terms[1],
        loss_style: terms[2],
        loss: terms[3],
        features,
        lifter: grad_lifter,
        decoder: grad_decoder,
    })
}

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

/// How [`FeatureTrainer::new_with`] reports its setup and where it keeps the encodings it can
/// reuse.
#[derive(Clone, Copy)]
pub struct FeatureSetup<'a> {
    /// Where the setup's [`Stage::Prepare`] progress and its summary line go.
    pub sink: &'a dyn Sink,
    /// The folder of cached encodings to read and fill (see "Encoding cache" in the module
    /// documentation; a run's is `OUT/`[`ENCODINGS_DIR`]); `None` encodes everything and
    /// writes nothing.
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

/// The start of every cache file.
const ENCODING_MAGIC: &[u8; 8] = b"DSGSENC2";

/// The encoding cache of one setup: the folder, the part of every key that does not depend on
/// the image, and the files used so far.
struct EncodingCache<'a> {
    dir: &'a Path,
    prefix: String,
    used: Vec<String>,
    reused: usize,
    rebuilt: usize,
    write_error: Option<String>,
    /// The thread writing the files, started at the first write.
    writer: Option<CacheWriter>,
}

/// Values a cache file is written from: a view's target, shared with the training data, or
/// values of the file's own.
enum CacheValues {
    Shared(Arc<Array4<f32>>),
    Own(Vec<f32>),
}

impl CacheValues {
    fn as_slice(&self) -> &[f32] {
        match self {
            CacheValues::Shared(a) => a.as_slice().expect("targets are in standard layout"),
            CacheValues::Own(v) => v,
        }
    }
}

/// A cache file to write: its path, its key and its values (the concatenation of the parts).
struct CacheFile {
    path: PathBuf,
    key: String,
    parts: Vec<CacheValues>,
}

/// A thread that writes cache files in the order they are sent, so that encoding never waits
/// for the disk. It stops at the first failure and returns it.
struct CacheWriter {
    files: mpsc::Sender<CacheFile>,
    thread: std::thread::JoinHandle<Option<String>>,
}

impl CacheWriter {
    fn start() -> std::io::Result<CacheWriter> {
        let (files, queue) = mpsc::channel::<CacheFile>();
        let thread = std::thread::Builder::new()
            .name("encoding-cache".into())
            .spawn(move || {
                for file in queue {
                    let parts: Vec<&[f32]> = file.parts.iter().map(CacheValues::as_slice).collect();
                    let written = base::write_atomic_unsynced_with(&file.path, |f| {
                        write_entry(f, &file.key, &parts)
                    });
                    if let Err(e) = written {
                        return Some(format!("{}: {e}", file.path.display()));
                    }
                }
                None
            })?;
        Ok(CacheWriter { files, thread })
    }

    /// Waits for every file sent to be written; the first failure, if any.
    fn finish(self) -> Option<String> {
        drop(self.files);
        self.thread
            .join()
            .unwrap_or_else(|_| Some("the cache writer stopped unexpectedly".into()))
    }
}

/// What the cached values were computed by: the program's version and its executable's size
/// and modification time (`None` when they cannot be read: nothing is cached then).
fn program_identity() -> Option<String> {
    let exe = std::env::current_exe().ok()?;
    let meta = std::fs::metadata(exe).ok()?;
    let modified = meta.modified().ok()?.duration_since(UNIX_EPOCH).ok()?;
    Some(format!(
        "{} {} {}",
        env!("CARGO_PKG_VERSION"),
        meta.len(),
        modified.as_nanos()
    ))
}

impl<'a> EncodingCache<'a> {
    fn new(
        dir: &'a Path,
        encoder: &Encoder<f32>,
        variant: Variant,
        normalize: FeatureNorm,
    ) -> Option<Self> {
        let program = program_identity()?;
        Some(EncodingCache {
            dir,
            prefix: format!(
                "{program}\n{}\n{}\n{}",
                weights_fingerprint(encoder),
                variant.as_str(),
                normalize.as_str()
            ),
            used: Vec::new(),
            reused: 0,
            rebuilt: 0,
            write_error: None,
            writer: None,
        })
    }

    /// The file name of the encoding of a `width x height` RGB image as a `kind` (`view` or
    /// `style`), and its key.
    fn entry(&self, kind: &str, width: u32, height: u32, rgb: &[f32]) -> (String, String) {
        let mut h = Fnv1a::new();
        h.eat(ENCODING_MAGIC);
        h.eat(self.prefix.as_bytes());
        h.eat(kind.as_bytes());
        h.eat(&width.to_le_bytes());
        h.eat(&height.to_le_bytes());
        for &v in rgb {
            h.eat_f32(v);
        }
        let key = h.hex();
        (format!("{kind}-{key}.bin"), key)
    }

    /// The `len` values stored under `name` for `key`, if the file is sound (format, key,
    /// length and checksum); a file that is present but unsound counts as rebuilt.
    fn read(&mut self, name: &str, key: &str, len: usize) -> Option<Vec<f32>> {
        self.used.push(name.to_string());
        let bytes = std::fs::read(self.dir.join(name)).ok()?;
        let values = decode_entry(&bytes, key, len);
        match values {
            Some(_) => self.reused += 1,
            None => self.rebuilt += 1,
        }
        values
    }

    /// Stores the concatenation of `parts` under `name` for `key`, on the writer thread; a
    /// failure ends the writing, not the run, and [`EncodingCache::finish`] reports it.
    fn write(&mut self, name: &str, key: &str, parts: Vec<CacheValues>) {
        if self.write_error.is_some() {
            return;
        }
        if self.writer.is_none() {
            match CacheWriter::start() {
                Ok(w) => self.writer = Some(w),
                Err(e) => {
                    self.write_error = Some(format!("could not start the cache writer: {e}"));
                    return;
                }
            }
        }
        let file = CacheFile {
            path: self.dir.join(name),
            key: key.to_string(),
            parts,
        };
        // A send fails only once the writer has stopped at a failure, which `finish` reports.
        let _ = self.writer.as_ref().expect("started").files.send(file);
    }

    /// Waits for every file to be written, and keeps the first failure in `write_error`.
    fn finish(&mut self) {
        if let Some(e) = self.writer.take().and_then(CacheWriter::finish) {
            self.write_error.get_or_insert(e);
        }
    }

    /// Removes the cache files of this folder that the run did not use (best effort).
    fn prune(&self) {
        let Ok(entries) = std::fs::read_dir(self.dir) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let ours =
                (name.starts_with("view-") || name.starts_with("style-")) && name.ends_with(".bin");
            if ours && !self.used.contains(&name) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// A setup that stops early (an error) still waits for the files already sent.
impl Drop for EncodingCache<'_> {
    fn drop(&mut self) {
        self.finish();
    }
}

/// A cache file: the magic, the key (16 hexadecimal digits), the number of values (`u64`), the
/// values (`f32`), all little-endian, then the CRC-32 (IEEE) checksum of everything before it
/// (8 hexadecimal digits). A checksum that runs at memory speed, not a hash: the key already
/// names the contents, the checksum only tells a damaged file.
///
/// The values are the concatenation of `parts`, written to `out` in pieces, so that no second
/// copy of them is formed.
fn write_entry(out: &mut impl std::io::Write, key: &str, parts: &[&[f32]]) -> std::io::Result<()> {
    /// Values converted and written per piece (256 KiB).
    const PIECE: usize = 1 << 16;
    let mut crc = crc32fast::Hasher::new();
    let mut put = |out: &mut dyn std::io::Write, bytes: &[u8]| {
        crc.update(bytes);
        out.write_all(bytes)
    };
    let len: usize = parts.iter().map(|p| p.len()).sum();
    put(out, ENCODING_MAGIC)?;
    put(out, key.as_bytes())?;
    put(out, &(len as u64).to_le_bytes())?;
    // The conversion buffer of big-endian machines (little-endian ones write the values' bytes).
    let mut bytes = Vec::new();
    for piece in parts.iter().flat_map(|p| p.chunks(PIECE)) {
        if cfg!(target_endian = "little") {
            // The values' own bytes are already little-endian.
            put(out, bytemuck::cast_slice(piece))?;
        } else {
            bytes.clear();
            bytes.extend(piece.iter().flat_map(|v| v.to_le_bytes()));
            put(out, &bytes)?;
        }
    }
    out.write_all(format!("{:08x}", crc.finalize()).as_bytes())
}

/// The values of a cache file written by [`write_entry`] for `key` with `len` values, or
/// `None` if anything does not match.
fn decode_entry(bytes: &[u8], key: &str, len: usize) -> Option<Vec<f32>> {
    let head = ENCODING_MAGIC.len() + key.len() + 8;
    if bytes.len() != head + 4 * len + 8 {
        return None;
    }
    let (body, checksum) = bytes.split_at(bytes.len() - 8);
    if checksum != format!("{:08x}", crc32fast::hash(body)).as_bytes()
        || &body[..8] != ENCODING_MAGIC
        || &body[8..8 + key.len()] != key.as_bytes()
        || body[8 + key.len()..head] != (len as u64).to_le_bytes()
    {
        return None;
    }
    Some(if cfg!(target_endian = "little") {
        // Little-endian bytes are the values' own (copied, as `bytes` may be unaligned).
        bytemuck::pod_collect_to_vec(&body[head..])
    } else {
        body[head..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    })
}

/// The flat values of per-level statistics: each level's means, then its standard deviations.
fn stats_values(stats: &StyleFeatureStats<f32>) -> Vec<f32> {
    stats
        .levels
        .iter()
        .flat_map(|l| l.mean.iter().chain(l.std.iter()).copied())
        .collect()
}

/// Statistics of one image at levels of the given widths from [`stats_values`].
fn stats_from_values(
    values: &[f32],
    widths: &[usize],
) -> Result<StyleFeatureStats<f32>, TrainError> {
    let mut levels = Vec::with_capacity(widths.len());
    let mut at = 0;
    for &c in widths {
        let row = |from: usize| {
            ndarray::Array2::from_shape_vec((1, c), values[from..from + c].to_vec()).map_err(
                |error| TrainError::Array {
                    what: "cannot rebuild cached style statistics".into(),
                    error,
                },
            )
        };
        levels.push(ChannelStats::new(row(at)?, row(at + c)?)?);
        at += 2 * c;
    }
    Ok(StyleFeatureStats { levels })
}

/// One encoded training view: its alignment target (normalised or not, [`FeatureNorm`]) and the
/// per-channel mean and std of its unnormalised deepest features.
struct ViewEncoding {
    target: Array4<f32>,
    mean: Vec<f32>,
    std: Vec<f32>,
}

/// Encodes one training view (see the module documentation).
fn encode_view(
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
struct CachedView {
    camera: Camera,
    /// Shared with the encoding cache's writer while it writes the file.
    target: Arc<Array4<f32>>,
}

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

/// Mean loss terms over (view, style) pairs on whole feature maps.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureEvaluation {
    /// Completed iterations when evaluated.
    pub step: u64,
    /// Number of (view, style) pairs averaged.
    pub pairs: usize,
    /// Mean alignment term.
    pub loss_align: f64,
    /// Mean content term (0 when the next iteration has no content and style terms: the
    /// alignment warm-up or the alignment-only ablation).
    pub loss_content: f64,
    /// Mean unweighted style term (0 likewise).
    pub loss_style: f64,
    /// Mean total, with the loss weights of the next iteration.
    pub loss: f64,
}

impl FeatureEvaluation {
    /// The evaluation as event metrics.
    pub fn metrics(&self) -> Vec<Metric> {
        [
            ("loss", self.loss),
            ("align", self.loss_align),
            ("content", self.loss_content),
            ("style", self.loss_style),
            ("pairs", self.pairs as f64),
        ]
        .map(|(name, value)| Metric { name, value })
        .to_vec()
    }
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

/// A fixed evaluation sample: a view's camera and feature-map size, the centred window and the
/// view's alignment target on it, and a style's statistics.
#[derive(Clone, Debug)]
struct EvalSample {
    camera: Camera,
    feature_size: (u32, u32),
    window: CropWindow,
    target: Array4<f32>,
    style: StyleFeatureStats<f32>,
}

/// The centred window of at most `crop x crop` pixels of a `w x h` map.
fn centred_window(w: usize, h: usize, crop: usize) -> CropWindow {
    let (cw, ch) = (w.min(crop), h.min(crop));
    CropWindow {
        x: (w - cw) / 2,
        y: (h - ch) / 2,
        width: cw,
        height: ch,
    }
}

impl EvalSample {
    /// The sample of a view whose whole alignment target is `target` (`[1, C, h, w]`).
    fn new(
        camera: Camera,
        target: &Array4<f32>,
        style: StyleFeatureStats<f32>,
        crop: usize,
    ) -> EvalSample {
        let (_, _, h, w) = target.dim();
        let window = centred_window(w, h, crop);
        let target = target
            .slice(s![
                ..,
                ..,
                window.y..window.y + window.height,
                window.x..window.x + window.width
            ])
            .to_owned();
        EvalSample {
            camera,
            feature_size: (w as u32, h as u32),
            window,
            target,
            style,
        }
    }
}

/// The (view, style) index pairs of the evaluation: `pairs` draws from the seed's evaluation
/// stream, a view then a style each.
fn eval_indices(seed: u64, pairs: usize, views: usize, styles: usize) -> Vec<(usize, usize)> {
    let mut rng = StdRng::seed_from_u64(mix(seed, EVAL_STREAM, 0));
    (0..pairs)
        .map(|_| (rng.random_range(0..views), rng.random_range(0..styles)))
        .collect()
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

/// Checks that the encoder takes RGB and the decoder its deepest width; returns that width.
fn check_networks(encoder: &Encoder<f32>, decoder: &Decoder<f32>) -> Result<usize, TrainError> {
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
        let deepest = check_networks(&encoder, &decoder)?;
        if geometry.is_empty() {
            return Err(TrainError::Dataset("the geometry has no Gaussians".into()));
        }
        if views.is_empty() {
            return Err(TrainError::Dataset("no training views".into()));
        }
        for v in &views {
            v.check()?;
        }
        let res = config.variant.resolution();
        let encoder = encoder.with_resolution(res);
        let decoder = decoder.with_resolution(res);

        let n = geometry.len();
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
            DecoderMode::Scratch => init_decoder_with(&encoder, &mut rng)?.with_resolution(res),
            DecoderMode::Mlp => init_mlp_decoder(deepest, &mut rng)?.with_resolution(res),
        };
        let geometry_fingerprint = geometry_fingerprint(&scene);

        let cameras = if cameras.is_empty() {
            views
                .iter()
                .map(|v| CameraRecord::new(v.name.clone(), &v.camera, false))
                .collect()
        } else {
            cameras
        };

        let start = Instant::now();
        let mut tally = Tally::start(Stage::Prepare, 2 * styles.len() + views.len(), setup.sink);
        // Every style image is decoded before anything is encoded: a bad file stops the run now.
        let mut decoded = 0;
        let style_images = styles.load_all_resized(config.style_size, &mut |done| {
            tally.advance(done - decoded, "decode styles");
            decoded = done;
        })?;
        let mut cache = setup
            .cache
            .and_then(|dir| EncodingCache::new(dir, &encoder, config.variant, config.normalize));

        let mut mean_sum = vec![0.0f64; deepest];
        let mut std_sum = vec![0.0f64; deepest];
        let mut cached = Vec::with_capacity(views.len());
        for v in &views {
            let k = v.camera.intrinsics;
            let (fw, fh) = feature_size(&encoder, config.variant, k.width, k.height);
            let shape = (1, deepest, fh as usize, fw as usize);
            let len = deepest * (fh as usize * fw as usize + 2);
            let entry = cache
                .as_ref()
                .map(|c| c.entry("view", k.width, k.height, &v.image));
            let stored = match (&mut cache, &entry) {
                (Some(c), Some((name, key))) => c.read(name, key, len),
                _ => None,
            };
            let (target, mean, std) = match stored {
                Some(mut values) => {
                    let std = values.split_off(len - deepest);
                    let mean = values.split_off(len - 2 * deepest);
                    let target = Array4::from_shape_vec(shape, values).map_err(|error| {
                        TrainError::Array {
                            what: format!(
                                "cannot rebuild the cached encoding of view `{}`",
                                v.name
                            ),
                            error,
                        }
                    })?;
                    (Arc::new(target), mean, std)
                }
                None => {
                    let e = encode_view(&encoder, config.variant, config.normalize, v, deepest)?;
                    let target = Arc::new(e.target);
                    if let (Some(c), Some((name, key))) = (&mut cache, &entry) {
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

        let widths = encoder.widths().to_vec();
        let stats_len = 2 * widths.iter().sum::<usize>();
        let mut style_stats = Vec::with_capacity(style_images.len());
        for img in &style_images {
            let entry = cache
                .as_ref()
                .map(|c| c.entry("style", img.width, img.height, &img.data));
            let stored = match (&mut cache, &entry) {
                (Some(c), Some((name, key))) => c.read(name, key, stats_len),
                _ => None,
            };
            let stats = match stored {
                Some(values) => stats_from_values(&values, &widths)?,
                None => {
                    let stats = encode_style(&encoder, &to_tensor(img))?;
                    if let (Some(c), Some((name, key))) = (&mut cache, &entry) {
                        c.write(name, key, vec![CacheValues::Own(stats_values(&stats))]);
                    }
                    stats
                }
            };
            style_stats.push(stats);
            tally.advance(1, "encode styles");
        }
        drop(style_images);
        let crop = config.crop_side() as usize;
        let eval = eval_indices(
            config.seed,
            config.eval_pairs,
            cached.len(),
            style_stats.len(),
        )
        .into_iter()
        .map(|(v, st)| {
            let view = &cached[v];
            EvalSample::new(view.camera, &view.target, style_stats[st].clone(), crop)
        })
        .collect();
        if let Some(c) = &mut cache {
            c.finish();
        }
        let mut summary = format!(
            "{} views and {} style images encoded in {:.1} s",
            cached.len(),
            style_stats.len(),
            start.elapsed().as_secs_f64()
        );
        if let Some(c) = &cache {
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
                setup
                    .sink
                    .emit(Event::Warning(format!("encodings not cached: {e}")));
            }
        }
        tally.finish();
        setup.sink.emit(Event::Log {
            stage: Stage::Prepare,
            message: summary,
        });

        let mut adam = Adam::new(config.adam);
        adam.add_param("features", config.lr_features, n, f);
        adam.add_param("lifter.weight", config.lr_lifter, deepest, f);
        adam.add_param("lifter.bias", config.lr_lifter, 1, deepest);
        if config.decoder_mode.trains_decoder() {
            register_decoder(&mut adam, &decoder, config.lr_decoder);
        }
        Ok(FeatureTrainer {
            config,
            provenance,
            scene,
            lifter,
            encoder,
            decoder,
            views: cached,
            styles: style_stats,
            adam,
            step: 0,
            ema: None,
            scene_mean,
            scene_std,
            cameras,
            background,
            geometry_fingerprint,
            eval,
            evaluations: Vec::new(),
        })
    }

    /// Draws the evaluation samples from held-out views and styles instead of the training
    /// ones (see "Evaluation" in the module documentation): `eval_pairs` (view, style) pairs
    /// from the seed, only the views drawn are encoded, reported to `sink` as
    /// [`Stage::Prepare`] progress. Views must have the training views' kind (RGB images at
    /// the resolution to train at); their feature maps follow [`feature_size`].
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
            let sample = Stage3Sample {
                camera: &e.camera,
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
        let sample = Stage3Sample {
            camera: &v.camera,
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
