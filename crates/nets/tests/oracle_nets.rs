//! The encoder, decoder, one wide layer and the lifter against the float64 PyTorch oracle
//! (`oracle/fixtures/nets.safetensors`, 1/8-width AdaIN layout, standard and fullres).
//!
//! Tolerances: the `f64` runs use the exact float64 weights and must agree to 1e-10 relative (only
//! summation order differs from PyTorch). The `f32` runs round weights and inputs to `f32` and
//! accumulate dot products of up to 2304 terms through up to 9 layers; with unit round-off 6e-8
//! the expected relative error is a few 1e-6, so 1e-4 (the project's f32 acceptance level) leaves
//! a wide margin while still catching any indexing or convention error, which shows up as O(1).

mod common;

use common::*;
use ndarray::Array4;
use nets::{conv, Decoder, Encoder, Lifter, Resolution};

const TOL_F32: f64 = 1e-4;
const TOL_F64: f64 = 1e-10;

fn networks_f32(res: Resolution) -> (Encoder, Decoder) {
    let fx = nets_fixture();
    let enc = Encoder::from_state_dict(&state_dict(&fx, "vgg."))
        .unwrap()
        .with_depth(4)
        .unwrap()
        .with_resolution(res);
    let dec = Decoder::from_state_dict(&state_dict(&fx, "decoder."))
        .unwrap()
        .with_resolution(res);
    (enc, dec)
}

fn variant_name(res: Resolution) -> &'static str {
    match res {
        Resolution::Standard => "standard",
        Resolution::Fullres => "fullres",
    }
}

#[test]
fn layout_of_the_adain_fixture_is_recognised() {
    let fx = nets_fixture();
    let enc: Encoder = Encoder::from_state_dict(&state_dict(&fx, "vgg.")).unwrap();
    assert_eq!(enc.depth(), 5, "vgg_normalised reaches relu5_1");
    let enc = enc.with_depth(4).unwrap();
    assert_eq!(enc.widths(), vec![8, 16, 32, 64]);
    assert_eq!(enc.convs_per_level(), vec![2, 2, 4, 1]);
    let names: Vec<(String, String)> = enc
        .layers()
        .map(|l| (l.name.clone(), l.source.clone()))
        .collect();
    assert_eq!(names[0], ("conv0".into(), "0".into()));
    assert_eq!(names[1], ("conv1_1".into(), "2".into()));
    assert_eq!(names[5], ("conv3_1".into(), "16".into()));
    assert_eq!(names[9], ("conv4_1".into(), "29".into()));
    let dec: Decoder = Decoder::from_state_dict(&state_dict(&fx, "decoder.")).unwrap();
    let dnames: Vec<(String, String)> = dec
        .layers()
        .map(|l| (l.name.clone(), l.source.clone()))
        .collect();
    let expected = [
        ("conv4_1", "1"),
        ("conv3_4", "5"),
        ("conv3_3", "8"),
        ("conv3_2", "11"),
        ("conv3_1", "14"),
        ("conv2_2", "18"),
        ("conv2_1", "21"),
        ("conv1_2", "25"),
        ("conv1_1", "28"),
    ];
    for (got, want) in dnames.iter().zip(expected) {
        assert_eq!((got.0.as_str(), got.1.as_str()), want);
    }
    assert_eq!(dec.depth(), 4);
    assert_eq!(dec.in_channels(), 64);
    assert!(!dec.final_relu());
}

fn check_encoder(res: Resolution) {
    let fx = nets_fixture();
    let v = variant_name(res);
    let (e64, _) = networks_f64(res);
    let (e32, _) = networks_f32(res);
    for img in ["content", "style"] {
        let x = fx.get(img);
        let f64s = e64.forward(arr4::<f64>(x).view()).unwrap();
        let f32s = e32.forward(arr4::<f32>(x).view()).unwrap();
        for k in 0..4 {
            let e = fx.get(&format!("{v}.{img}.relu{}_1", k + 1));
            let err64 = rel_err(&f64s[k], e);
            let err32 = rel_err(&f32s[k], e);
            println!(
                "{v} {img} relu{}_1: f64 {err64:.2e}, f32 {err32:.2e}",
                k + 1
            );
            assert!(
                err64 <= TOL_F64,
                "{v} {img} relu{}_1 f64 error {err64:.3e}",
                k + 1
            );
            assert!(
                err32 <= TOL_F32,
                "{v} {img} relu{}_1 f32 error {err32:.3e}",
                k + 1
            );
        }
    }
}

#[test]
fn encoder_features_match_the_oracle_standard() {
    check_encoder(Resolution::Standard);
}

#[test]
fn encoder_features_match_the_oracle_fullres() {
    check_encoder(Resolution::Fullres);
}

