//! Density control: every operation checked for counts, parameter values and the Adam state of
//! every surviving, new and removed Gaussian. Expected values come from the 3DGS definitions
//! (copies, `scale / (0.8 N)`, `min(opacity, 0.01)`), not from the code under test.

use gaussian::FeatureGaussians;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use train::adam::AdamConfig;
use train::density::rotation_matrix;
use train::model::{F_DC, F_REST, OPACITY, ROTATION, SCALING, XYZ};
use train::{DensifyConfig, GaussianGrads, GaussianModel, LearningRates};

const GROUPS: [&str; 6] = [XYZ, F_DC, F_REST, OPACITY, SCALING, ROTATION];

/// `n` distinct Gaussians (degree 1 SH) whose parameters encode their index.
fn scene(n: usize) -> FeatureGaussians<f32> {
    let k = 4;
    FeatureGaussians {
        means: (0..n)
            .map(|i| [i as f32, 0.5 * i as f32, -(i as f32)])
            .collect(),
        log_scales: (0..n)
            .map(|i| [-3.0 + 0.01 * i as f32, -3.5, -4.0])
            .collect(),
        quats: (0..n).map(|i| [1.0, 0.1 * i as f32, 0.0, 0.2]).collect(),
        opacity_logits: (0..n).map(|i| -1.0 + 0.1 * i as f32).collect(),
        sh_degree: 1,
        sh: (0..n * k).map(|j| [j as f32, -(j as f32), 0.5]).collect(),
        feature_dim: 0,
        features: Vec::new(),
    }
}

/// A model whose Adam moments are non-zero and differ per Gaussian (three steps of random
/// gradients).
fn trained_model(n: usize, seed: u64) -> GaussianModel {
    let mut m = GaussianModel::new(
        scene(n),
        &LearningRates::default(),
        AdamConfig::default(),
        1.0,
    )
    .unwrap();
    let mut rng = StdRng::seed_from_u64(seed);
    for _ in 0..3 {
        let r3 = |rng: &mut StdRng| -> Vec<[f32; 3]> {
            (0..n)
                .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
                .collect()
        };
        let means = r3(&mut rng);
        let scales = r3(&mut rng);
        let quats: Vec<[f32; 4]> = (0..n)
            .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
            .collect();
        let op: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let sh: Vec<[f32; 3]> = (0..n * 4)
            .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
            .collect();
        m.step(&GaussianGrads {
            means: &means,
            quats: &quats,
            log_scales: &scales,
            opacity_logits: &op,
            sh: &sh,
            coeffs_per_gaussian: 4,
        })
        .unwrap();
    }
    m
}

/// Row `i` of the Adam moments of group `name`.
fn moments(m: &GaussianModel, name: &str, i: usize) -> (Vec<f32>, Vec<f32>) {
    let p = &m.adam.params()[m.group(name).unwrap()];
    let w = p.width();
    (
        p.exp_avg()[i * w..(i + 1) * w].to_vec(),
        p.exp_avg_sq()[i * w..(i + 1) * w].to_vec(),
    )
}

/// All parameters of Gaussian `i` as one vector.
fn params(s: &FeatureGaussians<f32>, i: usize) -> Vec<f32> {
    let k = s.sh_coeffs_per_gaussian();
    let mut v = s.means[i].to_vec();
    v.extend(s.log_scales[i]);
    v.extend(s.quats[i]);
    v.push(s.opacity_logits[i]);
    v.extend(s.sh[i * k..(i + 1) * k].iter().flatten());
    v
}

#[test]
fn clone_appends_exact_copies_with_zero_moments() {
    let mut m = trained_model(6, 1);
    m.stats.grad_norm_sum[2] = 1.0;
    let before = m.clone();
    let n = m
        .clone_gaussians(&[false, true, false, true, false, false])
        .unwrap();
    assert_eq!(n, 2);
    assert_eq!(m.len(), 8);
    m.check_consistency().unwrap();
    for i in 0..6 {
        assert_eq!(params(&m.scene, i), params(&before.scene, i));
        for g in GROUPS {
            assert_eq!(
                moments(&m, g, i),
                moments(&before, g, i),
                "group {g} row {i}"
            );
        }
    }
    assert_eq!(params(&m.scene, 6), params(&before.scene, 1));
    assert_eq!(params(&m.scene, 7), params(&before.scene, 3));
    for g in GROUPS {
        let (a, b) = moments(&m, g, 6);
        assert!(a.iter().chain(&b).all(|&v| v == 0.0), "group {g}");
        let (a, b) = moments(&m, g, 1);
        assert!(a.iter().any(|&v| v != 0.0) && b.iter().any(|&v| v != 0.0));
    }
    // densification_postfix resets every statistic
    assert!(m.stats.grad_norm_sum.iter().all(|&v| v == 0.0));
    // step counts are per tensor and unchanged
    for p in m.adam.params() {
        assert_eq!(p.step_count(), 3);
    }
}

