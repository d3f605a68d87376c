//! Tiled execution (`nets::tiled`) against the whole-image pass, for random image and tile sizes:
//! the oracle's 1/8-width encoder (every level) and decoder, standard and fullres, in `f64` and
//! `f32`, and the real WCT relu3_1 pair and the compressed relu4_1 pair in `f32`.
//!
//! Tolerance: none, in `f64` and `f32` alike. A tile sums every kept pixel's products in the
//! order of the whole image: the direct convolution's GEMMs block their inner dimension by the
//! channel count and the cache sizes only (never by the image width), and the tile regions
//! start at even coordinates, so the Winograd layers of the real networks use the same 2x2
//! blocks. (Without that rounding to even, the relu3_1 pair differed from the whole image by up
//! to 1.4e-6 of the largest value: measured when the rounding was taken out.)

mod common;

use common::*;
use dsgs_testkit::shared_path;
use ndarray::{s, Array4};
use nets::tiled::{grid, Region};
use nets::{Decoder, Encoder, Resolution};
use proptest::prelude::*;

/// Bit-identical (see the module docs).
const EXACT: f64 = 0.0;

fn image<T: base::Real>(seed: u64, h: usize, w: usize) -> Array4<T> {
    TestRng::new(seed)
        .array4((1, 3, h, w))
        .mapv(|v| T::lit(0.5 + 0.5 * v))
}

/// The largest difference relative to the largest reference value.
fn rel<T: base::Real>(a: &Array4<T>, b: &Array4<T>) -> f64 {
    assert_eq!(a.shape(), b.shape());
    dsgs_testkit::max_rel_err(&to_f64(a.iter()), &to_f64(b.iter()))
}

/// Every level of `enc` and the decoder of the deepest level, whole against tiled.
fn check_networks<T: base::Real>(
    enc: &Encoder<T>,
    dec: &Decoder<T>,
    x: &Array4<T>,
    tile: usize,
    tol: f64,
) -> Result<(), TestCaseError> {
    let whole = enc.forward(x.view()).unwrap();
    for (k, f) in whole.iter().enumerate() {
        let tiled = enc.forward_tiled(x.view(), k + 1, tile).unwrap();
        let err = rel(&tiled, f);
        prop_assert!(err <= tol, "relu{}_1, tile {tile}: {err:.3e}", k + 1);
    }
    let t = whole.last().unwrap();
    let decoded = dec.forward(t.view()).unwrap();
    let tiled = dec.forward_tiled(t.view(), tile).unwrap();
    let err = rel(&tiled, &decoded);
    prop_assert!(err <= tol, "decoder, tile {tile}: {err:.3e}");
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    #[test]
    fn tiles_of_the_fixture_networks_equal_the_whole_image_in_f64(
        h in 16usize..44, w in 16usize..44, tile in 1usize..24, seed in any::<u64>(), fullres in any::<bool>(),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let (enc, dec) = networks_f64(res);
        check_networks(&enc, &dec, &image::<f64>(seed, h, w), tile, EXACT)?;
    }

    #[test]
    fn tiles_of_the_fixture_networks_equal_the_whole_image_in_f32(
        h in 16usize..44, w in 16usize..44, tile in 1usize..24, seed in any::<u64>(), fullres in any::<bool>(),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let (enc, dec) = networks_f64(res);
        check_networks(&enc.cast::<f32>(), &dec.cast::<f32>(), &image::<f32>(seed, h, w), tile, EXACT)?;
    }
}

