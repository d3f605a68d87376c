//! The geometry step with the SH colour backward inside the SH groups' Adam pass
//! (`GaussianModel::step_from_colours`) against the step from the rasterizer's full gradients
//! (`raster::render_backward`, then `GaussianModel::step_except`), and the skipped groups of a
//! step. The reference is the composition of the two public steps the trainer used before, not
//! numbers taken from the code under test.

mod common;

use common::sphere_cameras;
use gaussian::FeatureGaussians;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use raster::SceneGrads;
use train::adam::AdamConfig;
use train::model::{F_DC, F_REST, OPACITY, ROTATION, SCALING, XYZ};
use train::render::{render_color, render_color_backward, render_color_backward_before_sh};
use train::{ColourGrads, GaussianGrads, GaussianModel, LearningRates};

const GROUPS: [&str; 6] = [XYZ, F_DC, F_REST, OPACITY, SCALING, ROTATION];

/// `n` Gaussians of SH degree 3 around the origin, with coefficients large enough that some
/// colours clamp at 0 and some Gaussians outside every view (a zero colour cotangent).
fn scene(n: usize, seed: u64) -> FeatureGaussians<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut g = FeatureGaussians {
        sh_degree: 3,
        ..Default::default()
    };
    for i in 0..n {
        let spread = if i % 7 == 0 { 30.0 } else { 0.9 };
        g.means
            .push(std::array::from_fn(|_| rng.random_range(-spread..spread)));
        g.log_scales
            .push(std::array::from_fn(|_| rng.random_range(-3.5f32..-1.5)));
        g.quats
            .push(std::array::from_fn(|_| rng.random_range(-1.0f32..1.0)));
        g.opacity_logits.push(rng.random_range(-1.0f32..3.0));
        for _ in 0..16 {
            g.sh.push(std::array::from_fn(|_| rng.random_range(-1.0f32..1.0)));
        }
    }
    g
}

/// A model after two steps of random gradients (non-zero, per-Gaussian Adam moments).
fn warmed_model(n: usize, seed: u64) -> GaussianModel {
    let cfg = AdamConfig {
        eps: 1e-15,
        ..AdamConfig::default()
    };
    let mut m = GaussianModel::new(scene(n, seed), &LearningRates::default(), cfg, 1.0).unwrap();
    let mut rng = StdRng::seed_from_u64(seed + 1);
    for _ in 0..2 {
        let mut r =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-1e-3..1e-3)).collect() };
        let (means, quats, scales, op, sh) = (r(3 * n), r(4 * n), r(3 * n), r(n), r(48 * n));
        m.step(&GaussianGrads {
            means: means.as_chunks().0,
            quats: quats.as_chunks().0,
            log_scales: scales.as_chunks().0,
            opacity_logits: &op,
            sh: sh.as_chunks().0,
            coeffs_per_gaussian: 16,
        })
        .unwrap();
    }
    m
}

fn bits<const K: usize>(v: &[[f32; K]]) -> Vec<u32> {
    v.as_flattened().iter().map(|x| x.to_bits()).collect()
}

fn scene_bits(s: &FeatureGaussians<f32>) -> [Vec<u32>; 5] {
    [
        bits(&s.means),
        bits(&s.quats),
        bits(&s.log_scales),
        s.opacity_logits.iter().map(|x| x.to_bits()).collect(),
        bits(&s.sh),
    ]
}

fn state_bits(m: &GaussianModel) -> Vec<(String, u64, Vec<u32>, Vec<u32>)> {
    m.adam
        .params()
        .iter()
        .map(|p| {
            let b = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect();
            (
                p.name.clone(),
                p.step_count(),
                b(p.exp_avg()),
                b(p.exp_avg_sq()),
            )
        })
        .collect()
}

fn full_grads(g: &SceneGrads<f32>) -> GaussianGrads<'_> {
    GaussianGrads {
        means: &g.means,
        quats: &g.quats,
        log_scales: &g.log_scales,
        opacity_logits: &g.opacity_logits,
        sh: &g.sh,
        coeffs_per_gaussian: 16,
    }
}

