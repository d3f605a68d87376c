//! Gradient property tests: every backward pass against central differences, in `f64`.
//!
//! The kernels are generic over the scalar type, so these tests run the production code itself in
//! `f64`, where a central difference is accurate to about `1e-16 * |L| / h`.
//!
//! * Linear maps (convolutions, upsampling, max-pool with its arg-max fixed) have no truncation
//!   error, so every input and parameter entry is checked one by one with `h = 1e-3`, to a relative
//!   tolerance of 1e-9 of the gradient's largest entry.
//! * Kinks are avoided on purpose: the ReLU test draws inputs at least 0.05 away from zero and
//!   steps by `h = 1e-4`; the max-pool test uses distinct values at least 0.01 apart with
//!   `h = 1e-4`, so no step changes an arg-max.
//! * Whole networks are checked by directional derivatives `<grad, d>` against
//!   `(L(x + h d) - L(x - h d)) / 2h` with `h = 1e-6`. A step moves a pre-activation by about 1e-6
//!   while pre-activations are spread over O(1), so the chance that a step crosses a ReLU kink or
//!   flips a max-pool is about 1e-6 per element, and the proptest seed is fixed so the cases are
//!   the same on every run. Truncation error is O(h^2) on the smooth pieces; the tolerance is
//!   1e-6 relative to `|grad| |d|`.

mod common;

use common::*;
use ndarray::{Array1, Array4};
use nets::conv::*;
use nets::pool::{max_pool2x2, max_pool2x2_backward, PoolRounding};
use nets::upsample::{upsample2x, upsample2x_backward};
use nets::{Decoder, Encoder, Lifter, Resolution, StateDict};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};

fn config(cases: u32) -> Config {
    Config {
        cases,
        rng_seed: RngSeed::Fixed(20_240_601),
        failure_persistence: None,
        ..Config::default()
    }
}

/// Checks every entry of `analytic` against central differences of `loss` along that entry of
/// `param` (a flat view of some array), with tolerance `tol` relative to the largest gradient.
fn check_entries(
    what: &str,
    param: &mut [f64],
    analytic: &[f64],
    h: f64,
    tol: f64,
    loss: &mut dyn FnMut(&[f64]) -> f64,
) {
    assert_eq!(param.len(), analytic.len(), "{what}: gradient shape");
    let scale = analytic
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(1e-12);
    for i in 0..param.len() {
        let keep = param[i];
        param[i] = keep + h;
        let lp = loss(param);
        param[i] = keep - h;
        let lm = loss(param);
        param[i] = keep;
        let fd = (lp - lm) / (2.0 * h);
        let err = (fd - analytic[i]).abs() / scale;
        assert!(
            err <= tol,
            "{what}[{i}]: analytic {} vs central difference {fd} (rel {err:.2e})",
            analytic[i]
        );
    }
}

const TOL_LINEAR: f64 = 1e-9;

