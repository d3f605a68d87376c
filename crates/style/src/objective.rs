//! The training objectives that run through the networks, each one function that returns every
//! loss term and the gradients a training step needs.
//!
//! * Decoder training (AdaIN): with `t` the decoder input (an AdaIN output), `g` the decoder, `phi`
//!   the frozen encoder (features `relu1_1 .. relu_k_1`) and `S` the style's per-level statistics,
//!
//!   ```text
//!   L = content(phi_k(g(t)), target) + w_s * style(phi(g(t)), S)
//!   ```
//!
//!   where `target` is a constant (usually `t` itself, as in the AdaIN paper). Gradients: the
//!   decoder input and every decoder parameter. A variant measures the style term with a
//!   separate style network `psi` instead of `phi` ([`decoder_training_loss_with_style_network`]).
//!
//! * The 3D stylization loss on a rasterized feature map `r` with the lifter `l = relu(W r + b)`,
//!   the style transform `T(x) = std_s x + mean_s` and a frozen decoder and encoder:
//!
//!   ```text
//!   t = T(l(r)),   image = g(t)
//!   L = L_align(l(r), target) + lambda_c content(phi_k(image), t) + lambda_s style(phi(image), S)
//!   ```
//!
//!   `target` is the normalised `relu_k_1` of the content view (see [`align_target`]). The content
//!   term compares with `t`, which depends on `r`, so its gradient flows through both arguments.
//!   Gradients: `r`, the lifter's weight and bias, and, when [`Stage3Weights::train_decoder`]
//!   asks for them, the decoder's parameters (the decoder is trained in this stage in the
//!   paper's decoder ablation).
//!
//!   The design ablation [`FeatureNorm::AfterRaster`] aligns `l(r)` with the *unnormalised*
//!   `relu_k_1` instead and normalises each lifted map over its own pixels before the
//!   transform: `t = T(IN(l(r)))`, `IN` the instance normalisation of [`instance_normalize`].
//!
//! Sums of loss terms are formed in `f64` and rounded once.

use base::Real;
use ndarray::{Array4, ArrayView4};
use nets::{ConvGrad, Decoder, Encoder, Lifter};

use crate::adain::{
    instance_normalize, instance_normalize_backward, normalize, style_transform,
    style_transform_backward,
};
use crate::cache::StyleFeatureStats;
use crate::error::{Result, StyleError};
use crate::loss::{
    align_loss, align_loss_backward, content_loss, mse_backward, style_loss, style_loss_backward,
    AlignLoss,
};
use crate::stats::ChannelStats;

/// The result of [`decoder_training_loss`].
#[derive(Clone, Debug)]
pub struct DecoderLoss<T: Real> {
    /// The decoded image `g(t)`.
    pub image: Array4<T>,
    /// The content term `content(phi_k(g(t)), target)`: MSE on the deepest encoder level.
    pub loss_content: T,
    /// The unweighted style term `style(phi(g(t)), S)`: summed over levels, MSE of per-channel
    /// means plus MSE of per-channel standard deviations.
    pub loss_style: T,
    /// `loss_content + w_s * loss_style`.
    pub loss: T,
    /// `dL/dt`.
    pub grad_input: Array4<T>,
    /// `dL/d(weight, bias)` of every decoder conv in [`Decoder::layers`] order; each
    /// [`ConvGrad::source`] is the layer's key prefix in its weights (e.g. `1` for `decoder.1`).
    pub grad_params: Vec<ConvGrad<T>>,
}

fn check_levels<T: Real>(encoder: &Encoder<T>, style: &StyleFeatureStats<T>) -> Result<()> {
    if encoder.depth() != style.levels.len() {
        return Err(StyleError::Invalid {
            what: "style statistics",
            problem: format!(
                "{} levels for an encoder to relu{}_1 (encode the style with the same encoder)",
                style.levels.len(),
                encoder.depth()
            ),
        });
    }
    Ok(())
}

