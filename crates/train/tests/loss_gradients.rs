//! SSIM and the photometric loss: the forward against a direct, unoptimised transcription of the
//! 3DGS `ssim` (an explicit 11x11 zero-padded window per pixel), the backward against central
//! differences, all in f64.
//!
//! SSIM is smooth everywhere (its denominators are at least `C1 * C2 > 0`, and the windowed
//! variances are non-negative because the window weights sum to at most 1), so any images work.
//! The L1 term has a kink where `render == target`; the property tests draw targets that differ
//! from the render by at least 0.05 in every value, far beyond the 1e-6 difference step, so no
//! evaluation crosses a kink.
//!
//! Tolerances. Forward: 1e-12 relative, rounding of sums of ~121 terms in f64. Gradients: central
//! differences with step h = 1e-6 have truncation error O(h^2 f''') ~ 1e-12 and rounding error
//! ~ 1e-16 / h = 1e-10 on a loss of order 1; directional derivatives are of order 1e-2 or more and
//! single-entry derivatives of order 1/(H W C) >= 1e-4, so 1e-5 relative leaves a wide margin while
//! any real error (a missing term in the chain rule) is orders of magnitude larger.

use dsgs_testkit::max_rel_err;
use proptest::prelude::*;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use train::loss::{l1_loss, photometric_loss, photometric_loss_with_grad, psnr};
use train::ssim::{gaussian_window, ssim, ssim_with_grad, C1, C2};
use train::ImageShape;

const H_STEP: f64 = 1e-6;
const GRAD_TOL: f64 = 1e-5;