proptest! {
    #![proptest_config(config(24))]

    #[test]
    fn conv3x3_reflect_gradients(seed in any::<u64>(), n in 1usize..3, c in 1usize..4, o in 1usize..4,
                                 h in 2usize..6, w in 2usize..6) {
        let mut rng = TestRng::new(seed);
        let x = rng.array4((n, c, h, w));
        let wt = rng.array4((o, c, 3, 3));
        let b = rng.array1(o);
        let v = rng.array4((n, o, h, w));
        let dx = conv3x3_reflect_backward_input(v.view(), wt.view());
        let (dw, db) = conv3x3_reflect_backward_params(x.view(), v.view());
        let mut xs = x.clone().into_raw_vec_and_offset().0;
        check_entries("conv3x3 dx", &mut xs, dx.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let xa = Array4::from_shape_vec((n, c, h, w), p.to_vec()).unwrap();
            dot(&conv3x3_reflect(xa.view(), wt.view(), b.view(), false), &v)
        });
        let mut ws = wt.clone().into_raw_vec_and_offset().0;
        check_entries("conv3x3 dw", &mut ws, dw.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let wa = Array4::from_shape_vec((o, c, 3, 3), p.to_vec()).unwrap();
            dot(&conv3x3_reflect(x.view(), wa.view(), b.view(), false), &v)
        });
        let mut bs = b.to_vec();
        check_entries("conv3x3 db", &mut bs, db.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let ba = Array1::from_vec(p.to_vec());
            dot(&conv3x3_reflect(x.view(), wt.view(), ba.view(), false), &v)
        });
    }

    #[test]
    fn conv1x1_gradients(seed in any::<u64>(), n in 1usize..3, c in 1usize..5, o in 1usize..5,
                         h in 1usize..5, w in 1usize..5) {
        let mut rng = TestRng::new(seed);
        let x = rng.array4((n, c, h, w));
        let wt = rng.array4((o, c, 1, 1));
        let b = rng.array1(o);
        let v = rng.array4((n, o, h, w));
        let dx = conv1x1_backward_input(v.view(), wt.view());
        let (dw, db) = conv1x1_backward_params(x.view(), v.view());
        let mut xs = x.clone().into_raw_vec_and_offset().0;
        check_entries("conv1x1 dx", &mut xs, dx.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let xa = Array4::from_shape_vec((n, c, h, w), p.to_vec()).unwrap();
            dot(&conv1x1(xa.view(), wt.view(), b.view(), false), &v)
        });
        let mut ws = wt.clone().into_raw_vec_and_offset().0;
        check_entries("conv1x1 dw", &mut ws, dw.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let wa = Array4::from_shape_vec((o, c, 1, 1), p.to_vec()).unwrap();
            dot(&conv1x1(x.view(), wa.view(), b.view(), false), &v)
        });
        let mut bs = b.to_vec();
        check_entries("conv1x1 db", &mut bs, db.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let ba = Array1::from_vec(p.to_vec());
            dot(&conv1x1(x.view(), wt.view(), ba.view(), false), &v)
        });
    }

    /// ReLU through the lifter with an identity weight and zero bias, so the lifter is exactly
    /// `relu(x)`; inputs are at least 0.05 away from zero.
    #[test]
    fn relu_gradient(seed in any::<u64>(), c in 1usize..5, h in 1usize..5, w in 1usize..5) {
        let mut rng = TestRng::new(seed);
        let x = rng.array4((1, c, h, w)).mapv(|u| u.signum() * (0.05 + u.abs()));
        let eye = Array4::from_shape_fn((c, c, 1, 1), |(i, j, _, _)| if i == j { 1.0 } else { 0.0 });
        let relu: Lifter<f64> = Lifter::new(eye, Array1::zeros(c)).unwrap();
        let v = rng.array4((1, c, h, w));
        let (y, tape) = relu.forward_with_tape(x.view()).unwrap();
        prop_assert_eq!(y, x.mapv(|u| u.max(0.0)));
        let g = relu.backward(&tape, v.view()).unwrap();
        let mut xs = x.clone().into_raw_vec_and_offset().0;
        check_entries("relu dx", &mut xs, g.input.as_slice().unwrap(), 1e-4, TOL_LINEAR, &mut |p| {
            let xa = Array4::from_shape_vec((1, c, h, w), p.to_vec()).unwrap();
            dot(&relu.forward(xa.view()).unwrap(), &v)
        });
    }

    /// Max-pool with distinct values (a shuffled grid 0.01 apart), both roundings, odd and even
    /// sizes, so ceil-mode windows that hang over the edge are covered.
    #[test]
    fn max_pool_gradient(seed in any::<u64>(), c in 1usize..3, h in 2usize..7, w in 2usize..7,
                         ceil in any::<bool>()) {
        let mut rng = TestRng::new(seed);
        let total = c * h * w;
        let mut vals: Vec<f64> = (0..total).map(|i| i as f64 * 0.01).collect();
        for i in (1..total).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            vals.swap(i, j);
        }
        let x = Array4::from_shape_vec((1, c, h, w), vals).unwrap();
        let rounding = if ceil { PoolRounding::Ceil } else { PoolRounding::Floor };
        let (y, arg) = max_pool2x2(x.view(), rounding);
        let (ho, wo) = (rounding.pooled(h), rounding.pooled(w));
        prop_assert_eq!(y.dim(), (1, c, ho, wo));
        // The forward value against a direct maximum over the clipped window.
        for ((_, ch, oy, ox), &m) in y.indexed_iter() {
            let mut best = f64::NEG_INFINITY;
            for yy in 2 * oy..(2 * oy + 2).min(h) {
                for xx in 2 * ox..(2 * ox + 2).min(w) {
                    best = best.max(x[[0, ch, yy, xx]]);
                }
            }
            prop_assert_eq!(m, best);
        }
        let v = rng.array4((1, c, ho, wo));
        let dx = max_pool2x2_backward(v.view(), &arg);
        let mut xs = x.clone().into_raw_vec_and_offset().0;
        check_entries("maxpool dx", &mut xs, dx.as_slice().unwrap(), 1e-4, TOL_LINEAR, &mut |p| {
            let xa = Array4::from_shape_vec((1, c, h, w), p.to_vec()).unwrap();
            dot(&max_pool2x2(xa.view(), rounding).0, &v)
        });
    }

    #[test]
    fn upsample_gradient(seed in any::<u64>(), c in 1usize..3, h in 1usize..5, w in 1usize..5) {
        let mut rng = TestRng::new(seed);
        let x = rng.array4((2, c, h, w));
        let y = upsample2x(x.view());
        for ((n, ch, yy, xx), &val) in y.indexed_iter() {
            prop_assert_eq!(val, x[[n, ch, yy / 2, xx / 2]]);
        }
        let v = rng.array4((2, c, 2 * h, 2 * w));
        let dx = upsample2x_backward(v.view());
        let mut xs = x.clone().into_raw_vec_and_offset().0;
        check_entries("upsample dx", &mut xs, dx.as_slice().unwrap(), 1e-3, TOL_LINEAR, &mut |p| {
            let xa = Array4::from_shape_vec((2, c, h, w), p.to_vec()).unwrap();
            dot(&upsample2x(xa.view()), &v)
        });
    }
}

