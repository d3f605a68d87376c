//! Every tile kernel gives the same bits: the `f32` lane kernels, at every instruction set this
//! machine can run, against the scalar reference loops, forward and backward, on random scenes
//! (any size, partial tiles, any channel count), on saturated scenes (alpha clamp and
//! transmittance stop everywhere), on scenes of Gaussians a few pixels across, and on hostile
//! values (opacities above 1, degenerate and non-finite conics and channels).

mod common;

use common::{cast, cotangents, ellipse, random_scene, Rng, Scene2d};
use proptest::prelude::*;
use raster::{rasterize_backward_with, rasterize_binned_with, Cotangents, Isa, Kernel, TileBins};

/// Everything a kernel computes, as bits, every NaN as the one canonical NaN (vector code may
/// propagate another NaN operand than scalar code; the payload carries no meaning).
///
/// The backward pass takes the forward pass's bins (with the row lists it kept) or, with
/// `fresh_bins`, bins built anew (so it builds the row lists itself).
fn fingerprint(
    s: &Scene2d,
    kernel: Kernel,
    cot_seed: u64,
    with_aux: bool,
    fresh_bins: bool,
) -> Vec<Vec<u32>> {
    let scene = s.cast::<f32>();
    let (splats, bg) = (scene.splats(), &scene.background);
    let bins = scene.tile_bins();
    let out = rasterize_binned_with(&splats, bins.clone(), bg, kernel).unwrap();
    let backward_bins = if fresh_bins { &bins } else { &out.bins };
    let px = (s.width * s.height) as usize;
    let (vi, va, vd) = cotangents(&mut Rng(cot_seed), px, s.channel_count, 1.0);
    let (vi, va, vd) = (cast::<f32>(&vi), cast::<f32>(&va), cast::<f32>(&vd));
    let cot = Cotangents {
        image: &vi,
        alpha: with_aux.then_some(&va[..]),
        depth: with_aux.then_some(&vd[..]),
    };
    // A small record budget so that several batches run.
    let g = rasterize_backward_with(&splats, backward_bins, bg, &cot, 4096, kernel).unwrap();
    let bits = |v: &[f32]| {
        v.iter()
            .map(|x| if x.is_nan() { f32::NAN } else { *x }.to_bits())
            .collect::<Vec<u32>>()
    };
    vec![
        bits(&out.image),
        bits(&out.alpha),
        bits(&out.depth),
        bits(&out.normalized_depth),
        out.blended.clone(),
        bits(g.means2d.as_flattened()),
        bits(g.conics.as_flattened()),
        bits(&g.opacities),
        bits(&g.depths),
        bits(&g.channels),
        bits(&g.background),
    ]
}

const PARTS: [&str; 11] = [
    "image",
    "alpha",
    "depth",
    "normalized depth",
    "blend counts",
    "means2d grad",
    "conics grad",
    "opacities grad",
    "depths grad",
    "channels grad",
    "background grad",
];

/// Asserts that every lane kernel this machine can run matches the scalar loops bit for bit,
/// with and without the row lists kept by the forward pass.
fn check_all_kernels(s: &Scene2d, cot_seed: u64, with_aux: bool) {
    let reference = fingerprint(s, Kernel::Scalar, cot_seed, with_aux, true);
    let runs = Isa::available()
        .into_iter()
        .flat_map(|isa| [(Kernel::Lanes(isa), false), (Kernel::Lanes(isa), true)])
        .chain([(Kernel::Scalar, false)]);
    for (kernel, fresh) in runs {
        let got = fingerprint(s, kernel, cot_seed, with_aux, fresh);
        let isa = kernel;
        for ((r, g), part) in reference.iter().zip(&got).zip(PARTS) {
            if let Some(i) = r.iter().zip(g).position(|(a, b)| a != b) {
                panic!(
                    "{} kernel (fresh bins: {fresh}) differs from scalar in {part} at {i}: \
                     {:e} vs {:e}",
                    isa.name(),
                    f32::from_bits(g[i]),
                    f32::from_bits(r[i]),
                );
            }
        }
    }
}

/// Opaque Gaussians: most pixels clamp alphas and stop on the transmittance threshold.
fn saturate(s: &mut Scene2d, rng: &mut Rng) {
    for o in &mut s.opacities {
        *o = rng.uniform(0.95, 1.0);
    }
}