fn check_decoder(res: Resolution) {
    let fx = nets_fixture();
    let v = variant_name(res);
    let (_, d64) = networks_f64(res);
    let (_, d32) = networks_f32(res);
    let t = fx.get(&format!("{v}.adain"));
    let e = fx.get(&format!("{v}.decoded"));
    let err64 = rel_err(&d64.forward(arr4::<f64>(t).view()).unwrap(), e);
    let err32 = rel_err(&d32.forward(arr4::<f32>(t).view()).unwrap(), e);
    println!("{v} decoded: f64 {err64:.2e}, f32 {err32:.2e}");
    assert!(err64 <= TOL_F64, "{v} decoded f64 error {err64:.3e}");
    assert!(err32 <= TOL_F32, "{v} decoded f32 error {err32:.3e}");
}

#[test]
fn decoder_output_matches_the_oracle_standard() {
    check_decoder(Resolution::Standard);
}

#[test]
fn decoder_output_matches_the_oracle_fullres() {
    check_decoder(Resolution::Fullres);
}

/// The content + 10 * style loss of the oracle and its cotangents on relu1_1..relu4_1, written
/// out in the test from the oracle definitions (content: MSE of relu4_1 with the AdaIN target `t`;
/// style: MSE of channel means plus MSE of channel standard deviations at every level), so the
/// gradient checks below cover exactly the network backward passes.
fn style_loss_cotangents(
    gf: &[Array4<f64>],
    sf: &[Array4<f64>],
    t: &Array4<f64>,
) -> (f64, Vec<Array4<f64>>) {
    let mut cot = Vec::new();
    let mut loss_s = 0.0;
    for k in 0..4 {
        let (gm, gs) = mean_std(gf[k].view());
        let (sm, ss) = mean_std(sf[k].view());
        let nc = gm.len() as f64;
        loss_s += gm
            .iter()
            .zip(&sm)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            / nc
            + gs.iter()
                .zip(&ss)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                / nc;
        let dm: Vec<f64> = gm
            .iter()
            .zip(&sm)
            .map(|(a, b)| 10.0 * 2.0 * (a - b) / nc)
            .collect();
        let ds: Vec<f64> = gs
            .iter()
            .zip(&ss)
            .map(|(a, b)| 10.0 * 2.0 * (a - b) / nc)
            .collect();
        let mut c = mean_std_backward(gf[k].view(), &dm, &ds);
        if k == 3 {
            c = c + (&gf[3] - t) * (2.0 / t.len() as f64);
        }
        cot.push(c);
    }
    let loss_c = (&gf[3] - t).mapv(|d| d * d).sum() / t.len() as f64;
    (loss_c + 10.0 * loss_s, cot)
}

/// Decoder input and parameter gradients of the oracle's content + 10 * style loss, through the
/// decoder and encoder backward passes under test, in `f64` (to 1e-10) and in `f32` (to the
/// same 1e-4 as the forward passes: the chain is longer, about 36 convolutions, but the measured
/// error stays near 2e-6).
fn check_decoder_gradients(res: Resolution) {
    let fx = nets_fixture();
    let v = variant_name(res);
    let (enc, dec) = networks_f64(res);
    let t = arr4::<f64>(fx.get(&format!("{v}.adain")));
    let (image, dtape) = dec.forward_with_param_tape(t.view()).unwrap();
    let (gf, etape) = enc.forward_with_tape(image.view()).unwrap();
    let sf = enc.forward(arr4::<f64>(fx.get("style")).view()).unwrap();
    let (loss, cot) = style_loss_cotangents(&gf, &sf, &t);
    let want = fx.get(&format!("{v}.loss")).scalar();
    assert!(
        (loss - want).abs() <= 1e-10 * want.abs(),
        "{v} loss {loss} vs {want}"
    );
    let views: Vec<_> = cot.iter().map(|c| Some(c.view())).collect();
    let dimage = enc.backward(&etape, &views).unwrap();
    let grads = dec.backward_with_params(&dtape, dimage.view()).unwrap();
    let err = rel_err(&grads.input, fx.get(&format!("{v}.grad.decoder_input")));
    println!("{v} grad decoder_input: {err:.2e}");
    assert!(err <= TOL_F64, "{v} decoder input gradient error {err:.3e}");
    for g in &grads.params {
        let ew = rel_err(
            &g.weight,
            fx.get(&format!("{v}.grad.decoder.{}.weight", g.source)),
        );
        let eb = rel_err(
            &g.bias,
            fx.get(&format!("{v}.grad.decoder.{}.bias", g.source)),
        );
        println!(
            "{v} grad {} ({}): weight {ew:.2e} bias {eb:.2e}",
            g.name, g.source
        );
        assert!(
            ew <= TOL_F64 && eb <= TOL_F64,
            "{v} gradient of {} off: {ew:.3e} {eb:.3e}",
            g.name
        );
    }

    // The same in f32 (the loss cotangents are formed in f64 from the f32 features).
    let (enc, dec) = networks_f32(res);
    let t32 = arr4::<f32>(fx.get(&format!("{v}.adain")));
    let (image, dtape) = dec.forward_with_param_tape(t32.view()).unwrap();
    let (gf, etape) = enc.forward_with_tape(image.view()).unwrap();
    let sf = enc.forward(arr4::<f32>(fx.get("style")).view()).unwrap();
    let up = |a: &Array4<f32>| a.mapv(|x| x as f64);
    let gf64: Vec<_> = gf.iter().map(up).collect();
    let sf64: Vec<_> = sf.iter().map(up).collect();
    let (_, cot) = style_loss_cotangents(&gf64, &sf64, &t);
    let cot32: Vec<Array4<f32>> = cot.iter().map(|c| c.mapv(|x| x as f32)).collect();
    let views: Vec<_> = cot32.iter().map(|c| Some(c.view())).collect();
    let dimage = enc.backward(&etape, &views).unwrap();
    let grads = dec.backward_with_params(&dtape, dimage.view()).unwrap();
    let mut worst = rel_err(&grads.input, fx.get(&format!("{v}.grad.decoder_input")));
    for g in &grads.params {
        worst = worst
            .max(rel_err(
                &g.weight,
                fx.get(&format!("{v}.grad.decoder.{}.weight", g.source)),
            ))
            .max(rel_err(
                &g.bias,
                fx.get(&format!("{v}.grad.decoder.{}.bias", g.source)),
            ));
    }
    println!("{v} f32 decoder gradients: worst {worst:.2e}");
    assert!(
        worst <= TOL_F32,
        "{v} f32 decoder gradients: worst error {worst:.3e}"
    );
}

