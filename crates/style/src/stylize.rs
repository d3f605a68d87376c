//! Feed-forward stylization with the networks: encode a style once, transform a content
//! feature, decode.
//!
//! `stylize(c, s) = g((1 - alpha) phi_k(c) + alpha adain(phi_k(c), s))`, the AdaIN pipeline with
//! a content-style trade-off; [`stylize_image`] can first match the style image's colours to the
//! content ([`crate::colour`]).

use base::Real;
use ndarray::Array4;
use nets::{Decoder, Encoder};

use crate::adain::adain_alpha;
use crate::cache::{StyleCache, StyleFeatureStats, StyleKey};
use crate::colour::preserve_colour;
use crate::error::Result;
use crate::stats::ChannelStats;

/// The per-level statistics of a style image (`[N, 3, H, W]`, RGB in `[0, 1]`) under `encoder`.
pub fn encode_style<T: Real>(
    encoder: &Encoder<T>,
    style_image: &Array4<T>,
) -> Result<StyleFeatureStats<T>> {
    StyleFeatureStats::from_features(&encoder.forward(style_image.view())?)
}

impl<T: Real> StyleCache<T> {
    /// The statistics of `style_image` under `encoder`, encoded on first use. `encoder_tag` must
    /// name the encoder (weights and resolution variant) unambiguously.
    pub fn get_or_encode(
        &self,
        encoder_tag: &str,
        encoder: &Encoder<T>,
        style_image: &Array4<T>,
    ) -> Result<std::sync::Arc<StyleFeatureStats<T>>> {
        let key = StyleKey::from_image(encoder_tag, style_image);
        self.get_or_compute(&key, || encode_style(encoder, style_image))
    }
}

/// Decodes `alpha * adain(phi_k(content), style) + (1 - alpha) * phi_k(content)`.
pub fn stylize<T: Real>(
    encoder: &Encoder<T>,
    decoder: &Decoder<T>,
    content_image: &Array4<T>,
    style: &ChannelStats<T>,
    alpha: f64,
) -> Result<Array4<T>> {
    let feats = encoder.forward(content_image.view())?;
    let t = adain_alpha(feats.last().expect("encoder depth >= 1"), style, alpha)?;
    Ok(decoder.forward(t.view())?)
}

/// Stylizes `content_image` with `style_image`, optionally preserving the content's colours
/// (the style image is colour-matched to the content before it is encoded).
pub fn stylize_image<T: Real>(
    encoder: &Encoder<T>,
    decoder: &Decoder<T>,
    content_image: &Array4<T>,
    style_image: &Array4<T>,
    alpha: f64,
    keep_colour: bool,
) -> Result<Array4<T>> {
    let style_image = if keep_colour {
        preserve_colour(style_image, content_image)?
    } else {
        style_image.clone()
    };
    let stats = encode_style(encoder, &style_image)?;
    stylize(encoder, decoder, content_image, stats.deepest(), alpha)
}
