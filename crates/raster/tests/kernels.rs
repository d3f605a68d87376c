//! Every tile kernel gives the same bits: the `f32` lane kernels, at every instruction set this
//! machine can run, against the scalar reference loops, forward and backward, on random scenes
//! (any size, partial tiles, any channel count), on saturated scenes (alpha clamp and
//! transmittance stop everywhere) and on hostile values (opacities above 1, degenerate and
//! non-finite conics and channels).

mod common;

use common::{random_scene, Rng, Scene2d};
use proptest::prelude::*;
use raster::{
    rasterize_backward_with, rasterize_binned_with, Cotangents, Isa, Kernel, Splats, TileBins,
};

/// Everything a kernel computes, as bits, every NaN as the one canonical NaN (vector code may
/// propagate another NaN operand than scalar code; the payload carries no meaning).
fn fingerprint(s: &Scene2d, kernel: Kernel, cot_seed: u64, with_aux: bool) -> Vec<Vec<u32>> {
    let f = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let means: Vec<[f32; 2]> = s.means2d.iter().map(|r| r.map(|x| x as f32)).collect();
    let conics: Vec<[f32; 3]> = s.conics.iter().map(|r| r.map(|x| x as f32)).collect();
    let (depths, opac, ch, bg) = (
        f(&s.depths),
        f(&s.opacities),
        f(&s.channels),
        f(&s.background),
    );
    let splats = Splats {
        means2d: &means,
        conics: &conics,
        depths: &depths,
        radii: &s.radii,
        opacities: &opac,
        channels: &ch,
        channel_count: s.channel_count,
    };
    let bins = TileBins::new(s.width, s.height, &means, &depths, &s.radii).unwrap();
    let out = rasterize_binned_with(&splats, bins, &bg, kernel).unwrap();
    let mut rng = Rng(cot_seed);
    let px = (s.width * s.height) as usize;
    let vi = f(&rng.vec(px * s.channel_count, -1.0, 1.0));
    let va = f(&rng.vec(px, -1.0, 1.0));
    let vd = f(&rng.vec(px, -1.0, 1.0));
    let cot = Cotangents {
        image: &vi,
        alpha: with_aux.then_some(&va[..]),
        depth: with_aux.then_some(&vd[..]),
    };
    // A small record budget so that several batches run.
    let g = rasterize_backward_with(&splats, &out.bins, &bg, &cot, 4096, kernel).unwrap();
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

/// Asserts that every lane kernel this machine can run matches the scalar loops bit for bit.
fn check_all_kernels(s: &Scene2d, cot_seed: u64, with_aux: bool) {
    let reference = fingerprint(s, Kernel::Scalar, cot_seed, with_aux);
    for isa in Isa::available() {
        let got = fingerprint(s, Kernel::Lanes(isa), cot_seed, with_aux);
        for ((r, g), part) in reference.iter().zip(&got).zip(PARTS) {
            if let Some(i) = r.iter().zip(g).position(|(a, b)| a != b) {
                panic!(
                    "{} kernel differs from scalar in {part} at {i}: {:e} vs {:e}",
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

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn random_scenes_are_bit_identical(
        seed in any::<u64>(), n in 0usize..400, width in 1u32..70, height in 1u32..50,
        d in prop::sample::select(vec![0usize, 1, 3, 4, 9, 16, 35]),
        mode in 0u8..3, with_aux in any::<bool>(),
    ) {
        let mut rng = Rng(seed);
        let mut s = random_scene(&mut rng, n, width, height, d);
        match mode {
            1 => saturate(&mut s, &mut rng),
            2 => hostile(&mut s, &mut rng),
            _ => {}
        }
        check_all_kernels(&s, seed ^ 0x5eed, with_aux);
    }
}
