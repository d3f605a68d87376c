//! Property tests on random scenes: the forward pass against a dense transcription of the oracle,
//! and every gradient of the backward pass against central differences of the forward pass.
//!
//! Scenes have random Gaussian counts, channel counts 1..=40, and image sizes that are not
//! multiples of 16 (so edge tiles are partial); Gaussians may lie partly outside the image.

mod common;

use common::{cotangents, dense_reference, min_gap, random_scene, Rng, Scene2d};
use dsgs_testkit::max_rel_err;
use proptest::prelude::*;
use raster::{rasterize, rasterize_backward, Cotangents};

/// An image side `16 k + r` with `r` in 1..16: never a multiple of 16.
fn side() -> impl Strategy<Value = u32> {
    (1u32..4, 1u32..16).prop_map(|(k, r)| 16 * k + r)
}

/// The outputs `(image, alpha, depth)` of the forward pass.
fn outputs(s: &Scene2d) -> Vec<Vec<f64>> {
    let out = rasterize(&s.splats(), s.width, s.height, &s.background).unwrap();
    vec![out.image, out.alpha, out.depth]
}

/// A central difference and an estimate of its round-off.
struct Central {
    value: f64,
    /// Round-off of `value`: every output is computed to a few ulps, so each output difference
    /// `a - b` carries an error of about `eps (|a| + |b|)`; these add up over the pixels like a
    /// random walk (independent roundings), divided by `2 h`. The factor 8 covers the roundings
    /// of one output (the blending of up to 23 Gaussians, about `sqrt(2 * 23)` ulps as a random
    /// walk). Pixels whose outputs do not change contribute nothing.
    noise: f64,
}