/// Gaussians a few pixels across (variances 0.2 to 3 px^2), as in trained scenes: most lanes of
/// the rows they reach are skipped, and many tiles stop early when they are opaque.
fn shrink(s: &mut Scene2d, rng: &mut Rng) {
    for (conic, radii) in s.conics.iter_mut().zip(&mut s.radii) {
        let (l1, l2) = (rng.uniform(0.2, 3.0), rng.uniform(0.2, 3.0));
        (*conic, *radii) = ellipse(l1, l2, rng.uniform(0.0, std::f64::consts::PI), 3.5);
    }
}

/// Values a fuzzer or a broken optimiser step could produce.
fn hostile(s: &mut Scene2d, rng: &mut Rng) {
    let n = s.means2d.len();
    let specials = [
        f64::NAN,
        f64::INFINITY,
        -f64::INFINITY,
        0.0,
        -0.0,
        1e30,
        -1e-30,
    ];
    for _ in 0..n.div_ceil(4) {
        let g = (rng.next_u64() % n as u64) as usize;
        let v = specials[(rng.next_u64() % specials.len() as u64) as usize];
        match rng.next_u64() % 5 {
            0 => s.opacities[g] = rng.uniform(1.0, 40.0),
            1 => s.conics[g][(rng.next_u64() % 3) as usize] = v,
            2 => s.conics[g] = [1.0, 0.999_999, 1.0],
            3 if s.channel_count > 0 => {
                s.channels[g * s.channel_count + (rng.next_u64() as usize % s.channel_count)] = v
            }
            _ => s.opacities[g] = v,
        }
    }
}

#[test]
fn this_machine_runs_the_portable_lanes_at_least() {
    assert!(Isa::available().contains(&Isa::Portable));
    assert!(Isa::best().is_available());
    assert_eq!(Kernel::parse("scalar"), Ok(Kernel::Scalar));
    assert_eq!(Kernel::parse("portable"), Ok(Kernel::Lanes(Isa::Portable)));
    assert!(Kernel::parse("sse9")
        .unwrap_err()
        .contains("unknown kernel"));
}

#[test]
fn a_busy_scene_with_partial_tiles_is_bit_identical() {
    let mut rng = Rng(3);
    let s = random_scene(&mut rng, 2500, 83, 45, 35);
    check_all_kernels(&s, 5, true);
}

#[test]
fn a_busy_scene_of_small_gaussians_is_bit_identical() {
    let mut rng = Rng(4);
    for (d, opaque) in [(3, false), (35, false), (3, true)] {
        let mut s = random_scene(&mut rng, 6000, 83, 45, d);
        shrink(&mut s, &mut rng);
        if opaque {
            saturate(&mut s, &mut rng);
        }
        check_all_kernels(&s, 6, true);
    }
}

/// A tile list of 12,000 Gaussians of which only six blend (the others' alphas stay below the
/// skip threshold), with runs of thousands of entries between them: the forward pass's kept
/// rows then hold steps along the list too long for a row's word (escaped ones), and the
/// backward pass's replay of them must still give the scalar loops' bits.
#[test]
fn long_runs_of_entries_that_blend_nowhere_are_bit_identical() {
    let mut rng = Rng(9);
    let n = 12_000;
    let mut s = random_scene(&mut rng, n, 16, 16, 3);
    let blending = [0, 1, 2, 6000, 6001, 11_999];
    for g in 0..n {
        s.means2d[g] = [rng.uniform(4.0, 12.0), rng.uniform(4.0, 12.0)];
        // Depth order is list order.
        s.depths[g] = 1.0 + g as f64 * 1e-3;
        s.opacities[g] = if blending.contains(&g) { 0.6 } else { 0.003 };
    }
    check_all_kernels(&s, 10, true);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn random_scenes_are_bit_identical(
        seed in any::<u64>(), n in 0usize..400, width in 1u32..70, height in 1u32..50,
        // Every channel count the lane kernels specialise (3, 32, 35, 64) and others.
        d in prop::sample::select(vec![0usize, 1, 3, 4, 9, 16, 32, 35, 64]),
        mode in 0u8..5, with_aux in any::<bool>(),
    ) {
        let mut rng = Rng(seed);
        let mut s = random_scene(&mut rng, n, width, height, d);
        match mode {
            1 => saturate(&mut s, &mut rng),
            2 => hostile(&mut s, &mut rng),
            3 => shrink(&mut s, &mut rng),
            4 => {
                shrink(&mut s, &mut rng);
                saturate(&mut s, &mut rng);
            }
            _ => {}
        }
        check_all_kernels(&s, seed ^ 0x5eed, with_aux);
    }
}

