//! The fixed evaluation of a run (see "Evaluation" in the [module documentation](super)): its
//! samples, drawn once from the seed, and its result ([`FeatureEvaluation`]).

use gaussian::Camera;
use ndarray::{s, Array4};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use style::StyleFeatureStats;

use super::objective::CropWindow;
use crate::decoder_training::{mix, EVAL_STREAM};
use base::event::Metric;

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

/// A fixed evaluation sample: a view's camera and feature-map size, the centred window and the
/// view's alignment target on it, and a style's statistics.
#[derive(Clone, Debug)]
pub(super) struct EvalSample {
    pub(super) camera: Camera,
    pub(super) feature_size: (u32, u32),
    pub(super) window: CropWindow,
    pub(super) target: Array4<f32>,
    pub(super) style: StyleFeatureStats<f32>,
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
    pub(super) fn new(
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
pub(super) fn eval_indices(
    seed: u64,
    pairs: usize,
    views: usize,
    styles: usize,
) -> Vec<(usize, usize)> {
    let mut rng = StdRng::seed_from_u64(mix(seed, EVAL_STREAM, 0));
    (0..pairs)
        .map(|_| (rng.random_range(0..views), rng.random_range(0..styles)))
        .collect()
}