#[test]
fn prune_removes_rows_with_their_moments() {
    let mut m = trained_model(7, 2);
    m.stats.visible_count = (0..7).collect();
    let before = m.clone();
    let removed = m
        .prune(&[true, false, false, true, true, false, false])
        .unwrap();
    assert_eq!(removed, 3);
    assert_eq!(m.len(), 4);
    m.check_consistency().unwrap();
    for (new, old) in [1usize, 2, 5, 6].into_iter().enumerate() {
        assert_eq!(params(&m.scene, new), params(&before.scene, old));
        for g in GROUPS {
            assert_eq!(moments(&m, g, new), moments(&before, g, old));
        }
    }
    assert_eq!(m.stats.visible_count, vec![1, 2, 5, 6]);
    assert!(m.prune(&[true; 3]).is_err());
}

#[test]
fn split_replaces_a_gaussian_by_two_samples_of_itself() {
    let mut m = trained_model(4, 3);
    let before = m.clone();
    let mut rng = StdRng::seed_from_u64(9);
    let n = m
        .split_gaussians(&[false, true, false, true], 2, 0.8, &mut rng)
        .unwrap();
    assert_eq!(n, 2);
    assert_eq!(m.len(), 4 - 2 + 4);
    m.check_consistency().unwrap();
    // survivors first, in order, with their moments
    for (new, old) in [(0usize, 0usize), (1, 2)] {
        assert_eq!(params(&m.scene, new), params(&before.scene, old));
        for g in GROUPS {
            assert_eq!(moments(&m, g, new), moments(&before, g, old));
        }
    }
    // then copy 0 of Gaussians 1 and 3, then copy 1 of both
    for (new, old) in [(2usize, 1usize), (3, 3), (4, 1), (5, 3)] {
        let s = &m.scene;
        let b = &before.scene;
        for a in 0..3 {
            let expected = ((b.log_scales[old][a] as f64).exp() / 1.6).ln();
            assert!((s.log_scales[new][a] as f64 - expected).abs() < 1e-6);
        }
        assert_eq!(s.quats[new], b.quats[old]);
        assert_eq!(s.opacity_logits[new], b.opacity_logits[old]);
        assert_eq!(s.sh[new * 4..new * 4 + 4], b.sh[old * 4..old * 4 + 4]);
        // the sampled mean lies within a few of the original standard deviations
        let d: Vec<f64> = (0..3)
            .map(|a| s.means[new][a] as f64 - b.means[old][a] as f64)
            .collect();
        let dist = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let max_scale = (b.log_scales[old][0] as f64).exp();
        assert!(
            dist > 0.0 && dist < 6.0 * max_scale,
            "{dist} vs {max_scale}"
        );
        for g in GROUPS {
            let (a, v) = moments(&m, g, new);
            assert!(a.iter().chain(&v).all(|&x| x == 0.0));
        }
    }
}

