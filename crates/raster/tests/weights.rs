//! An image's blend weights (`raster::weights`) on random scenes of any size, partial tiles and
//! channel count: applied to the channel values they give the forward pass's image bit for bit
//! (its alpha too), their transpose is the backward pass's channel gradient up to the order of
//! the sums and satisfies the adjoint identity, and they do not depend on the thread count.

mod common;

use common::{cast, cotangents, random_scene, Rng, Scene2d};
use proptest::prelude::*;
use raster::{blend_weights, rasterize, rasterize_backward, Cotangents};

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// The forward image of the `f32` scene against the weights applied to its channels.
fn same_image_as_forward(s: &Scene2d) {
    let scene = s.cast::<f32>();
    let splats = scene.splats();
    let out = rasterize(&splats, s.width, s.height, &scene.background).unwrap();
    let w = blend_weights(&splats, &scene.tile_bins()).unwrap();
    let image = w
        .apply(&scene.channels, s.channel_count, &scene.background)
        .unwrap();
    assert_eq!(bits(&image), bits(&out.image));
    let alpha: Vec<f32> = w.transmittance.iter().map(|t| 1.0 - t).collect();
    assert_eq!(bits(&alpha), bits(&out.alpha));
    let counts: Vec<u32> = w.offsets.windows(2).map(|o| (o[1] - o[0]) as u32).collect();
    assert_eq!(counts, out.blended);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn applied_weights_are_the_forward_image(
        seed in any::<u64>(),
        n in 1usize..300,
        width in 1u32..70,
        height in 1u32..70,
        d in 1usize..6,
    ) {
        same_image_as_forward(&random_scene(&mut Rng(seed), n, width, height, d));
    }

    /// In `f64`, `W^T v` is the backward pass's channel gradient (relative 1e-12: the two sum
    /// the same products in different orders, tile records against row-major pixels, and in
    /// f64 a sum of a few hundred terms of size at most 1 differs by far less), and
    /// `<v, W c> = <W^T v, c>` to the same tolerance.
    #[test]
    fn the_transpose_is_the_channel_gradient(
        seed in any::<u64>(),
        n in 1usize..200,
        width in 1u32..50,
        height in 1u32..50,
        d in 1usize..5,
    ) {
        let s = random_scene(&mut Rng(seed), n, width, height, d);
        let splats = s.splats();
        let out = rasterize(&splats, s.width, s.height, &s.background).unwrap();
        let px = (s.width * s.height) as usize;
        let (vi, _, _) = cotangents(&mut Rng(seed ^ 1), px, d, 1.0);
        let cot = Cotangents { image: &vi, alpha: None, depth: None };
        let g = rasterize_backward(&splats, &out.bins, &s.background, &cot).unwrap();
        let w = blend_weights(&splats, &s.tile_bins()).unwrap();
        let t = w.apply_transpose(&vi, d, n).unwrap();
        for (a, b) in t.iter().zip(&g.channels) {
            prop_assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} vs {b}");
        }
        let zero = vec![0.0; d];
        let wc = w.apply(&s.channels, d, &zero).unwrap();
        let lhs: f64 = vi.iter().zip(&wc).map(|(a, b)| a * b).sum();
        let rhs: f64 = t.iter().zip(&s.channels).map(|(a, b)| a * b).sum();
        prop_assert!((lhs - rhs).abs() <= 1e-12 * (1.0 + lhs.abs()), "{lhs} vs {rhs}");
    }
}

#[test]
fn weights_do_not_depend_on_the_thread_count() {
    let s = random_scene(&mut Rng(7), 2000, 150, 97, 3).cast::<f32>();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| blend_weights(&s.splats(), &s.tile_bins()).unwrap())
    };
    let one = run(1);
    assert!(one.pairs() > 0);
    for t in [2, 3, 5] {
        let other = run(t);
        assert_eq!(other.offsets, one.offsets, "{t} threads");
        assert_eq!(other.gaussians, one.gaussians, "{t} threads");
        assert_eq!(bits(&other.weights), bits(&one.weights), "{t} threads");
        let (vi, _, _) = cotangents(&mut Rng(3), 150 * 97, 3, 1.0);
        let vi = cast::<f32>(&vi);
        assert_eq!(
            bits(&other.apply_transpose(&vi, 3, 2000).unwrap()),
            bits(&one.apply_transpose(&vi, 3, 2000).unwrap())
        );
    }
}

#[test]
fn mismatched_inputs_are_refused() {
    let s = random_scene(&mut Rng(11), 50, 20, 20, 2);
    let w = blend_weights(&s.splats(), &s.tile_bins()).unwrap();
    assert!(w.apply(&s.channels[..10], 2, &[0.0; 2]).is_err());
    assert!(w.apply(&s.channels, 2, &[0.0; 3]).is_err());
    assert!(w.apply_transpose(&[0.0; 7], 2, 50).is_err());
    assert!(w.pairs() > 0);
    assert!(w.apply_transpose(&[0.0; 800], 2, 3).is_err());
    let other = random_scene(&mut Rng(12), 40, 20, 20, 2);
    assert!(blend_weights(&s.splats(), &other.tile_bins()).is_err());
}