#[test]
fn decoder_gradients_of_the_style_loss_match_the_oracle_standard() {
    check_decoder_gradients(Resolution::Standard);
}

#[test]
fn decoder_gradients_of_the_style_loss_match_the_oracle_fullres() {
    check_decoder_gradients(Resolution::Fullres);
}

fn check_wide<T: base::Real>(tol: f64) {
    let fx = nets_fixture();
    let x = arr4::<T>(fx.get("wide.input"));
    let w = arr4::<T>(fx.get("wide.weight"));
    let b: ndarray::Array1<T> = fx
        .get("wide.bias")
        .data
        .iter()
        .map(|&v| T::lit(v))
        .collect();
    let y = conv::conv3x3_reflect(x.view(), w.view(), b.view(), true);
    let v = arr4::<T>(fx.get("wide.v_output"));
    let g = ndarray::Zip::from(&v)
        .and(&y)
        .map_collect(|&v, &y| if y > T::zero() { v } else { T::zero() });
    let dx = conv::conv3x3_reflect_backward_input(g.view(), w.view());
    let (dw, db) = conv::conv3x3_reflect_backward_params(x.view(), g.view());
    let errs = [
        ("output", rel_err(&y, fx.get("wide.output"))),
        ("grad.input", rel_err(&dx, fx.get("wide.grad.input"))),
        ("grad.weight", rel_err(&dw, fx.get("wide.grad.weight"))),
        ("grad.bias", rel_err(&db, fx.get("wide.grad.bias"))),
    ];
    for (what, err) in errs {
        println!("wide {what} ({}): {err:.2e}", std::any::type_name::<T>());
        assert!(err <= tol, "wide {what}: error {err:.3e} above {tol:.0e}");
    }
}

#[test]
fn wide_layer_forward_and_gradients_match_the_oracle() {
    check_wide::<f64>(TOL_F64);
    check_wide::<f32>(TOL_F32);
}

#[test]
fn lifter_matches_the_oracle() {
    let fx = nets_fixture();
    let w = arr4::<f32>(fx.get("lifter.weight"));
    let b = fx.get("lifter.bias").to_f32().into();
    let lifter = Lifter::new(w, b).unwrap();
    let y = lifter
        .forward(arr4::<f32>(fx.get("stage3.raster_features")).view())
        .unwrap();
    let err = rel_err(&y, fx.get("stage3.lifted"));
    println!("lifter f32: {err:.2e}");
    assert!(err <= TOL_F32);
    let l64: Lifter<f64> = Lifter::new(
        arr4(fx.get("lifter.weight")),
        fx.get("lifter.bias").data.clone().into(),
    )
    .unwrap();
    let y = l64
        .forward(arr4::<f64>(fx.get("stage3.raster_features")).view())
        .unwrap();
    let err = rel_err(&y, fx.get("stage3.lifted"));
    println!("lifter f64: {err:.2e}");
    assert!(err <= TOL_F64);
}
