//! Channel statistics accumulated tile by tile (`ChannelMoments`) against the statistics of the
//! whole map (`channel_stats`), and the style loss from them.
//!
//! Tolerance 1e-12 relative in `f64`: both sum the same values in `f64`, in another order and
//! with the pairwise merge's few extra operations per tile, a rounding of order 1e-16 per
//! operation over at most a few thousand additions here.

use ndarray::{s, Array2, Array4};
use proptest::prelude::*;
use style::{channel_stats, style_loss, style_loss_of_stats, ChannelMoments, ChannelStats};

const TOL: f64 = 1e-12;

fn rel(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

proptest! {
    #[test]
    fn statistics_of_the_tiles_equal_those_of_the_whole_map(
        n in 1usize..3, c in 1usize..5, h in 2usize..24, w in 1usize..24,
        tile in 1usize..9, seed in any::<u64>(), offset in -50.0f64..50.0,
    ) {
        let mut state = seed;
        let x = Array4::from_shape_simple_fn((n, c, h, w), || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            offset + (state >> 11) as f64 / (1u64 << 53) as f64
        });
        let mut m = ChannelMoments::new(n, c);
        for y0 in (0..h).step_by(tile) {
            for x0 in (0..w).step_by(tile) {
                let t = x.slice(s![.., .., y0..(y0 + tile).min(h), x0..(x0 + tile).min(w)]).to_owned();
                m.add(&t).unwrap();
            }
        }
        let whole = channel_stats(&x).unwrap();
        let tiled: ChannelStats<f64> = m.stats().unwrap();
        prop_assert!(rel(&tiled.mean, &whole.mean) <= TOL);
        prop_assert!(rel(&tiled.std, &whole.std) <= TOL);
        let style = vec![ChannelStats::new(
            Array2::from_elem((1, c), offset + 0.3),
            Array2::from_elem((1, c), 0.2),
        ).unwrap()];
        let a = style_loss(std::slice::from_ref(&x), &style).unwrap();
        let b = style_loss_of_stats(&[tiled], &style).unwrap();
        prop_assert!((a - b).abs() <= TOL * a.abs().max(1e-300), "{a} {b}");
    }
}

#[test]
fn too_few_pixels_or_a_wrong_shape_is_an_error() {
    let mut m = ChannelMoments::new(1, 2);
    assert!(m.stats::<f32>().is_err());
    assert!(m.add(&Array4::<f32>::zeros((1, 3, 2, 2))).is_err());
    m.add(&Array4::<f32>::zeros((1, 2, 1, 1))).unwrap();
    assert!(m.stats::<f32>().is_err());
    m.add(&Array4::<f32>::ones((1, 2, 1, 1))).unwrap();
    let s: ChannelStats<f64> = m.stats().unwrap();
    assert_eq!(s.mean[[0, 1]], 0.5);
}
