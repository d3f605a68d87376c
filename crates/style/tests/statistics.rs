//! Channel statistics (`channel_stats`, `masked_channel_stats`) and the mean squared and
//! absolute errors (`mse`, `l1`) against sequential references written here, and the alignment
//! target from known statistics against the one that computes them.
//!
//! Tolerance 1e-12 relative in `f64`: the library sums the same values in `f64` in another
//! fixed order (interleaved partial sums), a rounding of order 1e-16 per addition over at most
//! a few thousand additions here.

use ndarray::{Array2, Array4};
use proptest::prelude::*;
use style::{channel_stats, l1, masked_channel_stats, mse, FeatureNorm, STATS_EPS};

const TOL: f64 = 1e-12;

/// Mean and std of the selected values, one running sum per pass, in index order.
fn reference(values: &[f64]) -> (f64, f64) {
    let m = values.len() as f64;
    let mut sum = 0.0;
    for v in values {
        sum += v;
    }
    let mean = sum / m;
    let mut ss = 0.0;
    for v in values {
        ss += (v - mean) * (v - mean);
    }
    (mean, (ss / (m - 1.0) + STATS_EPS).sqrt())
}

fn close(a: f64, b: f64, scale: f64) -> bool {
    (a - b).abs() <= TOL * scale
}

fn random_map(n: usize, c: usize, h: usize, w: usize, seed: u64, offset: f64) -> Array4<f64> {
    let mut state = seed;
    Array4::from_shape_simple_fn((n, c, h, w), || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        offset + (state >> 11) as f64 / (1u64 << 53) as f64
    })
}

proptest! {
    #[test]
    fn statistics_match_a_sequential_two_pass_reference(
        n in 1usize..3, c in 1usize..4, h in 1usize..20, w in 1usize..20,
        seed in any::<u64>(), offset in -50.0f64..50.0, mask_seed in any::<u64>(),
    ) {
        prop_assume!(h * w >= 2);
        let x = random_map(n, c, h, w, seed, offset);
        // About half the pixels, at least two.
        let mut mask = Array2::from_shape_fn((h, w), |(y, xx)| {
            (mask_seed >> ((y * w + xx) % 64)) & 1 == 1
        });
        mask[[0, 0]] = true;
        let last = (h - 1, w - 1);
        mask[[last.0, last.1]] = true;
        if h * w == 2 || last == (0, 0) {
            mask.fill(true);
        }
        let whole = channel_stats(&x).unwrap();
        let masked = masked_channel_stats(&x, mask.view()).unwrap();
        let scale = offset.abs() + 1.0;
        for i in 0..n {
            for j in 0..c {
                let plane: Vec<f64> = x.slice(ndarray::s![i, j, .., ..]).iter().copied().collect();
                let (mean, std) = reference(&plane);
                prop_assert!(close(whole.mean[[i, j]], mean, scale));
                prop_assert!(close(whole.std[[i, j]], std, 1.0));
                let selected: Vec<f64> = plane
                    .iter()
                    .zip(mask.iter())
                    .filter(|(_, &m)| m)
                    .map(|(&v, _)| v)
                    .collect();
                let (mean, std) = reference(&selected);
                prop_assert!(close(masked.mean[[i, j]], mean, scale));
                prop_assert!(close(masked.std[[i, j]], std, 1.0));
            }
        }
    }

    #[test]
    fn mean_errors_match_a_sequential_reference(
        n in 1usize..3, c in 1usize..4, h in 1usize..20, w in 1usize..20,
        seed in any::<u64>(), offset in -5.0f64..5.0,
    ) {
        let a = random_map(n, c, h, w, seed, offset);
        let b = random_map(n, c, h, w, seed ^ 0x9e37_79b9_7f4a_7c15, 0.0);
        let (mut sq, mut abs) = (0.0, 0.0);
        for (x, y) in a.iter().zip(b.iter()) {
            sq += (x - y) * (x - y);
            abs += (x - y).abs();
        }
        let k = a.len() as f64;
        let scale = (offset.abs() + 1.0).powi(2);
        prop_assert!(close(mse(&a, &b).unwrap(), sq / k, scale));
        prop_assert!(close(l1(&a, &b).unwrap(), abs / k, scale));
    }

    #[test]
    fn the_alignment_target_from_known_statistics_is_the_computed_one(
        c in 1usize..5, h in 1usize..12, w in 2usize..12, seed in any::<u64>(),
    ) {
        let x = random_map(1, c, h, w, seed, 0.5).mapv(|v| v as f32);
        let stats = channel_stats(&x).unwrap();
        for norm in [FeatureNorm::BeforeRaster, FeatureNorm::AfterRaster] {
            let a = norm.align_target(&x).unwrap();
            let b = norm.align_target_with_stats(x.clone(), &stats).unwrap();
            prop_assert_eq!(a.shape(), b.shape());
            prop_assert!(a.iter().zip(b.iter()).all(|(p, q)| p.to_bits() == q.to_bits()));
        }
    }
}
