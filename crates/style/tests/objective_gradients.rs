//! The composite objectives' gradients against central differences in `f64`, along random
//! directions, on small random inputs through the oracle's (fullres) networks.
//!
//! For a direction `v`, `(L(x + h v) - L(x - h v)) / (2h)` must equal `<dL/dx, v>`. The losses are
//! smooth except at ReLU kinks; each case checks with a replay of the networks
//! (`common::pattern`) that the ReLU pattern is the same at `x - h v`, `x` and `x + h v`, and
//! discards the case otherwise (`prop_assume!`), so no difference straddles a kink. Inside one
//! linear piece the only curvature comes from the statistics and squared errors, so with
//! `h = 1e-6` the truncation error is about `1e-12` relative, and rounding adds about
//! `1e-16 |L| / h = 1e-10`; the tolerance `1e-6` (relative to `max(|<g, v>|, 1e-3 |L|)`, which
//! guards against directions that happen to be nearly orthogonal to the gradient) is far above
//! both and far below the effect of any wrong term.
//!
//! That estimate needs `h v` to be a small *relative* change. Inputs are of order one, but a
//! decoder layer's weights are of order `0.1` and a 3x3 convolution sums thousands of them, so
//! a parameter direction with entries of order one moves every layer by many times its own size
//! per unit `h`, and the loss's third derivative along it grows with the product over layers.
//! Measured on the fixture networks, such a direction (all nine layers at once) left a
//! difference off the analytic value by `1.2e-5` relative at `h = 3e-6` and `1.6e-6` at
//! `h = 1e-6`, shrinking as `h^2` towards it: truncation, not a wrong gradient. Parameter directions are therefore scaled per layer
//! by the root mean square of that layer's weights (`param_scales`); with them the difference
//! at `h = 1e-6` agrees to about `1e-8` relative.

mod common;

use common::*;
use ndarray::{Array1, Array4};
use nets::{Decoder, Encoder, Lifter, Resolution};
use proptest::prelude::*;
use style::*;

const H: f64 = 1e-6;
const TOL: f64 = 1e-6;

fn map(
    n: usize,
    c: usize,
    h: usize,
    w: usize,
    lo: f64,
    hi: f64,
) -> impl Strategy<Value = Array4<f64>> {
    prop::collection::vec(lo..hi, n * c * h * w)
        .prop_map(move |v| Array4::from_shape_vec((n, c, h, w), v).unwrap())
}

struct Nets {
    enc: Encoder<f64>,
    dec: Decoder<f64>,
    lift: Lifter<f64>,
}

fn nets() -> Nets {
    let fx = nets_fixture();
    let (enc, dec) = networks::<f64>(&fx, Resolution::Fullres);
    Nets {
        enc,
        dec,
        lift: lifter::<f64>(&fx),
    }
}

/// All ReLU patterns of lifter (if given), decoder and encoder for a decoder input or raster map;
/// `norm` says whether the lifted map is instance-normalised before the transform.
fn patterns(
    n: &Nets,
    x: &Array4<f64>,
    with_lifter: Option<&Lifter<f64>>,
    style: &StyleFeatureStats<f64>,
) -> Vec<Option<Array4<bool>>> {
    patterns_with(n, &n.dec, x, with_lifter, style, FeatureNorm::BeforeRaster)
}

fn patterns_with(
    n: &Nets,
    dec: &Decoder<f64>,
    x: &Array4<f64>,
    with_lifter: Option<&Lifter<f64>>,
    style: &StyleFeatureStats<f64>,
    norm: FeatureNorm,
) -> Vec<Option<Array4<bool>>> {
    let mut out = Vec::new();
    let t = match with_lifter {
        Some(l) => {
            let f = pattern::forward(&pattern::lifter_steps(l), x);
            out.extend(f.pattern);
            let y = match norm {
                FeatureNorm::BeforeRaster => f.outputs[0].clone(),
                FeatureNorm::AfterRaster => instance_normalize(&f.outputs[0]).unwrap(),
            };
            style_transform(&y, style.deepest()).unwrap()
        }
        None => x.clone(),
    };
    let d = pattern::forward(&pattern::decoder_steps(dec), &t);
    out.extend(d.pattern);
    let e = pattern::forward(&pattern::encoder_steps(&n.enc), &d.outputs[0]);
    out.extend(e.pattern);
    out
}

