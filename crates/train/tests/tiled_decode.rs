//! A stylized frame decoded in tiles (`SceneBundle::decode_in_tiles`) equals the frame decoded
//! whole, bit for bit, for any budget, in both variants and for frame sizes that are not
//! multiples of the tiles (standard: the decoded image is larger than the frame and cropped).
//!
//! No tolerance: lifting and the style transform act on each pixel alone, and the decoder's tiles
//! equal the whole image's (`nets::tiled`, property-tested there).
//!
//! A bundle of the design ablation (`FeatureNorm::AfterRaster`) normalises every tile with the
//! statistics of the whole view (`SceneBundle::view_stats`), which do not depend on the budget
//! either; those statistics equal `channel_stats` of the whole lifted map up to the `f64`
//! rounding of another summation order, which the cast to `f32` leaves at most one `f32` ulp
//! (1.2e-7 relative) apart: checked to 1e-6.

mod common;

use common::small_bundle;
use ndarray::{s, Array2};
use proptest::prelude::*;
use runtime::bundle::feature_size;
use style::ChannelStats;
use train::{FeatureNorm, Variant};

/// Lift, transform and decode the whole feature map at once, then crop: the definition the
/// tiles must reproduce.
fn whole(
    bundle: &runtime::SceneBundle,
    features: &ndarray::Array4<f32>,
    stats: &ChannelStats<f32>,
    width: u32,
    height: u32,
) -> ndarray::Array4<f32> {
    let mut lifted = bundle.lifter.forward(features.view()).unwrap();
    if let Some(v) = bundle.view_stats(features).unwrap() {
        lifted = style::normalize(&lifted, &v).unwrap();
    }
    let t = style::style_transform(&lifted, stats).unwrap();
    let image = bundle.decoder.forward(t.view()).unwrap();
    image
        .slice(s![.., .., ..height as usize, ..width as usize])
        .to_owned()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 8, ..ProptestConfig::default() })]

    #[test]
    fn a_frame_decoded_in_tiles_equals_the_frame_decoded_whole(
        width in 20u32..72, height in 20u32..72, budget_kib in 16u64..4096,
        fullres in any::<bool>(), camera in 0usize..4, shift in -0.5f32..0.5,
        after in any::<bool>(),
    ) {
        let variant = if fullres { Variant::Fullres } else { Variant::Standard };
        let mut bundle = small_bundle(5);
        if after {
            bundle.info.normalize = FeatureNorm::AfterRaster;
        }
        let decoder = bundle.decoder.clone();
        let bundle = bundle.with_decoder(decoder, variant).unwrap();
        let cam = bundle.cameras()[camera].resized(width, height);
        let features = bundle.render_features(&cam).unwrap();
        let fs = feature_size(&bundle.encoder, variant, width, height);
        prop_assert_eq!(features.dim(), (1, 5, fs.1 as usize, fs.0 as usize));
        let c = bundle.lifter.out_channels();
        let stats = ChannelStats::new(
            Array2::from_shape_fn((1, c), |(_, j)| shift + 0.1 * j as f32),
            Array2::from_shape_fn((1, c), |(_, j)| 0.5 + 0.05 * (j % 7) as f32),
        ).unwrap();
        let budget = budget_kib << 10;
        let (tiled, _) = bundle.decode_in_tiles(&features, &stats, width, height, budget).unwrap();
        let side = bundle.decode_tile_side(
            (features.dim().2, features.dim().3), width, height, budget,
        );
        // The smallest budgets leave room for the smallest tiles only: several per frame.
        if budget_kib < 64 {
            prop_assert!(side < width.max(height) as usize);
        }
        prop_assert!(side >= 16);
        prop_assert_eq!(tiled, whole(&bundle, &features, &stats, width, height));
        let view = bundle.view_stats(&features).unwrap();
        prop_assert_eq!(view.is_some(), after);
        if let Some(v) = view {
            let lifted = bundle.lifter.forward(features.view()).unwrap();
            let direct = style::channel_stats(&lifted).unwrap();
            for (a, b) in v.mean.iter().chain(&v.std).zip(direct.mean.iter().chain(&direct.std)) {
                prop_assert!((a - b).abs() <= 1e-6 * (1.0 + b.abs()), "{a} vs {b}");
            }
        }
    }
}
