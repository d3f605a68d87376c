//! Feature-space operations of style transfer and the losses of every training stage, each with
//! an exact backward pass.
//!
//! * [`stats`]: per-channel mean and std (unbiased variance, eps 1e-5), optionally over a mask.
//! * [`adain`]: instance normalisation, the 3D transform `T(x) = std_s x + mean_s`, AdaIN with a
//!   content-style trade-off and style interpolation.
//! * [`spatial`]: different styles in different regions.
//! * [`colour`]: colour preservation (the style image's colours matched to the content's).
//! * [`loss`]: content, style and alignment losses.
//! * [`cache`]: per-style statistics computed once and reused across views.
//! * [`objective`]: the decoder training loss and the 3D stylization loss through the networks,
//!   each one function with its gradients.
//! * [`fold`]: a style's transform folded into the decoder's first convolution.
//! * [`stylize`]: feed-forward stylization of images.
//!
//! Everything is generic over the workspace's numeric trait [`base::Real`] (`f32` in production,
//! `f64` in gradient checks against central differences and the float64 oracle; the very same type
//! runs through the encoder, decoder and lifter of `nets`) and works on `ndarray::Array4` feature
//! maps in NCHW layout. Reductions (means, variances, loss sums) always accumulate in `f64`,
//! sequentially in a fixed order, so `f32` results are correctly rounded sums and identical for any
//! number of threads.

pub mod adain;
pub mod cache;
pub mod colour;
pub mod error;
pub mod fold;
pub mod loss;
pub mod objective;
pub mod spatial;
pub mod stats;
pub mod stylize;

pub use adain::{
    adain, adain_alpha, adain_backward, adain_mix, adain_with_stats, blend, instance_normalize,
    instance_normalize_backward, mix_stats, normalize, style_transform, style_transform_backward,
};
pub use cache::{StyleCache, StyleFeatureStats, StyleKey};
pub use colour::{preserve_colour, preserve_colour_with_eps, COLOUR_EPS};
pub use error::{Result, StyleError};
pub use fold::fold_style_transform;
pub use loss::{
    align_loss, align_loss_backward, content_loss, content_loss_backward, l1, l1_backward, mse,
    mse_backward, style_loss, style_loss_backward, AlignLoss,
};
pub use objective::{
    align_target, decoder_training_loss, stage3_loss, DecoderLoss, Stage3Loss, Stage3Weights,
};
pub use spatial::{adain_spatial, adain_spatial_backward, Region};
pub use stats::{
    channel_stats, channel_stats_backward, masked_channel_stats, masked_channel_stats_backward,
    resize_mask_nearest, ChannelStats, STATS_EPS,
};
pub use stylize::{encode_style, stylize, stylize_image};
