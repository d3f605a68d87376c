//! Feature-space operations of style transfer and the losses of every training stage, each with
//! an exact backward pass.
//!
//! * [`stats`]: per-channel mean and std (unbiased variance, eps 1e-5), optionally over a mask.
//! * [`adain`](mod@adain): instance normalisation, the 3D transform `T(x) = std_s x + mean_s`,
//!   AdaIN with a content-style trade-off and style interpolation.
//! * [`spatial`]: different styles in different regions.
//! * [`colour`]: colour preservation (the style image's colours matched to the content's).
//! * [`loss`]: content, style and alignment losses.
//! * [`cache`]: per-style statistics computed once and reused across views.
//! * [`objective`]: the decoder training loss and the 3D stylization loss through the networks,
//!   each one function with its gradients.
//! * [`fold`]: a style's transform folded into the decoder's first convolution.
//! * [`stylize`](mod@stylize): feed-forward stylization of images.
//! * [`texture`]: a texture distance through Gram matrices, which sees the correlations between
//!   channels that the channel statistics of the style loss do not.
//!
//! Everything is generic over the workspace's numeric trait [`base::Real`] (`f32` in production,
//! `f64` in gradient checks against central differences and the float64 oracle; the very same type
//! runs through the encoder, decoder and lifter of `nets`) and works on `ndarray::Array4` feature
//! maps in NCHW layout. Reductions (means, variances, loss sums) always accumulate in `f64`,
//! sequentially in a fixed order, so `f32` results are correctly rounded sums and identical for any
//! number of threads.
//!
//! # Example
//!
//! AdaIN gives a content feature map the per-channel statistics of a style feature map; the
//! style loss measures how far a feature map's statistics are from a style's, and its backward
//! pass is the exact gradient (checked here against a central difference).
//!
//! ```
//! use ndarray::Array4;
//! use style::{adain, channel_stats, style_loss, style_loss_backward};
//!
//! // Two feature maps in NCHW layout (1 sample, 3 channels), of different spatial sizes.
//! let content = Array4::from_shape_fn((1, 3, 6, 5), |(_, c, y, x)| {
//!     ((c * 31 + y * 7 + x * 13) as f64 * 0.37).sin()
//! });
//! let style_features = Array4::from_shape_fn((1, 3, 4, 4), |(_, c, y, x)| {
//!     2.0 + c as f64 + (1.0 + c as f64) * ((c * 17 + y * 5 + x * 3) as f64 * 0.91).cos()
//! });
//! let target = channel_stats(&style_features)?;
//!
//! // AdaIN output: the content's layout with the style's mean and std in every channel (up to
//! // the 1e-5 added to the variances).
//! let stylized = adain(&content, &style_features)?;
//! let got = channel_stats(&stylized)?;
//! for (a, b) in got.mean.iter().zip(&target.mean) {
//!     assert!((a - b).abs() < 1e-9);
//! }
//! for (a, b) in got.std.iter().zip(&target.std) {
//!     assert!((a - b).abs() < 1e-4);
//! }
//!
//! // The style loss (summed over encoder levels; one level here) is near zero for the AdaIN
//! // output and clearly positive for the content itself.
//! let levels = [target];
//! assert!(style_loss(&[stylized], &levels)? < 1e-8);
//! let loss = |x: &Array4<f64>| style_loss(std::slice::from_ref(x), &levels);
//! assert!(loss(&content)? > 1.0);
//!
//! // Its gradient w.r.t. the content has the content's shape, is finite, and matches central
//! // differences.
//! let grad = style_loss_backward(std::slice::from_ref(&content), &levels, 1.0)?;
//! assert_eq!(grad[0].shape(), content.shape());
//! assert!(grad[0].iter().all(|g| g.is_finite()));
//! let h = 1e-6;
//! for index in [[0, 0, 0, 0], [0, 1, 3, 2], [0, 2, 5, 4]] {
//!     let (mut plus, mut minus) = (content.clone(), content.clone());
//!     plus[index] += h;
//!     minus[index] -= h;
//!     let numeric = (loss(&plus)? - loss(&minus)?) / (2.0 * h);
//!     assert!((grad[0][index] - numeric).abs() < 1e-6 * (1.0 + numeric.abs()));
//! }
//! # Ok::<(), style::StyleError>(())
//! ```

#![warn(missing_docs)]

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
pub mod texture;

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
    mse_backward, style_loss, style_loss_backward, style_loss_of_stats, AlignLoss,
};
pub use objective::{
    align_target, decoder_training_loss, decoder_training_loss_with_style_network, stage3_loss,
    DecoderLoss, FeatureNorm, Stage3Loss, Stage3Weights,
};
pub use spatial::{adain_spatial, adain_spatial_backward, Region};
pub use stats::{
    channel_stats, channel_stats_backward, masked_channel_stats, masked_channel_stats_backward,
    resize_mask_nearest, ChannelMoments, ChannelStats, STATS_EPS,
};
pub use stylize::{encode_style, stylize, stylize_image};
pub use texture::{gram, gram_distance, gram_distance_of, GramSums};
