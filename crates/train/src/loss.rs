//! The photometric loss of 3DGS and the image metrics used for evaluation.
//!
//! `loss = (1 - lambda) * L1 + lambda * (1 - SSIM)` with `lambda = 0.2`, where L1 is the mean
//! absolute difference over all channels and pixels and SSIM is [`crate::ssim`]. The gradient of
//! `|x - y|` is `sign(x - y)`, with `sign(0) = 0` as in PyTorch. PSNR is
//! `20 log10(1 / sqrt(MSE))` for images in [0, 1], as the 3DGS evaluation computes it.

use gaussian::Real;

use crate::error::TrainError;
use crate::ssim::{ssim, ssim_with_grad_map, sum_f64_of, ImageShape};

/// The terms of the photometric loss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossTerms {
    /// `(1 - lambda) * l1 + lambda * (1 - ssim)`.
    pub total: f64,
    /// Mean absolute error.
    pub l1: f64,
    /// Mean SSIM.
    pub ssim: f64,
}

/// The photometric loss of `render` against `target`.
pub fn photometric_loss<T: Real>(
    render: &[T],
    target: &[T],
    shape: ImageShape,
    lambda_dssim: f64,
) -> Result<LossTerms, TrainError> {
    let l1 = l1_loss(render, target, shape)?;
    let s = ssim(render, target, shape)?;
    Ok(LossTerms {
        total: (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s),
        l1,
        ssim: s,
    })
}

/// The photometric loss and its gradient with respect to `render` (laid out like `render`).
pub fn photometric_loss_with_grad<T: Real>(
    render: &[T],
    target: &[T],
    shape: ImageShape,
    lambda_dssim: f64,
) -> Result<(LossTerms, Vec<T>), TrainError> {
    let l1 = l1_loss(render, target, shape)?;
    let w_l1 = T::lit((1.0 - lambda_dssim) / shape.len() as f64);
    let w_ssim = T::lit(-lambda_dssim);
    let (ssim, grad) = ssim_with_grad_map(render, target, shape, |r, t, gs| {
        w_l1 * sign(r - t) + w_ssim * gs
    })?;
    Ok((
        LossTerms {
            total: (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim),
            l1,
            ssim,
        },
        grad,
    ))
}

/// Mean absolute difference.
pub fn l1_loss<T: Real>(a: &[T], b: &[T], shape: ImageShape) -> Result<f64, TrainError> {
    shape.check("l1: first image", a.len())?;
    shape.check("l1: second image", b.len())?;
    Ok(sum_f64_of(a, b, |x, y| (x - y).abs().to_f64_exact()) / a.len() as f64)
}

/// Mean squared difference.
pub fn mse<T: Real>(a: &[T], b: &[T], shape: ImageShape) -> Result<f64, TrainError> {
    shape.check("mse: first image", a.len())?;
    shape.check("mse: second image", b.len())?;
    Ok(sum_f64_of(a, b, |x, y| {
        let e = x.to_f64_exact() - y.to_f64_exact();
        e * e
    }) / a.len() as f64)
}

/// Peak signal-to-noise ratio in dB for images in [0, 1]: `20 log10(1 / sqrt(mse))`.
pub fn psnr<T: Real>(a: &[T], b: &[T], shape: ImageShape) -> Result<f64, TrainError> {
    Ok(psnr_from_mse(mse(a, b, shape)?))
}

/// PSNR in dB from a mean squared error.
pub fn psnr_from_mse(mse: f64) -> f64 {
    20.0 * (1.0 / mse.sqrt()).log10()
}

fn sign<T: Real>(v: T) -> T {
    if v > T::zero() {
        T::one()
    } else if v < T::zero() {
        -T::one()
    } else {
        T::zero()
    }
}