/// A tiny encoder (widths 3/4/5/6, relu3_1) and its decoder in the Sequential layout
/// (`named = false`: ceil pooling, no final ReLU) or the compressed named layout (floor pooling,
/// final ReLU).
fn tiny_networks(seed: u64, named: bool) -> (Encoder<f64>, Decoder<f64>) {
    let mut rng = TestRng::new(seed);
    let mut e = StateDict::new();
    let mut d = StateDict::new();
    if named {
        rng.conv_into(&mut e, "conv0", 3, 3, 1);
        for (name, o, c) in [
            ("conv11", 4, 3),
            ("conv12", 4, 4),
            ("conv21", 5, 4),
            ("conv22", 5, 5),
            ("conv31", 6, 5),
        ] {
            rng.conv_into(&mut e, name, o, c, 3);
        }
        rng.conv_into(&mut e, "conv11_aux", 7, 4, 1); // ignored
        for (name, o, c) in [
            ("conv31", 5, 6),
            ("conv22", 5, 5),
            ("conv21", 4, 5),
            ("conv12", 4, 4),
            ("conv11", 3, 4),
        ] {
            rng.conv_into(&mut d, name, o, c, 3);
        }
    } else {
        rng.conv_into(&mut e, "0", 3, 3, 1);
        for (name, o, c) in [
            ("2", 4, 3),
            ("5", 4, 4),
            ("9", 5, 4),
            ("12", 5, 5),
            ("16", 6, 5),
        ] {
            rng.conv_into(&mut e, name, o, c, 3);
        }
        for (name, o, c) in [
            ("1", 5, 6),
            ("5", 5, 5),
            ("8", 4, 5),
            ("12", 4, 4),
            ("15", 3, 4),
        ] {
            rng.conv_into(&mut d, name, o, c, 3);
        }
    }
    (
        Encoder::from_state_dict(&e).unwrap(),
        Decoder::from_state_dict(&d).unwrap(),
    )
}

