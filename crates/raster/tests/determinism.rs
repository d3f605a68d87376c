//! Bit-identical results for any number of threads and any gradient-buffer budget, and clear
//! errors for inconsistent inputs.

mod common;

use common::{cast, cotangents, random_scene, Rng, Scene2d};
use gaussian::Real;
use raster::{
    rasterize, rasterize_backward, rasterize_backward_with_budget, Cotangents, RasterError,
    Rasterized, SplatGrads,
};

/// A scene with a few thousand overlapping Gaussians over a 150x100 image.
fn busy_scene() -> Scene2d {
    random_scene(&mut Rng(7), 3000, 150, 100, 5)
}

fn bits<T: Real>(v: &[T]) -> Vec<u64> {
    v.iter().map(|x| x.to_f64_exact().to_bits()).collect()
}

fn run<T: Real>(s: &Scene2d, budget: usize) -> (Rasterized<T>, SplatGrads<T>) {
    let scene = s.cast::<T>();
    let (splats, bg) = (scene.splats(), &scene.background);
    let out = rasterize(&splats, s.width, s.height, bg).unwrap();
    let px = (s.width * s.height) as usize;
    let (vi, va, vd) = cotangents(&mut Rng(11), px, s.channel_count, 1.0);
    let (vi, va, vd) = (cast::<T>(&vi), cast::<T>(&va), cast::<T>(&vd));
    let cot = Cotangents {
        image: &vi,
        alpha: Some(&va),
        depth: Some(&vd),
    };
    let g = rasterize_backward_with_budget(&splats, &out.bins, bg, &cot, budget).unwrap();
    (out, g)
}

fn fingerprint<T: Real>((out, g): &(Rasterized<T>, SplatGrads<T>)) -> Vec<Vec<u64>> {
    vec![
        bits(&out.image),
        bits(&out.alpha),
        bits(&out.depth),
        bits(&out.normalized_depth),
        out.blended.iter().map(|&c| c as u64).collect(),
        bits(&g.means2d.concat()),
        bits(&g.conics.concat()),
        bits(&g.opacities),
        bits(&g.depths),
        bits(&g.channels),
        bits(&g.background),
    ]
}

fn in_pool<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

fn check_thread_independence<T: Real>() {
    let s = busy_scene();
    let budget = raster::DEFAULT_GRADIENT_BUFFER_VALUES;
    let one = in_pool(1, || run::<T>(&s, budget));
    let two = in_pool(2, || run::<T>(&s, budget));
    let three = in_pool(3, || run::<T>(&s, budget));
    assert!(one.0.blended_pairs() > 100_000, "the scene is too sparse");
    assert_eq!(fingerprint(&one), fingerprint(&two), "1 vs 2 threads");
    assert_eq!(fingerprint(&one), fingerprint(&three), "1 vs 3 threads");
}

#[test]
fn results_are_bit_identical_for_1_2_and_3_threads_f64() {
    check_thread_independence::<f64>();
}

#[test]
fn results_are_bit_identical_for_1_2_and_3_threads_f32() {
    check_thread_independence::<f32>();
}

/// A budget smaller than one tile's records forces one batch per tile (each batch visiting only
/// the Gaussians it has records of, over more than one gather chunk of Gaussians); the sums per
/// Gaussian still run in the same order, so the gradients are bit-identical, in `f64` (the
/// scalar loops) and in `f32` (the lane kernels where the machine has them).
#[test]
fn gradient_budget_does_not_change_results() {
    fn check<T: Real>() {
        let s = busy_scene();
        let big = run::<T>(&s, usize::MAX);
        let small = in_pool(2, || run::<T>(&s, 1000));
        let medium = in_pool(3, || run::<T>(&s, 20_000));
        let default = run::<T>(&s, raster::DEFAULT_GRADIENT_BUFFER_VALUES);
        assert_eq!(fingerprint(&big), fingerprint(&small));
        assert_eq!(fingerprint(&big), fingerprint(&medium));
        assert_eq!(fingerprint(&big), fingerprint(&default));
    }
    check::<f64>();
    check::<f32>();
}

#[test]
fn inconsistent_inputs_are_errors_naming_the_array() {
    let s = random_scene(&mut Rng(3), 10, 40, 30, 3);
    let mut splats = s.splats();
    let short = &s.opacities[..9];
    splats.opacities = short;
    let err = rasterize(&splats, 40, 30, &s.background).unwrap_err();
    assert_eq!(
        err,
        RasterError::Length {
            array: "opacities",
            actual: 9,
            expected: 10
        }
    );
    assert!(err.to_string().contains("opacities"));

    let splats = s.splats();
    let err = rasterize(&splats, 40, 30, &s.background[..2]).unwrap_err();
    assert!(matches!(
        err,
        RasterError::Length {
            array: "background",
            ..
        }
    ));
    let err = rasterize(&splats, 0, 30, &s.background).unwrap_err();
    assert!(matches!(err, RasterError::EmptyImage { .. }));

    let out = rasterize(&splats, 40, 30, &s.background).unwrap();
    let v = vec![0.0; 40 * 30 * 3 - 1];
    let cot = Cotangents {
        image: &v,
        alpha: None,
        depth: None,
    };
    let err = rasterize_backward(&splats, &out.bins, &s.background, &cot).unwrap_err();
    assert!(matches!(
        err,
        RasterError::Length {
            array: "v_image",
            ..
        }
    ));
    let fewer = random_scene(&mut Rng(3), 9, 40, 30, 3);
    let other = rasterize(&fewer.splats(), 40, 30, &fewer.background).unwrap();
    let v = vec![0.0; 40 * 30 * 3];
    let cot = Cotangents {
        image: &v,
        alpha: None,
        depth: None,
    };
    let err = rasterize_backward(&splats, &other.bins, &s.background, &cot).unwrap_err();
    assert!(matches!(err, RasterError::BinsMismatch { .. }));
}

/// No Gaussians, or no channels: the image is the background and alpha is zero; gradients are
/// empty or zero.
#[test]
fn degenerate_inputs_render_the_background() {
    let empty = random_scene(&mut Rng(1), 0, 20, 18, 2);
    let out = rasterize(&empty.splats(), 20, 18, &empty.background).unwrap();
    for p in out.image.chunks_exact(2) {
        assert_eq!(p, &empty.background[..]);
    }
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    let no_channels = random_scene(&mut Rng(2), 30, 20, 18, 0);
    let out = rasterize(&no_channels.splats(), 20, 18, &[]).unwrap();
    assert!(out.image.is_empty());
    assert!(out.alpha.iter().any(|&a| a > 0.0));
    let va = vec![1.0; 20 * 18];
    let g = rasterize_backward(
        &no_channels.splats(),
        &out.bins,
        &[],
        &Cotangents {
            image: &[],
            alpha: Some(&va),
            depth: None,
        },
    )
    .unwrap();
    assert!(g.opacities.iter().any(|&o| o > 0.0));
}