/// The scales of a parameter direction for one layer: the root mean square of its weights, and
/// of its biases (at least the weights' scale, so zero biases still move).
fn param_scales(weight: &[f64], bias: &[f64]) -> (f64, f64) {
    let rms = |a: &[f64]| (a.iter().map(|x| x * x).sum::<f64>() / a.len().max(1) as f64).sqrt();
    let sw = rms(weight);
    (sw, rms(bias).max(sw))
}

fn dot(a: &Array4<f64>, b: &Array4<f64>) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn close(what: &str, analytic: f64, numeric: f64, loss: f64) -> Result<(), TestCaseError> {
    let scale = analytic.abs().max(1e-3 * loss.abs());
    prop_assert!(
        (analytic - numeric).abs() <= TOL * scale,
        "{what}: analytic {analytic:.9e}, differences {numeric:.9e}"
    );
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(8))]

    #[test]
    fn stage3_gradients_match_differences(
        raster in map(1, 32, 5, 6, -1.0, 1.0),
        target in map(1, 64, 5, 6, -1.5, 1.5),
        style_img in map(1, 3, 6, 5, 0.0, 1.0),
        v in map(1, 32, 5, 6, -1.0, 1.0),
        vw in map(64, 32, 1, 1, -1.0, 1.0),
        vb in prop::collection::vec(-1.0f64..1.0, 64),
        l1 in any::<bool>(),
    ) {
        let n = nets();
        let s = encode_style(&n.enc, &style_img).unwrap();
        let weights = Stage3Weights { lambda_content: 0.7, lambda_style: 1.3, align: if l1 { AlignLoss::L1 } else { AlignLoss::Mse }, train_decoder: false };
        let norm = FeatureNorm::BeforeRaster;
        let out = stage3_loss(&n.lift, &n.dec, &n.enc, &raster, &target, &s, weights, norm).unwrap();
        let loss_at = |lift: &Lifter<f64>, r: &Array4<f64>| stage3_loss(lift, &n.dec, &n.enc, r, &target, &s, weights, norm).unwrap().loss;
        // Raster direction.
        let (rp, rm) = (&raster + &(&v * H), &raster - &(&v * H));
        let base = patterns(&n, &raster, Some(&n.lift), &s);
        prop_assume!(patterns(&n, &rp, Some(&n.lift), &s) == base && patterns(&n, &rm, Some(&n.lift), &s) == base);
        if l1 {
            // |lifted - target| must not change sign inside the step either.
            let lifted = |r: &Array4<f64>| n.lift.forward(r.view()).unwrap();
            let sign = |r: &Array4<f64>| (lifted(r) - &target).mapv(|d| d > 0.0);
            prop_assume!(sign(&rp) == sign(&raster) && sign(&rm) == sign(&raster));
        }
        let numeric = (loss_at(&n.lift, &rp) - loss_at(&n.lift, &rm)) / (2.0 * H);
        close("raster features", dot(&out.grad_raster_features, &v), numeric, out.loss)?;
        // Lifter parameter direction.
        let w = n.lift.layer().weight.clone();
        let b = n.lift.layer().bias.clone();
        let vb = Array1::from_vec(vb);
        let lp = Lifter::new(&w + &(&vw * H), &b + &(&vb * H)).unwrap();
        let lm = Lifter::new(&w - &(&vw * H), &b - &(&vb * H)).unwrap();
        prop_assume!(patterns(&n, &raster, Some(&lp), &s) == base && patterns(&n, &raster, Some(&lm), &s) == base);
        if l1 {
            let sign = |l: &Lifter<f64>| (l.forward(raster.view()).unwrap() - &target).mapv(|d| d > 0.0);
            prop_assume!(sign(&lp) == sign(&n.lift) && sign(&lm) == sign(&n.lift));
        }
        let numeric = (loss_at(&lp, &raster) - loss_at(&lm, &raster)) / (2.0 * H);
        let analytic = dot(&out.grad_lifter.weight, &vw) + out.grad_lifter.bias.iter().zip(&vb).map(|(a, b)| a * b).sum::<f64>();
        close("lifter parameters", analytic, numeric, out.loss)?;
    }

    #[test]
    fn decoder_training_gradients_match_differences(
        t in map(1, 64, 5, 6, 0.0, 2.0),
        target in map(1, 64, 5, 6, 0.0, 2.0),
        style_img in map(1, 3, 7, 5, 0.0, 1.0),
        v in map(1, 64, 5, 6, -1.0, 1.0),
        layer in 0usize..9,
        seed in 0u64..1000,
    ) {
        let n = nets();
        let s = encode_style(&n.enc, &style_img).unwrap();
        let out = decoder_training_loss(&n.enc, &n.dec, &t, &target, &s, 10.0).unwrap();
        let loss_at = |dec: &Decoder<f64>, x: &Array4<f64>| decoder_training_loss(&n.enc, dec, x, &target, &s, 10.0).unwrap().loss;
        let base = patterns(&n, &t, None, &s);
        let (tp, tm) = (&t + &(&v * H), &t - &(&v * H));
        prop_assume!(patterns(&n, &tp, None, &s) == base && patterns(&n, &tm, None, &s) == base);
        let numeric = (loss_at(&n.dec, &tp) - loss_at(&n.dec, &tm)) / (2.0 * H);
        close("decoder input", dot(&out.grad_input, &v), numeric, out.loss)?;
        // One layer's parameters along a pseudo-random direction.
        let shape = n.dec.layers().nth(layer).unwrap().weight.raw_dim();
        let mut st = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut rnd = || { st = st.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407); (st >> 11) as f64 / (1u64 << 53) as f64 - 0.5 };
        let l = n.dec.layers().nth(layer).unwrap();
        let (sw, sb) = param_scales(l.weight.as_slice().unwrap(), l.bias.as_slice().unwrap());
        let dw = Array4::from_shape_fn(shape, |_| sw * rnd());
        let db = Array1::from_shape_fn(shape[0], |_| sb * rnd());
        let shifted = |sign: f64| {
            let mut d = n.dec.clone();
            let l = d.layers_mut().nth(layer).unwrap();
            l.weight.scaled_add(sign * H, &dw);
            l.bias.scaled_add(sign * H, &db);
            d
        };
        let (dp, dm) = (shifted(1.0), shifted(-1.0));
        let pat = |d: &Decoder<f64>| {
            let f = pattern::forward(&pattern::decoder_steps(d), &t);
            let e = pattern::forward(&pattern::encoder_steps(&n.enc), &f.outputs[0]);
            (f.pattern, e.pattern)
        };
        prop_assume!(pat(&dp) == pat(&n.dec) && pat(&dm) == pat(&n.dec));
        let numeric = (loss_at(&dp, &t) - loss_at(&dm, &t)) / (2.0 * H);
        let g = &out.grad_params[layer];
        let analytic = dot(&g.weight, &dw) + g.bias.iter().zip(&db).map(|(a, b)| a * b).sum::<f64>();
        close(&format!("decoder layer {layer}"), analytic, numeric, out.loss)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(8))]

    /// The design ablation (`FeatureNorm::AfterRaster`: the lifted map instance-normalised over
    /// its own pixels before the transform) and the decoder's parameter gradients, which a
    /// decoder trained in stage 3 steps with: both against central differences.
    #[test]
    fn stage3_after_raster_and_decoder_gradients_match_differences(
        raster in map(1, 32, 5, 6, -1.0, 1.0),
        target in map(1, 64, 5, 6, 0.0, 2.0),
        style_img in map(1, 3, 6, 5, 0.0, 1.0),
        v in map(1, 32, 5, 6, -1.0, 1.0),
        seed in any::<u64>(),
        after in any::<bool>(),
    ) {
        let n = nets();
        let s = encode_style(&n.enc, &style_img).unwrap();
        let norm = if after { FeatureNorm::AfterRaster } else { FeatureNorm::BeforeRaster };
        let weights = Stage3Weights { lambda_content: 0.7, lambda_style: 1.3, align: AlignLoss::Mse, train_decoder: true };
        let loss_at = |dec: &Decoder<f64>, r: &Array4<f64>| {
            stage3_loss(&n.lift, dec, &n.enc, r, &target, &s, weights, norm).unwrap().loss
        };
        let out = stage3_loss(&n.lift, &n.dec, &n.enc, &raster, &target, &s, weights, norm).unwrap();
        // A frozen decoder: no decoder gradients, and every other result the same bits.
        let frozen = Stage3Weights { train_decoder: false, ..weights };
        let f = stage3_loss(&n.lift, &n.dec, &n.enc, &raster, &target, &s, frozen, norm).unwrap();
        prop_assert!(f.grad_decoder.is_empty());
        prop_assert_eq!(f.loss.to_bits(), out.loss.to_bits());
        prop_assert_eq!(&f.image, &out.image);
        prop_assert_eq!(&f.grad_raster_features, &out.grad_raster_features);
        prop_assert_eq!(&f.grad_lifter.weight, &out.grad_lifter.weight);
        prop_assert_eq!(&f.grad_lifter.bias, &out.grad_lifter.bias);
        let base = patterns_with(&n, &n.dec, &raster, Some(&n.lift), &s, norm);
        let same = |dec: &Decoder<f64>, r: &Array4<f64>| patterns_with(&n, dec, r, Some(&n.lift), &s, norm) == base;
        // Raster direction.
        let (rp, rm) = (&raster + &(&v * H), &raster - &(&v * H));
        prop_assume!(same(&n.dec, &rp) && same(&n.dec, &rm));
        let numeric = (loss_at(&n.dec, &rp) - loss_at(&n.dec, &rm)) / (2.0 * H);
        close("raster features", dot(&out.grad_raster_features, &v), numeric, out.loss)?;
        // Decoder parameters along one random direction.
        let dirs = decoder_direction(&n.dec, seed);
        let shifted = |h: f64| shifted_decoder(&n.dec, &dirs, h);
        let (dp, dm) = (shifted(H), shifted(-H));
        prop_assume!(same(&dp, &raster) && same(&dm, &raster));
        prop_assert_eq!(out.grad_decoder.len(), n.dec.layers().count());
        let analytic: f64 = out
            .grad_decoder
            .iter()
            .zip(&dirs)
            .map(|(g, (dw, db))| dot(&g.weight, dw) + g.bias.iter().zip(db).map(|(a, b)| a * b).sum::<f64>())
            .sum();
        let numeric = (loss_at(&dp, &raster) - loss_at(&dm, &raster)) / (2.0 * H);
        close("decoder parameters", analytic, numeric, out.loss)?;
    }
}

