//! The evaluation's losses of a frame encoded tile by tile (`eval::FrameLosses` under a small
//! budget) against the frame encoded whole, with the real relu3_1 encoder in both variants.
//!
//! The texture distance (Gram matrices accumulated in `f64` over the tiles) 1e-12 relative: the
//! same `f64` products of bit-identical features, summed in another order.
//!
//! Also the perceptual distance of the consistency metrics, tiled against whole: the same `f64`
//! terms of bit-identical features summed in another order, so 1e-12 relative.
//!
//! Tolerance of the losses 1e-6 relative: the tiles' features equal the whole frame's bit for bit
//! (`nets::tiled`), and the statistics differ only by the `f64` rounding of another summation
//! order (1e-12 relative, `style/tests/moments.rs`); rounded to `f32` (6e-8) they can move by
//! one unit in the last place, which moves a squared difference of statistics by twice that
//! relative to it, a few 1e-7 of the loss.

use dsgs_testkit::shared_path;
use gaussian::dataset::images::RgbImage;
use nets::{Encoder, Resolution};
use pipeline::consistency::{encodes_whole, perceptual_distance};
use pipeline::eval::{FrameLosses, StyleMeasures};
use proptest::prelude::*;
use style::{channel_stats, gram};

fn image(seed: u64, width: u32, height: u32) -> RgbImage {
    let mut state = seed;
    let data = (0..width * height * 3)
        .map(|i| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            // Smooth structure plus noise, in [0, 1].
            let p = (i / 3) as f32;
            (0.5 + 0.3 * (p * 0.07).sin()) * 0.8
                + 0.2 * ((state >> 40) as f32 / (1u64 << 24) as f32)
        })
        .collect();
    RgbImage {
        width,
        height,
        data,
    }
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 4, ..ProptestConfig::default() })]

    #[test]
    fn losses_of_tiles_equal_the_losses_of_the_whole_frame(
        width in 24u32..56, height in 24u32..56, seed in any::<u64>(), fullres in any::<bool>(),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let enc: Encoder = Encoder::from_checkpoint(&shared_path(
            "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
        )).unwrap().with_resolution(res);
        let colour = image(seed, width, height);
        let frame = image(seed ^ 1, width, height);
        let painting = pipeline::image_io::nchw_from_rgb(&image(seed ^ 2, 40, 30));
        let encoded = enc.forward(painting.view()).unwrap();
        let stats: Vec<_> = encoded.iter().map(|f| channel_stats(f).unwrap()).collect();
        let grams: Vec<_> = encoded.iter().map(|f| gram(f, 0).unwrap()).collect();
        let style = StyleMeasures { stats: &stats, grams: &grams };
        let whole = FrameLosses::new(&enc, &colour, 1 << 40).unwrap();
        let tiled = FrameLosses::new(&enc, &colour, 1 << 20).unwrap();
        prop_assert!(!whole.tiled() && tiled.tiled());
        let w = whole.of(&frame, style).unwrap();
        let t = tiled.of(&frame, style).unwrap();
        prop_assert!(rel(t.style, w.style) <= 1e-6, "style {t:?} {w:?}");
        prop_assert!(rel(t.content, w.content) <= 1e-6, "content {t:?} {w:?}");
        // The texture distance is summed in f64 throughout: only the summation order differs.
        prop_assert!(rel(t.texture, w.texture) <= 1e-12, "texture {t:?} {w:?}");
        prop_assert!(w.texture > 0.0);

        let mask: Vec<bool> = (0..width * height).map(|i| !(i * 7 + seed as u32 % 5).is_multiple_of(11)).collect();
        let distance = |budget| perceptual_distance(&enc, &colour, &frame, &mask, budget).unwrap().unwrap();
        prop_assert!(!encodes_whole(&enc.clone().with_resolution(Resolution::Standard), (height as usize, width as usize), 1 << 20).unwrap());
        let (dw, dt) = (distance(1 << 40), distance(1 << 20));
        prop_assert!(rel(dt, dw) <= 1e-12, "perceptual {dt} {dw}");
    }
}