/// Central difference, along one scalar of the scene, of the loss
/// `sum v_image image + sum v_alpha alpha + sum v_depth depth`. The output differences are taken
/// before the dot product with the cotangents, so pixels the perturbation does not reach
/// contribute exactly zero and the round-off stays that of the affected pixels.
fn central(
    s: &Scene2d,
    h: f64,
    cot: (&[f64], &[f64], &[f64]),
    set: impl Fn(&mut Scene2d, f64),
) -> Central {
    let mut p = s.clone();
    set(&mut p, h);
    let mut m = s.clone();
    set(&mut m, -h);
    let (op, om) = (outputs(&p), outputs(&m));
    let (mut sum, mut round_off) = (0.0, 0.0);
    for (v, (a, b)) in [cot.0, cot.1, cot.2].into_iter().zip(op.iter().zip(&om)) {
        for ((&v, &a), &b) in v.iter().zip(a).zip(b) {
            sum += v * (a - b);
            if a != b {
                round_off += (v * (a.abs() + b.abs())).powi(2);
            }
        }
    }
    Central {
        value: sum / (2.0 * h),
        noise: 8.0 * f64::EPSILON * round_off.sqrt() / (2.0 * h),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// The tiled forward pass equals the dense per-pixel transcription of the oracle.
    #[test]
    fn forward_matches_dense_reference(
        n in 1usize..60, d in 1usize..=40, width in side(), height in side(), seed in any::<u64>(),
    ) {
        let s = random_scene(&mut Rng(seed), n, width, height, d);
        let out = rasterize(&s.splats(), width, height, &s.background).unwrap();
        let r = dense_reference(&s);
        prop_assert_eq!(&out.blended, &r.blended);
        // Same products in the same order; only the channel sums may round differently.
        prop_assert!(max_rel_err(&out.image, &r.image) <= 1e-14);
        prop_assert!(max_rel_err(&out.alpha, &r.alpha) <= 1e-14);
        prop_assert!(max_rel_err(&out.depth, &r.depth) <= 1e-14);
    }
}

/// Perturbation sizes of the central differences.
const H_MEAN: f64 = 1e-6;
const H_CONIC: f64 = 1e-7;
const H_OPACITY: f64 = 1e-6;
const H_DEPTH: f64 = 1e-6;
const H_LINEAR: f64 = 1e-2;

/// The largest change of any Gaussian's `ln alpha` at any pixel that one perturbation above can
/// cause, for the scenes of [`random_scene`] (conic eigenvalues <= 1, covariance eigenvalues
/// <= 20 px^2, opacities >= 0.05, `sigma <= ln 255` wherever alpha >= 1/255):
/// means `|C d| h <= sqrt(2 ln 255) h = 3.4e-6`, conics `dx^2 h / 2 <= ln 255 * 20 h = 1.2e-5`,
/// opacities `h / 0.05 = 2e-5`. Depths and channels do not change alphas.
const MAX_LOG_ALPHA_STEP: f64 = 2e-5;

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    /// Gradients of means2d, conics, opacities, depths, channels and background against central
    /// differences of the forward pass.
    ///
    /// The forward pass is discontinuous where a Gaussian's alpha crosses 1/255 (it is skipped),
    /// where a pixel's transmittance crosses 1e-4 (the pixel stops), and where depths swap order,
    /// and it has a kink where `opacity exp(-sigma)` crosses the 0.999 clamp. Scenes are drawn
    /// away from all of these, deliberately: the dense reference reports each scene's margins
    /// (in `ln alpha` from 1/255 and 0.999 over every evaluated pair, and the stop margin in units
    /// of a one-Gaussian `ln alpha` change), and a scene is rejected unless every margin is at
    /// least five times [`MAX_LOG_ALPHA_STEP`], the most any perturbation here can move `ln alpha`,
    /// and all depths are at least 1e-3 apart. The tile boxes cannot cut a Gaussian off either: the
    /// radii of [`random_scene`] enclose the region where alpha can reach 1/255.
    ///
    /// The loss is smooth along every perturbation then, and central differences in `f64` with
    /// these steps are accurate to about 1e-8 of the largest gradient of a group (round-off
    /// `eps |L| / h`, truncation `h^2 |L'''| / 6`); 1e-6 of it is the tolerance. Where every
    /// gradient of a group is close to zero (a Gaussian that barely reaches the image) the
    /// round-off alone can exceed that: a case is rejected as ill-conditioned when any
    /// difference's round-off estimate ([`Central::noise`]) exceeds a fifth of the tolerance.
    #[test]
    fn gradients_match_central_differences(
        n in 1usize..24, d in 1usize..=40, width in side(), height in side(), seed in any::<u64>(),
    ) {
        let mut rng = Rng(seed);
        let s = random_scene(&mut rng, n, width, height, d);
        let r = dense_reference(&s);
        let margin = 5.0 * MAX_LOG_ALPHA_STEP;
        prop_assume!(r.blended.iter().any(|&c| c > 0));
        prop_assume!(r.alpha_min_margin > margin && r.alpha_max_margin > margin);
        prop_assume!(r.transmittance_margin_per_unit > margin);
        prop_assume!(min_gap(&s.depths) > 1e-3);

        let pixels = (width * height) as usize;
        let (v_image, v_alpha, v_depth) = cotangents(&mut rng, pixels, d, 0.1);
        let cot = (&v_image[..], &v_alpha[..], &v_depth[..]);
        let out = rasterize(&s.splats(), width, height, &s.background).unwrap();
        let g = rasterize_backward(
            &s.splats(),
            &out.bins,
            &s.background,
            &Cotangents { image: &v_image, alpha: Some(&v_alpha), depth: Some(&v_depth) },
        )
        .unwrap();

        let (mut an, mut fd): (Vec<f64>, Vec<Central>) = (vec![], vec![]);
        let group = |name: &str,
                     an: &mut Vec<f64>,
                     fd: &mut Vec<Central>|
         -> Result<(), TestCaseError> {
            let scale = fd.iter().map(|c| c.value.abs()).fold(0.0, f64::max);
            let noise = fd.iter().map(|c| c.noise).fold(0.0, f64::max);
            if noise > 0.2 * 1e-6 * scale {
                return Err(TestCaseError::reject(format!("{name}: the gradients are at round-off")));
            }
            let values: Vec<f64> = fd.iter().map(|c| c.value).collect();
            let err = max_rel_err(an, &values);
            eprintln!("{name}: {err:.2e}");
            assert!(err <= 1e-6, "{name}: max relative error {err:.3e} (n={n} d={d} {width}x{height})");
            an.clear();
            fd.clear();
            Ok(())
        };
        for i in 0..n {
            for k in 0..2 {
                an.push(g.means2d[i][k]);
                fd.push(central(&s, H_MEAN, cot, |p, h| p.means2d[i][k] += h));
            }
        }
        group("means2d", &mut an, &mut fd)?;
        for i in 0..n {
            for k in 0..3 {
                an.push(g.conics[i][k]);
                fd.push(central(&s, H_CONIC, cot, |p, h| p.conics[i][k] += h));
            }
        }
        group("conics", &mut an, &mut fd)?;
        for i in 0..n {
            an.push(g.opacities[i]);
            fd.push(central(&s, H_OPACITY, cot, |p, h| p.opacities[i] += h));
        }
        group("opacities", &mut an, &mut fd)?;
        for i in 0..n {
            an.push(g.depths[i]);
            fd.push(central(&s, H_DEPTH, cot, |p, h| p.depths[i] += h));
        }
        group("depths", &mut an, &mut fd)?;
        // The loss is linear in channels and background: every component of two Gaussians, the
        // background, and three random directions through all channels.
        for i in [0, n / 2] {
            for k in 0..d {
                an.push(g.channels[i * d + k]);
                fd.push(central(&s, H_LINEAR, cot, |p, h| p.channels[i * d + k] += h));
            }
        }
        for _ in 0..3 {
            let u = rng.vec(n * d, -1.0, 1.0);
            an.push(g.channels.iter().zip(&u).map(|(a, b)| a * b).sum());
            fd.push(central(&s, H_LINEAR, cot, |p, h| {
                for (c, du) in p.channels.iter_mut().zip(&u) {
                    *c += h * du;
                }
            }));
        }
        group("channels", &mut an, &mut fd)?;
        for k in 0..d {
            an.push(g.background[k]);
            fd.push(central(&s, H_LINEAR, cot, |p, h| p.background[k] += h));
        }
        group("background", &mut an, &mut fd)?;
    }
}