/// Mean SSIM computed literally: for every channel and pixel, the five windowed moments with an
/// explicit 2-D window and zero padding, then the SSIM formula.
fn naive_ssim(x: &[f64], y: &[f64], s: ImageShape) -> f64 {
    let g = gaussian_window();
    let at = |img: &[f64], yy: isize, xx: isize, c: usize| -> f64 {
        if yy < 0 || xx < 0 || yy >= s.height as isize || xx >= s.width as isize {
            0.0
        } else {
            img[(yy as usize * s.width + xx as usize) * s.channels + c]
        }
    };
    let mut total = 0.0;
    for c in 0..s.channels {
        for py in 0..s.height as isize {
            for px in 0..s.width as isize {
                let (mut mx, mut my, mut exx, mut eyy, mut exy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dy in 0..11 {
                    for dx in 0..11 {
                        let w = g[dy] * g[dx];
                        let a = at(x, py + dy as isize - 5, px + dx as isize - 5, c);
                        let b = at(y, py + dy as isize - 5, px + dx as isize - 5, c);
                        mx += w * a;
                        my += w * b;
                        exx += w * a * a;
                        eyy += w * b * b;
                        exy += w * a * b;
                    }
                }
                let (sxx, syy, sxy) = (exx - mx * mx, eyy - my * my, exy - mx * my);
                total += ((2.0 * mx * my + C1) * (2.0 * sxy + C2))
                    / ((mx * mx + my * my + C1) * (sxx + syy + C2));
            }
        }
    }
    total / s.len() as f64
}

fn random_image(rng: &mut StdRng, s: ImageShape) -> Vec<f64> {
    (0..s.len()).map(|_| rng.random_range(0.0..1.0)).collect()
}

/// A target that differs from `x` by 0.05..0.35 in every value, with random sign.
fn distant_target(rng: &mut StdRng, x: &[f64]) -> Vec<f64> {
    x.iter()
        .map(|&v| {
            let d = rng.random_range(0.05..0.35);
            if rng.random_bool(0.5) {
                v + d
            } else {
                v - d
            }
        })
        .collect()
}

#[test]
fn ssim_forward_matches_the_literal_definition() {
    let mut rng = StdRng::seed_from_u64(1);
    for s in [
        ImageShape::new(17, 12, 3),
        ImageShape::new(5, 7, 1),
        ImageShape::new(30, 3, 2),
    ] {
        let x = random_image(&mut rng, s);
        // a target correlated with x, so SSIM is far from 0 and from 1
        let y: Vec<f64> = x
            .iter()
            .map(|&v| 0.7 * v + 0.3 * rng.random_range(0.0..1.0))
            .collect();
        let fast = ssim(&x, &y, s).unwrap();
        let slow = naive_ssim(&x, &y, s);
        assert!(
            ((fast - slow) / slow).abs() < 1e-12,
            "{s:?}: {fast} vs {slow}"
        );
        assert!(fast > 0.1 && fast < 0.99, "{fast}");
        assert!((ssim(&x, &x, s).unwrap() - 1.0).abs() < 1e-12);
    }
}

#[test]
fn ssim_of_f32_images_agrees_with_f64() {
    let mut rng = StdRng::seed_from_u64(2);
    let s = ImageShape::new(40, 33, 3);
    let x = random_image(&mut rng, s);
    let y = random_image(&mut rng, s);
    let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
    let y32: Vec<f32> = y.iter().map(|&v| v as f32).collect();
    let v64 = ssim(&x, &y, s).unwrap();
    let v32 = ssim(&x32, &y32, s).unwrap();
    // f32 storage of the inputs and f32 window sums: about 1e-6 relative on a value of ~0.01..1
    assert!((v64 - v32).abs() < 1e-5, "{v64} vs {v32}");
}

#[test]
fn wrong_sizes_are_errors() {
    let s = ImageShape::new(4, 4, 3);
    assert!(ssim(&[0.0f64; 47], &[0.0; 48], s).is_err());
    assert!(l1_loss(&[0.0f64; 48], &[0.0; 47], s).is_err());
    assert!(photometric_loss(&[0.0f64; 0], &[0.0; 0], ImageShape::new(0, 4, 3), 0.2).is_err());
}

#[test]
fn psnr_of_a_uniform_error() {
    let s = ImageShape::new(3, 2, 1);
    let a = vec![0.5f64; 6];
    let b = vec![0.6f64; 6];
    // mse = 0.01 -> 20 log10(1 / 0.1) = 20 dB
    assert!((psnr(&a, &b, s).unwrap() - 20.0).abs() < 1e-9);
}

fn directional_check(
    f: &dyn Fn(&[f64]) -> f64,
    x: &[f64],
    grad: &[f64],
    rng: &mut StdRng,
) -> Result<(), TestCaseError> {
    // three random directions along which the derivative does not cancel: where
    // `|sum g_i v_i|` is below a thousandth of `sum |g_i v_i|`, the difference quotient's
    // round-off (a few ulps of the loss over `2 h`) is no longer small against the derivative,
    // and a relative comparison measures the round-off; such a direction is drawn again (at most
    // 30 draws, else the case is rejected). The tolerance is the same for every direction checked.
    let mut checked = 0;
    for _ in 0..30 {
        if checked == 3 {
            break;
        }
        let v: Vec<f64> = (0..x.len()).map(|_| rng.random_range(-1.0..1.0)).collect();
        let analytic: f64 = grad.iter().zip(&v).map(|(g, d)| g * d).sum();
        let scale: f64 = grad.iter().zip(&v).map(|(g, d)| (g * d).abs()).sum();
        if analytic.abs() < 1e-3 * scale {
            continue;
        }
        let xp: Vec<f64> = x.iter().zip(&v).map(|(a, b)| a + H_STEP * b).collect();
        let xm: Vec<f64> = x.iter().zip(&v).map(|(a, b)| a - H_STEP * b).collect();
        let numeric = (f(&xp) - f(&xm)) / (2.0 * H_STEP);
        let err = max_rel_err(&[analytic], &[numeric]);
        prop_assert!(
            err < GRAD_TOL,
            "directional: {analytic} vs {numeric} ({err:e})"
        );
        checked += 1;
    }
    prop_assume!(checked == 3, "every direction cancels");
    // eight single entries, compared as one vector
    let mut numeric = Vec::new();
    let mut analytic = Vec::new();
    for _ in 0..8 {
        let i = rng.random_range(0..x.len());
        let mut xp = x.to_vec();
        let mut xm = x.to_vec();
        xp[i] += H_STEP;
        xm[i] -= H_STEP;
        numeric.push((f(&xp) - f(&xm)) / (2.0 * H_STEP));
        analytic.push(grad[i]);
    }
    let err = max_rel_err(&analytic, &numeric);
    prop_assert!(
        err < GRAD_TOL,
        "entries: {analytic:?} vs {numeric:?} ({err:e})"
    );
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn ssim_gradient_matches_central_differences(
        w in 1usize..24, h in 1usize..24, c in 1usize..4, seed in any::<u64>()
    ) {
        let s = ImageShape::new(w, h, c);
        let mut rng = StdRng::seed_from_u64(seed);
        let x = random_image(&mut rng, s);
        let y = random_image(&mut rng, s);
        let g = ssim_with_grad(&x, &y, s).unwrap();
        prop_assert!((g.value - ssim(&x, &y, s).unwrap()).abs() < 1e-15);
        let f = |z: &[f64]| ssim(z, &y, s).unwrap();
        directional_check(&f, &x, &g.grad_x, &mut rng)?;
    }

    #[test]
    fn photometric_loss_gradient_matches_central_differences(
        w in 1usize..24, h in 1usize..24, c in 1usize..4, lambda in 0.0f64..1.0, seed in any::<u64>()
    ) {
        let s = ImageShape::new(w, h, c);
        let mut rng = StdRng::seed_from_u64(seed);
        let x = random_image(&mut rng, s);
        let y = distant_target(&mut rng, &x);
        let (terms, grad) = photometric_loss_with_grad(&x, &y, s, lambda).unwrap();
        let plain = photometric_loss(&x, &y, s, lambda).unwrap();
        prop_assert!((terms.total - plain.total).abs() < 1e-15);
        prop_assert!((terms.total - ((1.0 - lambda) * terms.l1 + lambda * (1.0 - terms.ssim))).abs() < 1e-15);
        let f = |z: &[f64]| photometric_loss(z, &y, s, lambda).unwrap().total;
        directional_check(&f, &x, &grad, &mut rng)?;
    }
}