/// A random direction in the decoder's parameters, one `(weight, bias)` pair per layer, each
/// layer's entries uniform in `[-1, 1)` times the layer's own scale ([`param_scales`]; see the
/// module docs), from `seed`.
fn decoder_direction(dec: &Decoder<f64>, seed: u64) -> Vec<(Array4<f64>, Array1<f64>)> {
    let mut rng = dsgs_testkit::SplitMix64(seed);
    dec.layers()
        .map(|l| {
            let (sw, sb) = param_scales(l.weight.as_slice().unwrap(), l.bias.as_slice().unwrap());
            let w = Array4::from_shape_simple_fn(l.weight.dim(), || sw * rng.uniform(-1.0, 1.0));
            let b = Array1::from_shape_simple_fn(l.bias.len(), || sb * rng.uniform(-1.0, 1.0));
            (w, b)
        })
        .collect()
}

/// `dec` moved by `h` along `dirs`.
fn shifted_decoder(
    dec: &Decoder<f64>,
    dirs: &[(Array4<f64>, Array1<f64>)],
    h: f64,
) -> Decoder<f64> {
    let mut d = dec.clone();
    for (l, (dw, db)) in d.layers_mut().zip(dirs) {
        l.weight = &l.weight + &(dw * h);
        l.bias = &l.bias + &(db * h);
    }
    d
}