#[test]
fn split_samples_follow_the_gaussian_covariance() {
    // 20,000 splits of one anisotropic, rotated Gaussian: the sample covariance of the new means
    // must be R diag(s^2) R^T. With 40,000 samples the standard error of each covariance entry is
    // about sqrt(2/40000) ~ 0.7% of the largest variance, so 5% is a safe bound.
    let mut g = scene(1);
    g.log_scales[0] = [(0.3f32).ln(), (0.1f32).ln(), (0.02f32).ln()];
    g.quats[0] = [0.8, 0.3, -0.5, 0.1];
    g.means[0] = [1.0, 2.0, 3.0];
    let reps = 20_000;
    let many = FeatureGaussians {
        means: vec![g.means[0]; reps],
        log_scales: vec![g.log_scales[0]; reps],
        quats: vec![g.quats[0]; reps],
        opacity_logits: vec![0.0; reps],
        sh_degree: 0,
        sh: vec![[0.0; 3]; reps],
        feature_dim: 0,
        features: Vec::new(),
    };
    let mut m =
        GaussianModel::new(many, &LearningRates::default(), AdamConfig::default(), 1.0).unwrap();
    let mut rng = StdRng::seed_from_u64(5);
    m.split_gaussians(&vec![true; reps], 2, 0.8, &mut rng)
        .unwrap();
    assert_eq!(m.len(), 2 * reps);
    let mean: [f64; 3] = std::array::from_fn(|a| {
        m.scene.means.iter().map(|p| p[a] as f64).sum::<f64>() / m.len() as f64
    });
    let r = rotation_matrix(g.quats[0]);
    let s2 = [0.09, 0.01, 0.0004];
    for a in 0..3 {
        assert!((mean[a] - g.means[0][a] as f64).abs() < 0.01);
        for b in 0..3 {
            let cov = m
                .scene
                .means
                .iter()
                .map(|p| (p[a] as f64 - mean[a]) * (p[b] as f64 - mean[b]))
                .sum::<f64>()
                / m.len() as f64;
            let expected: f64 = (0..3).map(|k| r[a][k] * s2[k] * r[b][k]).sum();
            assert!(
                (cov - expected).abs() < 0.05 * 0.09,
                "cov[{a}][{b}] = {cov}, expected {expected}"
            );
        }
    }
}

#[test]
fn densify_and_prune_follows_the_3dgs_rules() {
    // extent 10: clone/split boundary at max scale 0.1, world-scale prune above 1.0
    let extent = 10.0;
    let mut s = scene(6);
    s.log_scales[0] = [(0.05f32).ln(); 3]; // small, high gradient -> cloned
    s.log_scales[1] = [(0.5f32).ln(); 3]; // large, high gradient -> split
    s.log_scales[2] = [(0.05f32).ln(); 3]; // small, low gradient -> kept
    s.log_scales[3] = [(0.05f32).ln(); 3]; // transparent -> pruned
    s.opacity_logits[3] = -6.0; // sigmoid = 0.0025 < 0.005
    s.log_scales[4] = [(2.0f32).ln(), -3.0, -3.0]; // too large in the world -> pruned when large pruning is on
    s.log_scales[5] = [(0.05f32).ln(); 3]; // never visible -> kept
    for i in 0..5 {
        s.opacity_logits[i] = s.opacity_logits[i].max(-5.0);
    }
    s.opacity_logits[3] = -6.0;
    let make = |s: &FeatureGaussians<f32>| {
        let mut m = GaussianModel::new(
            s.clone(),
            &LearningRates::default(),
            AdamConfig::default(),
            extent,
        )
        .unwrap();
        // mean gradient norms: 0.0003, 0.0002 (exactly the threshold: selected, >=), 0.0001, ...
        m.stats.grad_norm_sum = vec![0.0006, 0.0004, 0.0003, 0.0, 0.0, 0.0];
        m.stats.visible_count = vec![2, 2, 3, 1, 1, 0];
        m
    };
    let cfg = DensifyConfig::default();
    let mut rng = StdRng::seed_from_u64(0);

    let mut m = make(&s);
    let report = m.densify_and_prune(&cfg, extent, false, &mut rng).unwrap();
    assert_eq!(report.before, 6);
    assert_eq!(report.cloned, 1);
    assert_eq!(report.split, 1);
    assert_eq!(report.pruned, 1);
    // 6 + 1 clone + 2 split - 1 split original - 1 transparent
    assert_eq!(report.after, 7);
    assert_eq!(m.len(), 7);
    m.check_consistency().unwrap();
    // order: survivors 0, 2, 4, 5; the clone of 0; the two halves of 1
    assert_eq!(m.scene.means[0], s.means[0]);
    assert_eq!(m.scene.means[1], s.means[2]);
    assert_eq!(m.scene.means[2], s.means[4]);
    assert_eq!(m.scene.means[3], s.means[5]);
    assert_eq!(m.scene.means[4], s.means[0]);
    for j in [5, 6] {
        assert!((m.scene.log_scales[j][0] - (0.5f32 / 1.6).ln()).abs() < 1e-6);
    }

    // after the first opacity reset, the oversized Gaussian goes too
    let mut m = make(&s);
    let report = m.densify_and_prune(&cfg, extent, true, &mut rng).unwrap();
    assert_eq!(report.pruned, 2);
    assert_eq!(m.len(), 6);
    assert!(!m.scene.means.contains(&s.means[4]));

    // the screen-size test, when switched on, uses the radii seen since the last densification
    let mut m = make(&s);
    m.stats.max_screen_radius = vec![0, 0, 25, 0, 0, 0];
    let on = DensifyConfig {
        prune_by_screen_size: true,
        ..cfg
    };
    let report = m.densify_and_prune(&on, extent, true, &mut rng).unwrap();
    assert_eq!(report.pruned, 3);
    assert!(!m.scene.means.contains(&s.means[2]));
    // ...and by default it never fires, as in the original code
    let mut m = make(&s);
    m.stats.max_screen_radius = vec![0, 0, 25, 0, 0, 0];
    let report = m.densify_and_prune(&cfg, extent, true, &mut rng).unwrap();
    assert_eq!(report.pruned, 2);
}