#[test]
fn a_forward_pass_ignores_row_lists_kept_for_other_gaussians() {
    // Bins kept by a forward pass of one scene, reused for a forward pass of the same means,
    // depths and radii with other conics and opacities: the second pass builds its own lists.
    let mut rng = Rng(17);
    let a = random_scene(&mut rng, 600, 50, 40, 3);
    let mut b = a.clone();
    for (o, c) in b.opacities.iter_mut().zip(&mut b.conics) {
        *o = (*o * 1.5).min(0.99);
        *c = [c[0] * 0.25, c[1] * 0.25, c[2] * 0.25];
    }
    let run = |s: &Scene2d, bins: Option<TileBins>| {
        let scene = s.cast::<f32>();
        let bins = bins.unwrap_or_else(|| scene.tile_bins());
        let kernel = Kernel::auto().unwrap();
        rasterize_binned_with(&scene.splats(), bins, &scene.background, kernel).unwrap()
    };
    let kept_from_a = run(&a, None).bins;
    let reused = run(&b, Some(kept_from_a));
    let fresh = run(&b, None);
    assert_eq!(reused.blended, fresh.blended);
    assert!(reused
        .image
        .iter()
        .zip(&fresh.image)
        .all(|(x, y)| x.to_bits() == y.to_bits()));
}

/// A forward pass of one scene keeps its row lists or blended rows in its bins; a backward pass
/// of the same means, depths and radii with other conics and opacities, given those bins, must
/// give the bits of a backward pass given bins that kept nothing.
fn backward_ignores_rows_kept_for_other_gaussians<T: gaussian::Real>(kernel: Kernel) {
    let mut rng = Rng(23);
    let a = random_scene(&mut rng, 600, 50, 40, 3);
    let mut b = a.clone();
    for (o, c) in b.opacities.iter_mut().zip(&mut b.conics) {
        *o = (*o * 1.5).min(0.99);
        *c = [c[0] * 0.25, c[1] * 0.25, c[2] * 0.25];
    }
    let (sa, sb) = (a.cast::<T>(), b.cast::<T>());
    let kept_from_a = rasterize_binned_with(&sa.splats(), sa.tile_bins(), &sa.background, kernel)
        .unwrap()
        .bins;
    let px = (b.width * b.height) as usize;
    let (vi, va, vd) = cotangents(&mut Rng(5), px, b.channel_count, 1.0);
    let (vi, va, vd) = (cast::<T>(&vi), cast::<T>(&va), cast::<T>(&vd));
    let cot = Cotangents {
        image: &vi,
        alpha: Some(&va[..]),
        depth: Some(&vd[..]),
    };
    let grads = |bins: &TileBins| {
        let g = rasterize_backward_with(&sb.splats(), bins, &sb.background, &cot, 1 << 20, kernel)
            .unwrap();
        [
            g.means2d.as_flattened().to_vec(),
            g.conics.as_flattened().to_vec(),
            g.opacities,
            g.depths,
            g.channels,
            g.background,
        ]
        .map(|v| {
            v.iter()
                .map(|x| x.to_f64_exact().to_bits())
                .collect::<Vec<u64>>()
        })
    };
    assert_eq!(grads(&kept_from_a), grads(&sb.tile_bins()));
}

#[test]
fn a_backward_pass_ignores_rows_kept_for_other_gaussians() {
    // f32 with this machine's kernel (the lane kernels' blended rows, or with DSGS_KERNEL=scalar
    // the reference loops' row lists), and the f64 reference loops' row lists.
    backward_ignores_rows_kept_for_other_gaussians::<f32>(Kernel::auto().unwrap());
    backward_ignores_rows_kept_for_other_gaussians::<f64>(Kernel::auto().unwrap());
    backward_ignores_rows_kept_for_other_gaussians::<f32>(Kernel::Scalar);
}