/// Encodes `image`, evaluates `lambda_c * content(phi_k, content_target) + lambda_s * style(phi, S)`
/// and returns `(features, content, style, dL/dimage, dL/dcontent_target)`.
fn perceptual<T: Real>(
    encoder: &Encoder<T>,
    image: &Array4<T>,
    content_target: &Array4<T>,
    style: &StyleFeatureStats<T>,
    lambda_c: f64,
    lambda_s: f64,
) -> Result<(T, T, Array4<T>, Array4<T>)> {
    check_levels(encoder, style)?;
    let (feats, tape) = encoder.forward_with_tape(image.view())?;
    let deepest = feats.last().expect("encoder depth >= 1");
    let loss_c = content_loss(deepest, content_target)?;
    let loss_s = style_loss(&feats, &style.levels)?;
    let mut cot = style_loss_backward(&feats, &style.levels, T::lit(lambda_s))?;
    let g_c = mse_backward(deepest, content_target, T::lit(lambda_c))?;
    let last = cot.last_mut().expect("one level per feature");
    last.zip_mut_with(&g_c, |a, &b| *a += b);
    let views: Vec<Option<ArrayView4<T>>> = cot.iter().map(|c| Some(c.view())).collect();
    let g_image = encoder.backward(&tape, &views)?;
    Ok((loss_c, loss_s, g_image, g_c.mapv(|v| -v)))
}

/// The decoder training loss `content(phi_k(g(t)), target) + w_s * style(phi(g(t)), S)` and its
/// gradients with respect to the decoder input `t` and the decoder parameters (see the module
/// documentation). The encoder must be the one the style statistics were computed with.
pub fn decoder_training_loss<T: Real>(
    encoder: &Encoder<T>,
    decoder: &Decoder<T>,
    input: &Array4<T>,
    content_target: &Array4<T>,
    style: &StyleFeatureStats<T>,
    style_weight: f64,
) -> Result<DecoderLoss<T>> {
    crate::adain::check_finite("style weight", style_weight)?;
    let (image, dtape) = decoder.forward_with_param_tape(input.view())?;
    let (loss_c, loss_s, g_image, _) =
        perceptual(encoder, &image, content_target, style, 1.0, style_weight)?;
    decoder_loss(
        decoder,
        &dtape,
        image,
        (loss_c, loss_s),
        &g_image,
        style_weight,
    )
}

/// [`decoder_training_loss`] with a separate *style network* `psi`:
/// `content(phi_k(g(t)), target) + w_s * style(psi(g(t)), S_psi)`. The content term stays on the
/// decoder's own encoder `phi` (whose deepest level the decoder inverts); the style term is
/// measured at every level of `psi`, and `style` must hold `psi`'s statistics of the style
/// images. This is the loss for an encoder too narrow to judge texture well on its own (the
/// 16x-compressed relu4_1 encoder, 16 to 128 channels), with the real VGG-19 layers as `psi`.
/// The image gradient is the sum of the two encoders' backward passes.
pub fn decoder_training_loss_with_style_network<T: Real>(
    encoder: &Encoder<T>,
    style_network: &Encoder<T>,
    decoder: &Decoder<T>,
    input: &Array4<T>,
    content_target: &Array4<T>,
    style: &StyleFeatureStats<T>,
    style_weight: f64,
) -> Result<DecoderLoss<T>> {
    crate::adain::check_finite("style weight", style_weight)?;
    check_levels(style_network, style)?;
    let (image, dtape) = decoder.forward_with_param_tape(input.view())?;
    // Content: the decoder's encoder, seeded at its deepest level only.
    let (feats, tape) = encoder.forward_with_tape(image.view())?;
    let deepest = feats.last().expect("encoder depth >= 1");
    let loss_c = content_loss(deepest, content_target)?;
    let g_c = mse_backward(deepest, content_target, T::one())?;
    let mut views: Vec<Option<ArrayView4<T>>> = vec![None; feats.len()];
    *views.last_mut().expect("encoder depth >= 1") = Some(g_c.view());
    let mut g_image = encoder.backward(&tape, &views)?;
    // Style: every level of the style network.
    let (sfeats, stape) = style_network.forward_with_tape(image.view())?;
    let loss_s = style_loss(&sfeats, &style.levels)?;
    let cot = style_loss_backward(&sfeats, &style.levels, T::lit(style_weight))?;
    let views: Vec<Option<ArrayView4<T>>> = cot.iter().map(|c| Some(c.view())).collect();
    let g_s = style_network.backward(&stape, &views)?;
    g_image.zip_mut_with(&g_s, |a, &b| *a += b);
    decoder_loss(
        decoder,
        &dtape,
        image,
        (loss_c, loss_s),
        &g_image,
        style_weight,
    )
}

