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
//!
//! [`conv_default_init`]: crate::decoder_training::conv_default_init
//! [`feature_size`]: runtime::bundle::feature_size
//! [`Stage::Prepare`]: base::event::Stage::Prepare
//! [`DecoderMode::Scratch`]: runtime::bundle::DecoderMode::Scratch
//! [`DecoderMode::Mlp`]: runtime::bundle::DecoderMode::Mlp
//! [`FeatureNorm::AfterRaster`]: style::FeatureNorm::AfterRaster
//! [`Event::Evaluation`]: base::event::Event::Evaluation

mod cache;
mod config;
mod evaluation;
mod objective;
mod setup;
mod trainer;

pub use config::FeatureTrainConfig;
pub use evaluation::FeatureEvaluation;
pub use objective::{stage3_gradients, CropWindow, Stage3Gradients, Stage3Sample, Stage3Setup};
pub use setup::{dataset_views, FeatureInputs, FeatureSetup};
pub use trainer::{geometry_fingerprint, FeatureStepReport, FeatureTrainSummary, FeatureTrainer};

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
