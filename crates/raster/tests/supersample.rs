//! Box supersampling (`raster::supersample`): the mean is the adjoint of its backward, keeps
//! constants, is the identity at factor 1, averages exactly the block each coarse pixel covers
//! when the camera is scaled by the factor, does not depend on the thread count, and refuses bad
//! input.

use std::borrow::Cow;

use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DMat4;
use proptest::prelude::*;

use raster::supersample::{box_mean, box_mean_backward};
use raster::{render, Channels, RasterError, RenderOptions};

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// `<box_mean(x), g> = <x, box_mean_backward(g)>` for any image and cotangent.
    #[test]
    fn the_backward_is_the_adjoint_of_the_mean(
        width in 1usize..7, height in 1usize..6, channels in 1usize..5, s in 1usize..5,
        seed in any::<u64>(),
    ) {
        let mut state = seed | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let x: Vec<f64> = (0..width * s * height * s * channels).map(|_| next()).collect();
        let g: Vec<f64> = (0..width * height * channels).map(|_| next()).collect();
        let m = box_mean(&x, width, height, channels, s).unwrap();
        let b = box_mean_backward(&g, width, height, channels, s).unwrap();
        let lhs: f64 = m.iter().zip(&g).map(|(a, b)| a * b).sum();
        let rhs: f64 = x.iter().zip(b.iter()).map(|(a, b)| a * b).sum();
        // Two sums of at most a few thousand products of terms below 1 in f64.
        prop_assert!((lhs - rhs).abs() <= 1e-12 * (1.0 + lhs.abs()), "{lhs} vs {rhs}");
    }

    /// A constant image stays that constant, and factor 1 is the identity bit for bit.
    #[test]
    fn constants_stay_and_factor_one_is_the_identity(
        width in 1usize..6, height in 1usize..6, channels in 1usize..4, k in 0u32..3,
        value in -10.0f32..10.0,
    ) {
        let s = 1usize << k;
        let fine = vec![value; width * s * height * s * channels];
        let m = box_mean(&fine, width, height, channels, s).unwrap();
        // s^2 additions in f32, each rounding by at most half an ulp of the partial sum (at
        // most s^2 |value|), then an exact scaling by a power of two.
        let tol = (s * s) as f32 * f32::EPSILON * value.abs();
        prop_assert!(m.iter().all(|&v| (v - value).abs() <= tol), "{m:?} vs {value}");
        let img: Vec<f32> = (0..width * height * channels).map(|i| i as f32 * 0.37).collect();
        // At factor 1 both borrow their input: the default render is not copied.
        let same = box_mean(&img, width, height, channels, 1).unwrap();
        prop_assert!(matches!(same, Cow::Borrowed(b) if std::ptr::eq(b, img.as_slice())));
        let same = box_mean_backward(&img, width, height, channels, 1).unwrap();
        prop_assert!(matches!(same, Cow::Borrowed(b) if std::ptr::eq(b, img.as_slice())));
    }
}

/// Rendering at `s` times the size with the camera scaled by `s`, then averaging, weighs a
/// Gaussian far smaller than a coarse pixel by the area it covers. The direct coarse render
/// instead widens it by the rasterizer's fixed low-pass (0.3 pixel^2, in coarse pixels) at full
/// opacity, so it counts as if it covered most of a coarse pixel.
#[test]
fn the_mean_of_a_finer_render_weighs_a_small_gaussian_by_its_area() {
    let intrinsics = Intrinsics {
        fx: 8.0,
        fy: 8.0,
        cx: 4.0,
        cy: 4.0,
        width: 8,
        height: 8,
    };
    let coarse = Camera::new(intrinsics, DMat4::IDENTITY);
    let s = 8usize;
    let fine = coarse.resized(8 * s as u32, 8 * s as u32);
    // A tiny Gaussian (about 0.1 coarse pixels across) at the corner shared by four pixels.
    let scene = FeatureGaussians::<f32> {
        means: vec![[0.0, 0.0, 5.0]],
        log_scales: vec![[-4.5, -4.5, -4.5]],
        quats: vec![[1.0, 0.0, 0.0, 0.0]],
        opacity_logits: vec![4.0],
        sh_degree: 0,
        sh: vec![[1.0, 1.0, 1.0]],
        ..Default::default()
    }
    .with_features(1, 1.0);
    let opts = RenderOptions::new(Channels::Features, vec![0.0]);
    let direct = render(&coarse, &scene, &opts).unwrap().raster.image;
    let fine_img = render(&fine, &scene, &opts).unwrap().raster.image;
    let mean = box_mean(&fine_img, 8, 8, 1, s).unwrap();
    let direct_total: f32 = direct.iter().sum();
    let mean_total: f32 = mean.iter().sum();
    // The four pixels around the corner share it.
    for (x, y) in [(3, 3), (4, 3), (3, 4), (4, 4)] {
        assert!(mean[y * 8 + x] > 0.0, "pixel ({x}, {y}) sees nothing");
    }
    // The mean conserves the fine render's total weight (s^2 fine pixels per coarse one).
    let fine_total: f32 = fine_img.iter().sum();
    assert!((mean_total * (s * s) as f32 - fine_total).abs() <= 1e-4 * fine_total);
    assert!(
        direct_total > 10.0 * mean_total,
        "direct {direct_total}, mean of the finer render {mean_total}"
    );
}

#[test]
fn the_result_does_not_depend_on_the_thread_count() {
    let (w, h, c, s) = (13, 9, 5, 4);
    let fine: Vec<f32> = (0..w * s * h * s * c)
        .map(|i| ((i * 7919) % 1000) as f32 / 997.0 - 0.4)
        .collect();
    let grad: Vec<f32> = (0..w * h * c).map(|i| (i % 17) as f32 * 0.1).collect();
    let run = |t: usize| {
        pool(t).install(|| {
            (
                box_mean(&fine, w, h, c, s).unwrap(),
                box_mean_backward(&grad, w, h, c, s).unwrap(),
            )
        })
    };
    let one = run(1);
    for t in [2, 3, 8] {
        assert_eq!(run(t), one, "{t} threads");
    }
}

#[test]
fn bad_sizes_and_factors_are_refused() {
    let img = vec![0.0f32; 2 * 2 * 3];
    assert_eq!(
        box_mean(&img, 2, 2, 3, 0).unwrap_err(),
        RasterError::Supersample(0)
    );
    assert!(matches!(
        box_mean(&img, 2, 2, 3, 2).unwrap_err(),
        RasterError::Length {
            array: "fine image",
            actual: 12,
            expected: 48
        }
    ));
    assert!(matches!(
        box_mean_backward(&img, 1, 1, 3, 2).unwrap_err(),
        RasterError::Length {
            array: "mean cotangent",
            actual: 12,
            expected: 3
        }
    ));
    assert!(box_mean_backward(&img, 2, 2, 3, 0).is_err());
}