proptest! {
    // The real networks run Winograd on their wide layers; fewer, smaller cases (each case
    // encodes and decodes the image once whole and once per tile).
    #![proptest_config(ProptestConfig { cases: 4, ..ProptestConfig::default() })]

    #[test]
    fn tiles_of_the_real_relu3_1_pair_equal_the_whole_image(
        h in 6usize..48, w in 6usize..48, tile in 3usize..32, seed in any::<u64>(), fullres in any::<bool>(),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let enc: Encoder = Encoder::from_checkpoint(&shared_path(
            "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
        )).unwrap().with_resolution(res);
        let dec: Decoder = Decoder::from_checkpoint(&shared_path(
            "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
        )).unwrap().with_resolution(res);
        check_networks(&enc, &dec, &image::<f32>(seed, h, w), tile, EXACT)?;
    }

    #[test]
    fn tiles_of_the_compressed_relu4_1_pair_equal_the_whole_image(
        h in 16usize..48, w in 16usize..48, tile in 3usize..32, seed in any::<u64>(), fullres in any::<bool>(),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let enc: Encoder = Encoder::from_checkpoint(&shared_path(
            "weights/compressed-16x-relu4_1/4SE.pth",
        )).unwrap().with_resolution(res);
        let dec: Decoder = Decoder::from_checkpoint(&shared_path(
            "weights/compressed-16x-relu4_1/4SD.pth",
        )).unwrap().with_resolution(res);
        check_networks(&enc, &dec, &image::<f32>(seed, h, w), tile, EXACT)?;
    }

    /// One region computed from only the input it names equals the same region of the whole
    /// output, and the input region grows by no more than the halo the planner assumes.
    #[test]
    fn a_region_needs_only_its_input_region(
        h in 16usize..40, w in 16usize..40, seed in any::<u64>(), fullres in any::<bool>(),
        corner in (0.0f64..1.0, 0.0f64..1.0, 0.0f64..1.0, 0.0f64..1.0),
    ) {
        let res = if fullres { Resolution::Fullres } else { Resolution::Standard };
        let (enc, dec) = networks_f64(res);
        let x = image::<f64>(seed, h, w);
        let feats = enc.forward(x.view()).unwrap();
        let t = &feats[feats.len() - 1];
        let (th, tw) = (t.dim().2, t.dim().3);
        let (oh, ow) = dec.output_size((th, tw));
        let at = |f: f64, n: usize| ((f * n as f64) as usize).min(n - 1);
        let (ya, yb) = (at(corner.0, oh), at(corner.1, oh));
        let (xa, xb) = (at(corner.2, ow), at(corner.3, ow));
        let out = Region::new(ya.min(yb), xa.min(xb), ya.max(yb) + 1, xa.max(xb) + 1);
        let need = dec.input_region((th, tw), out).unwrap();
        let part = t.slice(s![.., .., need.y0..need.y1, need.x0..need.x1]).to_owned();
        let y = dec.forward_region(part.view(), (th, tw), out).unwrap();
        let whole = dec.forward(t.view()).unwrap();
        let expected = whole.slice(s![.., .., out.y0..out.y1, out.x0..out.x1]).to_owned();
        prop_assert_eq!(&y, &expected);
        let (_, halo) = dec.tile_cost((th, tw));
        let grown = Region::new(
            out.y0.saturating_sub(halo), out.x0.saturating_sub(halo),
            out.y1 + halo, out.x1 + halo,
        );
        let scale = oh / th;
        let need_out = Region::new(need.y0 * scale, need.x0 * scale, need.y1 * scale, need.x1 * scale);
        prop_assert!(grown.contains(&need_out), "{need_out} outside {grown}");
    }
}

#[test]
fn a_bad_region_or_tile_input_is_an_error() {
    let (enc, dec) = networks_f64(Resolution::Fullres);
    let x = image::<f64>(1, 32, 30);
    let t = enc.forward(x.view()).unwrap().pop().unwrap();
    let e = dec
        .forward_region(t.view(), (32, 30), Region::new(0, 0, 33, 30))
        .unwrap_err();
    assert!(e.to_string().contains("not inside the 30x32 output"), "{e}");
    let e = dec
        .forward_region(t.view(), (32, 30), Region::new(0, 0, 4, 4))
        .unwrap_err();
    assert!(e.to_string().contains("input tile is 30x32"), "{e}");
    let e = enc.forward_tiled(x.view(), 5, 4).unwrap_err();
    assert!(e.to_string().contains("level 5"), "{e}");
    assert_eq!(grid(12, 10, 4).len(), 9);
}