#[test]
fn the_sh_backward_inside_adam_gives_the_bits_of_the_full_gradients_step() {
    // several parallel chunks and partial lane blocks; every active degree; no skip, the
    // opacity skipped (an opacity reset) and an SH group skipped (the separate path)
    let n = 2 * 341 + 57;
    let camera = &sphere_cameras(3, 3.0, 40, 45.0)[1];
    let bg = [0.2f32, 0.5, 1.0];
    for degree in 0..=3 {
        for skip in [&[][..], &[OPACITY][..], &[F_REST][..]] {
            let mut a = warmed_model(n, 40 + degree as u64);
            let mut b = a.clone();
            let fwd = render_color(camera, &a.scene, degree, bg).unwrap();
            let mut rng = StdRng::seed_from_u64(9);
            let v_image: Vec<f32> = (0..fwd.raster.image.len())
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();

            let full = render_color_backward(camera, &a.scene, degree, bg, &fwd, &v_image).unwrap();
            a.step_except(&full_grads(&full), skip).unwrap();

            let (rest, colours) =
                render_color_backward_before_sh(camera, &b.scene, degree, bg, &fwd, &v_image)
                    .unwrap();
            assert!(rest.sh.is_empty());
            assert!(colours.contains(&[0.0; 3]), "a Gaussian outside the view");
            assert!(colours.iter().any(|c| *c != [0.0; 3]));
            b.step_from_colours(
                &ColourGrads {
                    means: &rest.means,
                    quats: &rest.quats,
                    log_scales: &rest.log_scales,
                    opacity_logits: &rest.opacity_logits,
                    colours: &colours,
                    sh_degree: degree,
                    camera_center: camera.center_as(),
                },
                skip,
            )
            .unwrap();
            let what = format!("degree {degree}, skip {skip:?}");
            assert_eq!(scene_bits(&a.scene), scene_bits(&b.scene), "scene, {what}");
            assert_eq!(state_bits(&a), state_bits(&b), "Adam state, {what}");
        }
    }
}

#[test]
fn a_skipped_group_keeps_its_parameters_and_state() {
    let n = 300;
    let camera = &sphere_cameras(3, 3.0, 40, 45.0)[0];
    let start = warmed_model(n, 77);
    let fwd = render_color(camera, &start.scene, 3, [0.0; 3]).unwrap();
    let v_image = vec![0.5f32; fwd.raster.image.len()];
    let full = render_color_backward(camera, &start.scene, 3, [0.0; 3], &fwd, &v_image).unwrap();
    for skipped in GROUPS {
        let mut m = start.clone();
        m.step_except(&full_grads(&full), &[skipped]).unwrap();
        for name in GROUPS {
            let g = m.group(name).unwrap();
            let (before, after) = (&start.adam.params()[g], &m.adam.params()[g]);
            if name == skipped {
                assert_eq!(before, after, "state of skipped `{name}`");
            } else {
                assert_eq!(
                    after.step_count(),
                    before.step_count() + 1,
                    "`{name}` stepped"
                );
                assert_ne!(before.exp_avg(), after.exp_avg(), "`{name}` moments");
            }
        }
        let changed = |a: Vec<u32>, b: Vec<u32>| a != b;
        let [m0, q0, s0, o0, sh0] = scene_bits(&start.scene);
        let [m1, q1, s1, o1, sh1] = scene_bits(&m.scene);
        assert_eq!(changed(m0, m1), skipped != XYZ, "means, {skipped} skipped");
        assert_eq!(
            changed(q0, q1),
            skipped != ROTATION,
            "quats, {skipped} skipped"
        );
        assert_eq!(
            changed(s0, s1),
            skipped != SCALING,
            "scales, {skipped} skipped"
        );
        assert_eq!(
            changed(o0, o1),
            skipped != OPACITY,
            "opacities, {skipped} skipped"
        );
        // the SH array holds both SH groups
        assert!(changed(sh0, sh1), "sh, {skipped} skipped");
    }
}