/// The decoder training loss of `image` from its two terms, `content + w_s * style` (summed in
/// `f64`), with the decoder's input and parameter gradients from the image gradient `g_image`.
fn decoder_loss<T: Real>(
    decoder: &Decoder<T>,
    tape: &nets::DecoderTape<T>,
    image: Array4<T>,
    (loss_c, loss_s): (T, T),
    g_image: &Array4<T>,
    style_weight: f64,
) -> Result<DecoderLoss<T>> {
    let grads = decoder.backward_with_params(tape, g_image.view())?;
    let loss = T::lit(loss_c.to_f64_exact() + style_weight * loss_s.to_f64_exact());
    Ok(DecoderLoss {
        image,
        loss_content: loss_c,
        loss_style: loss_s,
        loss,
        grad_input: grads.input,
        grad_params: grads.params,
    })
}

/// Weights and options of the 3D stylization loss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stage3Weights {
    /// `lambda_c` (default 1).
    pub lambda_content: f64,
    /// `lambda_s` (default 1).
    pub lambda_style: f64,
    /// The alignment penalty (default MSE).
    pub align: AlignLoss,
    /// Whether to compute the decoder's parameter gradients ([`Stage3Loss::grad_decoder`]), for
    /// the ablations that train the decoder in stage 3 (default `false`: the paper's frozen
    /// decoder, whose backward pass then costs the input gradient alone).
    pub train_decoder: bool,
}

impl Default for Stage3Weights {
    fn default() -> Self {
        Stage3Weights {
            lambda_content: 1.0,
            lambda_style: 1.0,
            align: AlignLoss::Mse,
            train_decoder: false,
        }
    }
}

/// Where the features are normalised: the paper's consistency design and its ablation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FeatureNorm {
    /// The paper's design: each view's `relu_k_1` is instance-normalised before it becomes the
    /// alignment target, so the Gaussians carry normalised features and every view's lifted
    /// map goes through the same transform `T(l) = std_s l + mean_s`.
    #[default]
    BeforeRaster,
    /// The ablation: the Gaussians are aligned with the unnormalised `relu_k_1`, and each
    /// rendered view's lifted map is instance-normalised over its own pixels before the
    /// transform, `T(IN(l))` (AdaIN after rasterization: the statistics depend on the view).
    AfterRaster,
}

impl FeatureNorm {
    /// `"before-raster"` or `"after-raster"`.
    pub fn as_str(self) -> &'static str {
        match self {
            FeatureNorm::BeforeRaster => "before-raster",
            FeatureNorm::AfterRaster => "after-raster",
        }
    }

    /// The alignment target for an encoder's deepest features: normalised for
    /// [`FeatureNorm::BeforeRaster`], as they are for [`FeatureNorm::AfterRaster`].
    pub fn align_target<T: Real>(self, deepest: &Array4<T>) -> Result<Array4<T>> {
        match self {
            FeatureNorm::BeforeRaster => instance_normalize(deepest),
            FeatureNorm::AfterRaster => Ok(deepest.clone()),
        }
    }

    /// [`FeatureNorm::align_target`] of `deepest` when its channel statistics are already
    /// known (`stats`, from [`crate::channel_stats`] of `deepest`): the same values, without
    /// computing the statistics again or copying `deepest`.
    pub fn align_target_with_stats<T: Real>(
        self,
        deepest: Array4<T>,
        stats: &ChannelStats<T>,
    ) -> Result<Array4<T>> {
        match self {
            FeatureNorm::BeforeRaster => normalize(&deepest, stats),
            FeatureNorm::AfterRaster => Ok(deepest),
        }
    }
}

impl std::str::FromStr for FeatureNorm {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "before-raster" => Ok(FeatureNorm::BeforeRaster),
            "after-raster" => Ok(FeatureNorm::AfterRaster),
            other => Err(format!(
                "unknown normalization `{other}` (expected `before-raster` or `after-raster`)"
            )),
        }
    }
}