/// Directional-derivative check: `|fd - an| <= tol * |grad| * |d|`.
fn check_direction(what: &str, an: f64, lp: f64, lm: f64, h: f64, bound: f64) {
    let fd = (lp - lm) / (2.0 * h);
    let err = (fd - an).abs() / bound.max(1e-300);
    assert!(
        err <= 1e-6,
        "{what}: analytic {an} vs central difference {fd} (rel {err:.2e})"
    );
}

fn norm(a: &Array4<f64>) -> f64 {
    dot(a, a).sqrt()
}

proptest! {
    #![proptest_config(config(12))]

    /// Encoder input gradient with cotangents on a random subset of relu1_1..relu3_1.
    #[test]
    fn encoder_input_gradient(seed in any::<u64>(), n in 1usize..3, h in 8usize..13, w in 8usize..13,
                              named in any::<bool>(), fullres in any::<bool>(), subset in 1u8..8) {
        let (enc, _) = tiny_networks(seed, named);
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let enc = enc.with_resolution(res);
        let mut rng = TestRng::new(seed ^ 1);
        let x = rng.array4((n, 3, h, w));
        let (feats, tape) = enc.forward_with_tape(x.view()).unwrap();
        let cots: Vec<Option<Array4<f64>>> = feats
            .iter()
            .enumerate()
            .map(|(k, f)| (subset >> k & 1 == 1).then(|| rng.array4(f.dim())))
            .collect();
        let views: Vec<_> = cots.iter().map(|c| c.as_ref().map(|a| a.view())).collect();
        let dx = enc.backward(&tape, &views).unwrap();
        let loss = |xa: &Array4<f64>| -> f64 {
            let fs = enc.forward(xa.view()).unwrap();
            fs.iter().zip(&cots).map(|(f, c)| c.as_ref().map_or(0.0, |c| dot(f, c))).sum()
        };
        let d = rng.array4(x.dim());
        let hstep = 1e-6;
        let an = dot(&dx, &d);
        check_direction("encoder dx", an, loss(&(&x + &(&d * hstep))), loss(&(&x - &(&d * hstep))),
                        hstep, norm(&dx) * norm(&d));
    }

    /// Decoder input and parameter gradients.
    #[test]
    fn decoder_gradients(seed in any::<u64>(), n in 1usize..3, h in 2usize..5, w in 2usize..5,
                         named in any::<bool>(), fullres in any::<bool>()) {
        let (_, dec) = tiny_networks(seed, named);
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let dec = dec.with_resolution(res);
        let mut rng = TestRng::new(seed ^ 2);
        let x = rng.array4((n, 6, h, w)).mapv(|u| u.abs()); // decoder inputs are ReLU features
        check_decoder_gradients("decoder", &dec, &x, &mut rng);
    }

    /// Lifter input and parameter gradients (generic random weights: ReLU kinks avoided as in
    /// the whole-network checks).
    #[test]
    fn lifter_gradients(seed in any::<u64>(), f in 1usize..6, c in 1usize..6, h in 1usize..5) {
        let mut rng = TestRng::new(seed);
        let lifter: Lifter<f64> = Lifter::new(rng.array4((c, f, 1, 1)), rng.array1(c)).unwrap();
        let x = rng.array4((2, f, h, h + 1));
        let (y, tape) = lifter.forward_with_tape(x.view()).unwrap();
        let v = rng.array4(y.dim());
        let g = lifter.backward(&tape, v.view()).unwrap();
        let hstep = 1e-6;
        let d = rng.array4(x.dim());
        let loss = |l: &Lifter<f64>, xa: &Array4<f64>| dot(&l.forward(xa.view()).unwrap(), &v);
        check_direction("lifter dx", dot(&g.input, &d), loss(&lifter, &(&x + &(&d * hstep))),
                        loss(&lifter, &(&x - &(&d * hstep))), hstep, norm(&g.input) * norm(&d));
        let (dw, db) = (rng.array4((c, f, 1, 1)), rng.array1(c));
        let shifted = |s: f64| {
            let l = lifter.layer();
            Lifter::new(&l.weight + &(&dw * s), &l.bias + &(&db * s)).unwrap()
        };
        let an = dot(&g.params.weight, &dw) + dot(&g.params.bias, &db);
        let bound = ((dot(&g.params.weight, &g.params.weight) + dot(&g.params.bias, &g.params.bias))
            * (dot(&dw, &dw) + dot(&db, &db))).sqrt();
        check_direction("lifter dparams", an, loss(&shifted(hstep), &x), loss(&shifted(-hstep), &x),
                        hstep, bound);
    }
}