#[test]
fn opacity_reset_caps_opacities_and_zeroes_their_moments() {
    let mut m = trained_model(5, 4);
    m.scene.opacity_logits = vec![-8.0, -4.6, -4.5, 0.0, 3.0];
    let before = m.clone();
    m.reset_opacity(0.01).unwrap();
    for (i, &l) in m.scene.opacity_logits.iter().enumerate() {
        let p_before = 1.0 / (1.0 + (-(before.scene.opacity_logits[i] as f64)).exp());
        let p = 1.0 / (1.0 + (-(l as f64)).exp());
        assert!(
            (p - p_before.min(0.01)).abs() < 1e-8,
            "{i}: {p} vs {p_before}"
        );
    }
    let (a, v) = moments(&m, OPACITY, 2);
    assert!(a.iter().chain(&v).all(|&x| x == 0.0));
    // other groups untouched
    assert_eq!(moments(&m, XYZ, 2), moments(&before, XYZ, 2));
    assert_eq!(m.scene.means, before.scene.means);
}

#[test]
fn schedule_of_density_control() {
    let c = DensifyConfig::default();
    assert!(!c.densifies_at(500), "strictly after densify_from_iter");
    assert!(c.densifies_at(600));
    assert!(!c.densifies_at(650));
    assert!(c.densifies_at(14_900));
    assert!(!c.densifies_at(15_000));
    assert!(c.resets_opacity_at(3000, false));
    assert!(c.resets_opacity_at(12_000, false));
    assert!(!c.resets_opacity_at(15_000, false));
    assert!(!c.resets_opacity_at(500, false));
    assert!(c.resets_opacity_at(500, true));
    assert!(!c.prunes_large_at(3000));
    assert!(c.prunes_large_at(3100));
    assert!(c.gathers_stats(14_999) && !c.gathers_stats(15_000));
}

/// The optimiser must hold exactly the groups of the scene's SH degree, in order and with their
/// widths: a repeated group (which a damaged checkpoint could carry, and which would break the
/// next checkpoint write), a missing one or one of another width is refused, naming the groups.
#[test]
fn the_optimiser_groups_must_be_those_of_the_scene() {
    let fresh = || {
        GaussianModel::new(
            scene(3),
            &LearningRates::default(),
            AdamConfig::default(),
            1.0,
        )
        .unwrap()
    };
    let m = fresh();
    m.check_consistency().unwrap();
    let names: Vec<&str> = m.adam.params().iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, GROUPS);

    let mut repeated = fresh();
    repeated.adam.add_param(F_REST, 1e-3, 3, 9);
    let err = repeated.check_consistency().unwrap_err().to_string();
    // Named twice among the groups found, once among those expected.
    assert!(err.contains("optimiser groups"), "{err}");
    assert_eq!(err.matches("f_rest (9)").count(), 3, "{err}");

    // Degree 0: no f_rest group is expected, so the degree-1 layout does not fit it.
    let mut s = scene(3);
    s.sh_degree = 0;
    s.sh = s.sh.into_iter().step_by(4).collect();
    let mut m = fresh();
    m.scene = s;
    let err = m.check_consistency().unwrap_err().to_string();
    assert!(err.contains("SH degree 0"), "{err}");
}
