//! The settings of a feature training run ([`FeatureTrainConfig`]): their defaults, their
//! validation, the crop window's side and the loss weights of each iteration.

use serde::{Deserialize, Serialize};
use style::{FeatureNorm, Stage3Weights};

use crate::adam::AdamConfig;
use crate::error::TrainError;
use runtime::bundle::{DecoderMode, Variant, MAX_SUPERSAMPLE};

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
    /// Side of the block of rendered pixels averaged into each feature pixel
    /// ([`raster::supersample`]): 1 renders the feature map at its own resolution, one sample
    /// per feature pixel; `s` renders it `s` times finer and averages each `s x s` block, so a
    /// feature pixel is the features averaged over its footprint, as the encoder's pooled
    /// target summarises its image block. The bundle records it and stylization renders the
    /// same way. At most [`MAX_SUPERSAMPLE`] (16: a feature pixel of the standard relu4_1
    /// networks covers `8 x 8` image pixels).
    pub supersample: u32,
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
            supersample: 1,
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
    /// Fails with [`TrainError::Config`] naming the first setting that cannot work.
    pub(super) fn validate(&self) -> Result<(), TrainError> {
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
        if !(1..=MAX_SUPERSAMPLE).contains(&self.supersample) {
            return bad(format!(
                "supersample is {}; it must be 1 to {MAX_SUPERSAMPLE}",
                self.supersample
            ));
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_supersampling_factor_out_of_range_is_refused_by_name() {
        for s in [1, 8, MAX_SUPERSAMPLE] {
            let c = FeatureTrainConfig {
                supersample: s,
                ..Default::default()
            };
            assert!(c.validate().is_ok(), "{s}");
        }
        for s in [0, MAX_SUPERSAMPLE + 1] {
            let c = FeatureTrainConfig {
                supersample: s,
                ..Default::default()
            };
            let err = c.validate().unwrap_err().to_string();
            assert!(err.contains(&format!("supersample is {s}")), "{err}");
        }
    }
}