/// A second encoder to measure style with: the fixture encoder to relu2_1 with every weight
/// rescaled by a fixed pseudo-random factor in `[0.5, 1.5)`, so that its levels differ from the
/// decoder's encoder in depth and in values.
fn style_network(enc: &Encoder<f64>) -> Encoder<f64> {
    let mut psi = enc.clone().with_depth(2).unwrap();
    let mut rng = dsgs_testkit::SplitMix64(7);
    for l in psi.layers_mut() {
        l.weight.mapv_inplace(|w| w * rng.uniform(0.5, 1.5));
    }
    psi
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(8))]

    /// Decoder training with a separate style network: with the decoder's own encoder as the
    /// style network it is the one-network loss (the same loss bits; the gradients differ only
    /// in summation order), and with another network its gradients match central differences.
    #[test]
    fn decoder_training_with_a_style_network_matches_differences(
        t in map(1, 64, 5, 6, 0.0, 2.0),
        target in map(1, 64, 5, 6, 0.0, 2.0),
        style_img in map(1, 3, 7, 5, 0.0, 1.0),
        v in map(1, 64, 5, 6, -1.0, 1.0),
        seed in any::<u64>(),
    ) {
        let n = nets();
        let psi = style_network(&n.enc);
        // The same network for both terms: the one-network loss.
        let s = encode_style(&n.enc, &style_img).unwrap();
        let one = decoder_training_loss(&n.enc, &n.dec, &t, &target, &s, 10.0).unwrap();
        let same = decoder_training_loss_with_style_network(&n.enc, &n.enc, &n.dec, &t, &target, &s, 10.0).unwrap();
        prop_assert_eq!(one.loss.to_bits(), same.loss.to_bits());
        prop_assert_eq!(one.loss_style.to_bits(), same.loss_style.to_bits());
        prop_assert_eq!(&one.image, &same.image);
        let rel = |a: &Array4<f64>, b: &Array4<f64>| {
            let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
            let den: f64 = b.iter().map(|y| y * y).sum();
            (num / den.max(1e-300)).sqrt()
        };
        // Summation order only: a few units in the last place of f64.
        prop_assert!(rel(&same.grad_input, &one.grad_input) < 1e-12);
        for (a, b) in same.grad_params.iter().zip(&one.grad_params) {
            prop_assert!(rel(&a.weight, &b.weight) < 1e-12, "{}", a.name);
        }
        // Another network: the style statistics are its own, and the losses its levels'.
        let sp = encode_style(&psi, &style_img).unwrap();
        prop_assert!(decoder_training_loss_with_style_network(&n.enc, &n.enc, &n.dec, &t, &target, &sp, 10.0).is_err());
        let out = decoder_training_loss_with_style_network(&n.enc, &psi, &n.dec, &t, &target, &sp, 10.0).unwrap();
        let loss_at = |dec: &Decoder<f64>, x: &Array4<f64>| {
            decoder_training_loss_with_style_network(&n.enc, &psi, dec, x, &target, &sp, 10.0).unwrap().loss
        };
        let pat = |dec: &Decoder<f64>, x: &Array4<f64>| {
            let d = pattern::forward(&pattern::decoder_steps(dec), x);
            let e = pattern::forward(&pattern::encoder_steps(&n.enc), &d.outputs[0]);
            let p = pattern::forward(&pattern::encoder_steps(&psi), &d.outputs[0]);
            (d.pattern, e.pattern, p.pattern)
        };
        let base = pat(&n.dec, &t);
        // Decoder input direction.
        let (tp, tm) = (&t + &(&v * H), &t - &(&v * H));
        prop_assume!(pat(&n.dec, &tp) == base && pat(&n.dec, &tm) == base);
        let numeric = (loss_at(&n.dec, &tp) - loss_at(&n.dec, &tm)) / (2.0 * H);
        close("decoder input", dot(&out.grad_input, &v), numeric, out.loss)?;
        // Every decoder layer along one direction scaled to the layer (see the module docs).
        let dirs = decoder_direction(&n.dec, seed);
        let shifted = |h: f64| shifted_decoder(&n.dec, &dirs, h);
        let (dp, dm) = (shifted(H), shifted(-H));
        prop_assume!(pat(&dp, &t) == base && pat(&dm, &t) == base);
        let analytic: f64 = out
            .grad_params
            .iter()
            .zip(&dirs)
            .map(|(g, (dw, db))| dot(&g.weight, dw) + g.bias.iter().zip(db).map(|(a, b)| a * b).sum::<f64>())
            .sum();
        let numeric = (loss_at(&dp, &t) - loss_at(&dm, &t)) / (2.0 * H);
        close("decoder parameters", analytic, numeric, out.loss)?;
    }
}