/// The result of [`stage3_loss`].
#[derive(Clone, Debug)]
pub struct Stage3Loss<T: Real> {
    /// `relu(W r + b)`.
    pub lifted: Array4<T>,
    /// `T(lifted) = std_s * lifted + mean_s`.
    pub stylized_features: Array4<T>,
    /// The decoded image.
    pub image: Array4<T>,
    /// The alignment term `L_align(lifted, target)` (MSE or L1, see [`AlignLoss`]).
    pub loss_align: T,
    /// The unweighted content term `content(phi_k(image), stylized_features)`: MSE on the
    /// deepest encoder level.
    pub loss_content: T,
    /// The unweighted style term `style(phi(image), S)`: summed over levels, MSE of per-channel
    /// means plus MSE of per-channel standard deviations.
    pub loss_style: T,
    /// `loss_align + lambda_c loss_content + lambda_s loss_style`.
    pub loss: T,
    /// `dL/dr`, the gradient with respect to the rasterized feature map.
    pub grad_raster_features: Array4<T>,
    /// `dL/d(W, b)` of the lifter.
    pub grad_lifter: ConvGrad<T>,
    /// `dL/d(weight, bias)` of every decoder conv in [`Decoder::layers`] order when
    /// [`Stage3Weights::train_decoder`] is set, empty otherwise.
    pub grad_decoder: Vec<ConvGrad<T>>,
}

/// The alignment target: the content view's `relu_k_1` feature, instance-normalised.
pub fn align_target<T: Real>(encoder: &Encoder<T>, content_image: &Array4<T>) -> Result<Array4<T>> {
    let feats = encoder.forward(content_image.view())?;
    instance_normalize(feats.last().expect("encoder depth >= 1"))
}

/// The 3D stylization loss and its gradients (see the module documentation). `raster_features`
/// is `[N, F, H, W]`; `align_target` is `[N, C, H, W]` with `C` the lifter's output width, which
/// must equal the decoder's input width and the encoder's deepest width (fullres networks keep
/// `H x W` throughout). `norm` says where the features are normalised ([`FeatureNorm`]);
/// `align_target` must be the matching target ([`FeatureNorm::align_target`]).
#[allow(clippy::too_many_arguments)]
pub fn stage3_loss<T: Real>(
    lifter: &Lifter<T>,
    decoder: &Decoder<T>,
    encoder: &Encoder<T>,
    raster_features: &Array4<T>,
    align_target: &Array4<T>,
    style: &StyleFeatureStats<T>,
    weights: Stage3Weights,
    norm: FeatureNorm,
) -> Result<Stage3Loss<T>> {
    crate::adain::check_finite("lambda_content", weights.lambda_content)?;
    crate::adain::check_finite("lambda_style", weights.lambda_style)?;
    let (lifted, ltape) = lifter.forward_with_tape(raster_features.view())?;
    let deepest_style = style.deepest();
    let normalised = match norm {
        FeatureNorm::BeforeRaster => None,
        FeatureNorm::AfterRaster => Some(instance_normalize(&lifted)?),
    };
    let t = style_transform(normalised.as_ref().unwrap_or(&lifted), deepest_style)?;
    let (image, dtape) = if weights.train_decoder {
        decoder.forward_with_param_tape(t.view())?
    } else {
        decoder.forward_with_tape(t.view())?
    };
    let loss_a = align_loss(&lifted, align_target, weights.align)?;
    let (loss_c, loss_s, g_image, g_t_target) = perceptual(
        encoder,
        &image,
        &t,
        style,
        weights.lambda_content,
        weights.lambda_style,
    )?;
    let (mut g_t, grad_decoder) = if weights.train_decoder {
        let dgrads = decoder.backward_with_params(&dtape, g_image.view())?;
        (dgrads.input, dgrads.params)
    } else {
        (decoder.backward(&dtape, g_image.view())?, Vec::new())
    };
    // The content term's target is t itself.
    g_t.zip_mut_with(&g_t_target, |a, &b| *a += b);
    let mut g_lifted = match &normalised {
        None => style_transform_backward(&lifted, deepest_style, &g_t)?.0,
        Some(y) => {
            let g_y = style_transform_backward(y, deepest_style, &g_t)?.0;
            instance_normalize_backward(&lifted, &g_y)?
        }
    };
    let g_align = align_loss_backward(&lifted, align_target, weights.align, T::one())?;
    g_lifted.zip_mut_with(&g_align, |a, &b| *a += b);
    let grads = lifter.backward(&ltape, g_lifted.view())?;
    let loss = T::lit(
        loss_a.to_f64_exact()
            + weights.lambda_content * loss_c.to_f64_exact()
            + weights.lambda_style * loss_s.to_f64_exact(),
    );
    Ok(Stage3Loss {
        lifted,
        stylized_features: t,
        image,
        loss_align: loss_a,
        loss_content: loss_c,
        loss_style: loss_s,
        loss,
        grad_raster_features: grads.input,
        grad_lifter: grads.params,
        grad_decoder,
    })
}
