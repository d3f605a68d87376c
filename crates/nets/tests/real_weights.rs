//! The real pretrained networks of the shared `weights/` directory, imported from their PyTorch
//! checkpoints, against PyTorch's outputs on a real photo and painting
//! (`oracle/fixtures/real_weights.safetensors`, stored as float32):
//! the WCT relu3_1 encoder/decoder pair (standard and fullres) and the 16x-compressed relu4_1
//! pair (floor pooling, final ReLU).
//!
//! Tolerance 1e-4 relative, as for the other `f32` comparisons: the reference itself is float64
//! rounded to float32 (relative 6e-8), and our `f32` accumulation error through these networks
//! (dot products of up to 2304 terms, up to 9 convolutions in a row) is of order 1e-6.

mod common;

use common::*;
use dsgs_testkit::arrays::hwc_image;
use dsgs_testkit::oracle::real_weights_fixture;
use dsgs_testkit::{shared_path, Fixture};
use ndarray::Array4;
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, PoolRounding, Resolution, StateDict};

const TOL: f64 = 1e-4;

fn checkpoint(rel: &str) -> StateDict {
    load_checkpoint(&shared_path(&format!("weights/{rel}"))).unwrap()
}

fn check(what: &str, a: &Array4<f32>, fx: &Fixture, key: &str) {
    let err = rel_err(a, fx.get(key));
    println!("{what} {key}: {err:.2e}");
    assert!(err <= TOL, "{key}: relative error {err:.3e}");
}

#[test]
fn wct_relu3_1_pair_matches_pytorch() {
    let fx = real_weights_fixture();
    let enc: Encoder = Encoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
    ))
    .unwrap();
    let dec: Decoder = Decoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
    ))
    .unwrap();
    assert_eq!(enc.widths(), vec![64, 128, 256]);
    assert_eq!(enc.pool_rounding(), PoolRounding::Ceil);
    assert_eq!(dec.convs_per_level(), vec![1, 2, 2]);
    assert!(!dec.final_relu());
    for res in [Resolution::Standard, Resolution::Fullres] {
        let v = if res == Resolution::Standard {
            "standard"
        } else {
            "fullres"
        };
        let enc = enc.clone().with_resolution(res);
        let dec = dec.clone().with_resolution(res);
        for img in ["content", "style"] {
            let feats = enc.forward(hwc_image(fx.get(img)).view()).unwrap();
            assert_eq!(feats.len(), 3);
            for (k, f) in feats.iter().enumerate() {
                check("wct", f, &fx, &format!("wct.{v}.{img}.relu{}_1", k + 1));
            }
            if img == "content" {
                let decoded = dec.forward(feats[2].view()).unwrap();
                check("wct", &decoded, &fx, &format!("wct.{v}.decoded_content"));
            }
        }
        // The decoder on PyTorch's AdaIN features gives PyTorch's stylized image.
        let t = arr4::<f32>(fx.get(&format!("wct.{v}.adain")));
        check(
            "wct",
            &dec.forward(t.view()).unwrap(),
            &fx,
            &format!("wct.{v}.stylized"),
        );
    }
}

/// AdaIN with the oracle's statistics (unbiased variance + 1e-5), in f64.
fn adain(c: &Array4<f64>, s: &Array4<f64>) -> Array4<f64> {
    let (cm, cs) = mean_std(c.view());
    let (sm, ss) = mean_std(s.view());
    let ch = c.dim().1;
    Array4::from_shape_fn(c.dim(), |(n, k, y, x)| {
        let i = n * ch + k;
        (c[[n, k, y, x]] - cm[i]) / cs[i] * ss[i] + sm[i]
    })
}

#[test]
fn compressed_relu4_1_pair_matches_pytorch() {
    let fx = real_weights_fixture();
    let se = checkpoint("compressed-16x-relu4_1/4SE.pth");
    let sd = checkpoint("compressed-16x-relu4_1/4SD.pth");
    let enc: Encoder = Encoder::from_state_dict(&se).unwrap();
    let dec: Decoder = Decoder::from_state_dict(&sd).unwrap();
    assert_eq!(enc.widths(), vec![16, 32, 64, 128]);
    assert_eq!(enc.pool_rounding(), PoolRounding::Floor);
    assert!(dec.final_relu());
    assert_eq!(dec.in_channels(), 128);
    let c4 = enc
        .forward(hwc_image(fx.get("content")).view())
        .unwrap()
        .pop()
        .unwrap();
    check("compressed", &c4, &fx, "compressed.content.relu4_1");
    check(
        "compressed",
        &dec.forward(c4.view()).unwrap(),
        &fx,
        "compressed.decoded_content",
    );
    let s4 = enc
        .forward(hwc_image(fx.get("style")).view())
        .unwrap()
        .pop()
        .unwrap();
    let up = |a: &Array4<f32>| a.mapv(|v| v as f64);
    let t = adain(&up(&c4), &up(&s4)).mapv(|v| v as f32);
    check(
        "compressed",
        &dec.forward(t.view()).unwrap(),
        &fx,
        "compressed.stylized",
    );
}

/// The 1/8-width AdaIN checkpoints in both PyTorch file formats import to exactly the tensors of
/// `checkpoints.safetensors`, and build the networks of the fixture.
#[test]
fn fixture_checkpoints_build_the_adain_networks() {
    let ck = Fixture::shared("oracle/fixtures/checkpoints.safetensors");
    for (net, prefix) in [("vgg", "vgg."), ("decoder", "decoder.")] {
        for format in ["legacy", "zip"] {
            let sd = load_checkpoint(&shared_path(&format!("oracle/fixtures/{net}_{format}.pth")))
                .unwrap();
            assert_eq!(sd, state_dict(&ck, prefix), "{net}_{format}.pth");
        }
    }
    let enc: Encoder = Encoder::from_state_dict(
        &load_checkpoint(&shared_path("oracle/fixtures/vgg_zip.pth")).unwrap(),
    )
    .unwrap();
    assert_eq!(enc.widths(), vec![8, 16, 32, 64, 64]);
    let dec: Decoder = Decoder::from_state_dict(
        &load_checkpoint(&shared_path("oracle/fixtures/decoder_legacy.pth")).unwrap(),
    )
    .unwrap();
    assert_eq!(dec.in_channels(), 64);
}

#[test]
fn checkpoint_errors_name_the_file() {
    let path = shared_path("weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth");
    let msg = Encoder::<f32>::from_checkpoint(&path)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("feature_invertor_conv3_1.pth") && msg.contains("`0.weight`"),
        "{msg}"
    );
    let missing = shared_path("weights/no-such-file.pth");
    let msg = Decoder::<f32>::from_checkpoint(&missing)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("no-such-file.pth"), "{msg}");
}
