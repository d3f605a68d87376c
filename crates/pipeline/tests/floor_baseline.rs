//! The per-frame 2D baseline of `dsgs eval` (`pipeline::eval::baseline_view`) with a standard
//! encoder that pools with floor rounding (the real 16x-compressed relu4_1 pair): frames of any
//! size come back whole, where the decoder alone would give back less than the frame; and the
//! padding that makes this possible repeats the frame's last row and column.

use dsgs_testkit::shared_path;
use gaussian::dataset::RgbImage;
use gaussian::FeatureGaussians;
use ndarray::{Array1, Array4};
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, Lifter, PoolRounding};
use pipeline::eval::{baseline_view, pad_to_multiple};
use pipeline::stylize::{load_styles, style_targets};
use runtime::{BundleInfo, SceneBundle, Variant};

/// Feature channels of the bundle (its scene is empty: the baseline reads only the networks).
const F: usize = 4;

fn compressed_bundle() -> SceneBundle {
    let load = |rel: &str| load_checkpoint(&shared_path(&format!("weights/{rel}"))).unwrap();
    let encoder: Encoder =
        Encoder::from_state_dict(&load("compressed-16x-relu4_1/4SE.pth")).unwrap();
    let decoder: Decoder =
        Decoder::from_state_dict(&load("compressed-16x-relu4_1/4SD.pth")).unwrap();
    assert_eq!(encoder.pool_rounding(), PoolRounding::Floor);
    let c = *encoder.widths().last().unwrap();
    let lifter = Lifter::new(Array4::zeros((c, F, 1, 1)), Array1::zeros(c)).unwrap();
    let info = BundleInfo::new(
        &encoder,
        Variant::Standard,
        F,
        [0.0; 3],
        (vec![0.0; c], vec![1.0; c]),
        Vec::new(),
    );
    SceneBundle {
        scene: FeatureGaussians {
            feature_dim: F,
            ..Default::default()
        },
        encoder,
        decoder,
        lifter,
        info,
    }
}

/// A smooth colour image of `w x h`.
fn frame(w: u32, h: u32) -> RgbImage {
    let data = (0..w * h * 3)
        .map(|i| {
            let (p, c) = (i / 3, i % 3);
            let (x, y) = ((p % w) as f32 / w as f32, (p / w) as f32 / h as f32);
            (0.2 + 0.3 * x + 0.2 * y + 0.1 * c as f32).clamp(0.0, 1.0)
        })
        .collect();
    RgbImage {
        width: w,
        height: h,
        data,
    }
}

#[test]
fn baseline_frames_of_any_size_come_back_whole() {
    let bundle = compressed_bundle();
    let styles = load_styles(&[shared_path("data/styles/mondrian.jpg")], 64).unwrap();
    let targets = style_targets(&bundle, &styles, None, None).unwrap();
    // 90 x 160 is the beer can's draft frame; 37 x 29 is a multiple of nothing.
    for (w, h) in [(160, 90), (37, 29), (64, 48)] {
        let colour = frame(w, h);
        // The decoder alone gives back less than a side that is not a multiple of 8.
        let x = pipeline::image_io::nchw_from_rgb(&colour);
        let y = style::stylize::stylize(
            &bundle.encoder,
            &bundle.decoder,
            &x,
            targets[0].stats.deepest(),
            1.0,
        )
        .unwrap();
        assert_eq!(
            (y.dim().2, y.dim().3),
            ((h / 8 * 8) as usize, (w / 8 * 8) as usize)
        );
        let out = baseline_view(&bundle, &colour, &targets[0], 1.0).unwrap();
        assert_eq!((out.width, out.height), (w, h));
        assert!(out.data.iter().all(|v| (0.0..=1.0).contains(v)));
    }
}

#[test]
fn padding_repeats_the_last_row_and_column() {
    let x = Array4::from_shape_fn((1, 2, 3, 5), |(_, c, y, x)| (c * 100 + y * 10 + x) as f32);
    let p = pad_to_multiple(x.clone(), 4);
    assert_eq!(p.dim(), (1, 2, 4, 8));
    for c in 0..2 {
        for y in 0..4 {
            for xx in 0..8 {
                assert_eq!(p[[0, c, y, xx]], x[[0, c, y.min(2), xx.min(4)]]);
            }
        }
    }
    // Already a multiple: unchanged.
    let q = pad_to_multiple(p.clone(), 2);
    assert_eq!(q, p);
    assert_eq!(pad_to_multiple(x.clone(), 1), x);
}