/// A decoder's input gradient along a random direction, and its parameter gradients along one
/// random direction of all parameters, against central differences of `<v, decoder(x)>`.
fn check_decoder_gradients(what: &str, dec: &Decoder<f64>, x: &Array4<f64>, rng: &mut TestRng) {
    let (y, tape) = dec.forward_with_param_tape(x.view()).unwrap();
    let v = rng.array4(y.dim());
    let grads = dec.backward_with_params(&tape, v.view()).unwrap();
    // The input gradient alone, from either tape, is the same computation.
    let (y_light, light) = dec.forward_with_tape(x.view()).unwrap();
    assert_eq!(y_light, y, "{what}: the two taped forward passes differ");
    assert_eq!(
        dec.backward(&light, v.view()).unwrap(),
        grads.input,
        "{what}: input gradient"
    );
    assert_eq!(
        dec.backward(&tape, v.view()).unwrap(),
        grads.input,
        "{what}: input gradient"
    );
    assert!(
        dec.backward_with_params(&light, v.view()).is_err(),
        "{what}: parameter gradients from a tape without the conv inputs"
    );
    let hstep = 1e-6;
    let d = rng.array4(x.dim());
    let loss = |dd: &Decoder<f64>, xa: &Array4<f64>| dot(&dd.forward(xa.view()).unwrap(), &v);
    check_direction(
        &format!("{what} dx"),
        dot(&grads.input, &d),
        loss(dec, &(x + &(&d * hstep))),
        loss(dec, &(x - &(&d * hstep))),
        hstep,
        norm(&grads.input) * norm(&d),
    );
    let dirs: Vec<(Array4<f64>, Array1<f64>)> = dec
        .layers()
        .map(|l| (rng.array4(l.weight.dim()), rng.array1(l.bias.len())))
        .collect();
    let shifted = |s: f64| {
        let mut dd = dec.clone();
        for (l, (dw, db)) in dd.layers_mut().zip(&dirs) {
            l.weight = &l.weight + &(dw * s);
            l.bias = &l.bias + &(db * s);
        }
        dd
    };
    let (mut an, mut g2, mut d2) = (0.0, 0.0, 0.0);
    for (g, (dw, db)) in grads.params.iter().zip(&dirs) {
        an += dot(&g.weight, dw) + dot(&g.bias, db);
        g2 += dot(&g.weight, &g.weight) + dot(&g.bias, &g.bias);
        d2 += dot(dw, dw) + dot(db, db);
    }
    check_direction(
        &format!("{what} dparams"),
        an,
        loss(&shifted(hstep), x),
        loss(&shifted(-hstep), x),
        hstep,
        (g2 * d2).sqrt(),
    );
}

