//! The stage-3 objective of one sample: rasterize a window of the scene's feature map, evaluate
//! the 3D stylization loss on it and carry its gradient back to the per-Gaussian features and
//! the lifter ([`stage3_gradients`], steps 2-4 of the [module documentation](super)), for any
//! precision.

use gaussian::{Camera, FeatureGaussians, Real};
use ndarray::{s, Array4};
use nets::{ConvGrad, Decoder, Encoder, Lifter};
use raster::supersample::{box_mean, box_mean_backward};
use raster::{
    render_backward_features, render_window, Channels, PixelWindow, RasterError, RenderOptions,
};
use style::{
    align_loss, align_loss_backward, stage3_loss, FeatureNorm, Stage3Weights, StyleFeatureStats,
};

use crate::error::TrainError;

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
    /// Side of the block of rendered pixels averaged into each feature pixel (1: one sample
    /// per feature pixel; [`raster::supersample`]).
    pub supersample: usize,
}

/// One sample of the loss: a view, its alignment target, a style and a window.
#[derive(Clone, Copy, Debug)]
pub struct Stage3Sample<'a, T> {
    /// The feature map's camera ([`runtime::bundle::feature_map_camera`]: on the encoder's
    /// pooling grid where it pools with floor rounding), or any camera of the view, which is
    /// then rescaled to `feature_size`.
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
    let ss = setup.supersample;
    if ss == 0 {
        return Err(RasterError::Supersample(0).into());
    }
    // The feature map's camera scaled by the supersampling factor: fine pixel
    // `(ss x + i, ss y + j)` covers part `(i, j)` of feature pixel `(x, y)`.
    let cam = sample.camera.resized(
        sample.feature_size.0 * ss as u32,
        sample.feature_size.1 * ss as u32,
    );
    let opts = RenderOptions::new(Channels::Features, setup.feature_background.to_vec());
    // Only the window's pixels are rasterized (the Gaussians are projected for the whole map).
    let pixels = PixelWindow {
        x: (win.x * ss) as u32,
        y: (win.y * ss) as u32,
        width: (win.width * ss) as u32,
        height: (win.height * ss) as u32,
    };
    let fwd = render_window(&cam, scene, &opts, pixels)?;
    let img = box_mean(&fwd.raster.image, win.width, win.height, f, ss)?;
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
    let v_image = box_mean_backward(&v_image, win.width, win.height, f, ss)?;
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