/// A pointwise decoder `c -> 5 -> 4 -> 3` with random weights (`conv1_3` first).
fn tiny_pointwise(rng: &mut TestRng, c: usize, final_relu: bool) -> Decoder<f64> {
    let widths = [c, 5, 4, 3];
    let layers = (0..3)
        .map(|i| nets::ConvLayer {
            name: format!("conv1_{}", 3 - i),
            source: format!("conv1_{}", 3 - i),
            weight: rng.array4((widths[i + 1], widths[i], 1, 1)),
            bias: rng.array1(widths[i + 1]),
        })
        .collect();
    Decoder::pointwise(layers, final_relu).unwrap()
}

proptest! {
    #![proptest_config(config(12))]

    /// A pointwise decoder is the per-pixel MLP `W3 relu(W2 relu(W1 x + b1) + b2) + b3` (written
    /// out here pixel by pixel), keeps the input size at either resolution, and its input and
    /// parameter gradients match central differences.
    #[test]
    fn pointwise_decoder(seed in any::<u64>(), c in 1usize..6, h in 1usize..5, w in 1usize..5,
                         fullres in any::<bool>(), final_relu in any::<bool>()) {
        let mut rng = TestRng::new(seed);
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let dec = tiny_pointwise(&mut rng, c, final_relu).with_resolution(res);
        prop_assert!(dec.is_pointwise());
        prop_assert_eq!(dec.output_size((h, w)), (h, w));
        let x = rng.array4((2, c, h, w));
        let y = dec.forward(x.view()).unwrap();
        prop_assert_eq!(y.dim(), (2, 3, h, w));
        let layers: Vec<_> = dec.layers().collect();
        for n in 0..2 {
            for yy in 0..h {
                for xx in 0..w {
                    let mut a: Vec<f64> = (0..c).map(|ch| x[[n, ch, yy, xx]]).collect();
                    for (k, l) in layers.iter().enumerate() {
                        let relu = k + 1 < layers.len() || final_relu;
                        a = (0..l.out_channels())
                            .map(|o| {
                                let z = l.bias[o]
                                    + (0..a.len()).map(|i| l.weight[[o, i, 0, 0]] * a[i]).sum::<f64>();
                                if relu { z.max(0.0) } else { z }
                            })
                            .collect();
                    }
                    for (o, &want) in a.iter().enumerate() {
                        let got = y[[n, o, yy, xx]];
                        // Summation order may differ from the GEMM's: 1e-12 relative.
                        prop_assert!((got - want).abs() <= 1e-12 * (1.0 + want.abs()),
                                     "pixel ({n}, {o}, {yy}, {xx}): {got} vs {want}");
                    }
                }
            }
        }
        check_decoder_gradients("pointwise", &dec, &x, &mut rng);
    }
}

/// Malformed pointwise decoders are refused with the conv named.
#[test]
fn bad_pointwise_decoders_are_refused() {
    let mut rng = TestRng::new(7);
    let conv = |name: &str, o: usize, c: usize, k: usize, rng: &mut TestRng| nets::ConvLayer {
        name: name.into(),
        source: name.into(),
        weight: rng.array4((o, c, k, k)),
        bias: rng.array1(o),
    };
    let err = |r: Result<Decoder<f64>, nets::NetError>| r.unwrap_err().to_string();
    assert!(err(Decoder::pointwise(vec![], false)).contains("at least one"));
    let e = err(Decoder::pointwise(
        vec![conv("conv1_1", 3, 4, 3, &mut rng)],
        false,
    ));
    assert!(e.contains("conv1_1") && e.contains("[O, C, 1, 1]"), "{e}");
    let e = err(Decoder::pointwise(
        vec![
            conv("conv1_2", 5, 4, 1, &mut rng),
            conv("conv1_1", 3, 6, 1, &mut rng),
        ],
        false,
    ));
    assert!(
        e.contains("takes 6 channels") && e.contains("makes 5"),
        "{e}"
    );
    let e = err(Decoder::pointwise(
        vec![
            conv("conv1_1", 5, 4, 1, &mut rng),
            conv("conv1_1", 3, 5, 1, &mut rng),
        ],
        false,
    ));
    assert!(e.contains("two convs"), "{e}");
}
