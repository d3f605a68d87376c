//! Scene validation, activations, bounds and the array bookkeeping densification relies on.

use gaussian::scene::{normalize_quat, sigmoid};
use gaussian::{scene_extent_from_cameras, Camera, FeatureGaussians, Intrinsics, SceneError};
use glam::{DMat3, DVec3};

/// Three Gaussians at SH degree 1 (4 coefficients each) with 2-d features; every value is
/// distinct so that any mix-up between Gaussians shows.
fn scene() -> FeatureGaussians<f64> {
    let n = 3;
    FeatureGaussians {
        means: vec![[0.0, 1.0, 2.0], [-1.0, 5.0, 0.5], [3.0, -2.0, 1.0]],
        log_scales: vec![[0.0, -1.0, 1.0], [-2.0, -2.5, -3.0], [0.5, 0.25, 0.0]],
        quats: vec![
            [2.0, 0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0, 1.0],
            [0.0, 0.0, 0.0, -3.0],
        ],
        opacity_logits: vec![0.0, 2.0, -1.0],
        sh_degree: 1,
        sh: (0..n * 4)
            .map(|i| [i as f64, 10.0 + i as f64, 20.0 + i as f64])
            .collect(),
        feature_dim: 2,
        features: (0..n * 2).map(|i| 100.0 + i as f64).collect(),
    }
}

#[test]
fn a_consistent_scene_validates() {
    assert_eq!(scene().validate(), Ok(()));
    assert_eq!(FeatureGaussians::<f32>::default().validate(), Ok(()));
}

#[test]
fn validation_names_the_bad_array() {
    let mut s = scene();
    s.quats.pop();
    assert_eq!(
        s.validate(),
        Err(SceneError::Length {
            array: "quats",
            actual: 2,
            expected: 3
        })
    );
    let mut s = scene();
    s.sh.push([0.0; 3]);
    assert!(matches!(
        s.validate(),
        Err(SceneError::Length { array: "sh", .. })
    ));
    let mut s = scene();
    s.features.pop();
    assert!(matches!(
        s.validate(),
        Err(SceneError::Length {
            array: "features",
            ..
        })
    ));
    let mut s = scene();
    s.sh_degree = 4;
    assert_eq!(s.validate(), Err(SceneError::ShDegree(4)));
    let mut s = scene();
    s.log_scales[2][1] = f64::NAN;
    assert_eq!(
        s.validate(),
        Err(SceneError::NonFinite {
            array: "log_scales",
            index: 2
        })
    );
    let mut s = scene();
    s.features[3] = f64::INFINITY;
    assert_eq!(
        s.validate(),
        Err(SceneError::NonFinite {
            array: "features",
            index: 3
        })
    );
    let msg = SceneError::NonFinite {
        array: "means",
        index: 7,
    }
    .to_string();
    assert!(msg.contains("means") && msg.contains('7'), "{msg}");
}

#[test]
fn activations() {
    let s = scene();
    assert_eq!(s.scale(0), [1.0, (-1.0f64).exp(), 1.0f64.exp()]);
    assert_eq!(
        s.scales()[1],
        [(-2.0f64).exp(), (-2.5f64).exp(), (-3.0f64).exp()]
    );
    assert_eq!(s.opacity(0), 0.5);
    assert!((s.opacity(1) - 1.0 / (1.0 + (-2.0f64).exp())).abs() < 1e-15);
    assert_eq!(s.opacities()[2], sigmoid(-1.0));
    assert_eq!(s.rotation(0), [1.0, 0.0, 0.0, 0.0]);
    assert_eq!(s.rotation(1), [0.5; 4]);
    // q = -z: a rotation by pi about z.
    let as_mat = |rows: [[f64; 3]; 3]| DMat3::from_cols_array_2d(&rows).transpose();
    let half_turn = DMat3::from_cols(-DVec3::X, -DVec3::Y, DVec3::Z);
    assert!(as_mat(s.rotation_matrix(2)).abs_diff_eq(half_turn, 1e-15));
    // (1,1,1,1)/2 is a third of a turn about (1,1,1): the cyclic permutation x->y->z->x.
    let cyc = DMat3::from_axis_angle(DVec3::ONE.normalize(), 2.0 * std::f64::consts::FRAC_PI_3);
    assert!(as_mat(s.rotation_matrix(1)).abs_diff_eq(cyc, 1e-15));
    assert!(cyc.abs_diff_eq(DMat3::from_cols(DVec3::Y, DVec3::Z, DVec3::X), 1e-15));
    assert_eq!(normalize_quat([0.0f32; 4]), [0.0; 4]);
}

#[test]
fn bounds_and_extent() {
    let s = scene();
    let (lo, hi) = s.bounds().unwrap();
    assert_eq!(lo, [-1.0, -2.0, 0.5]);
    assert_eq!(hi, [3.0, 5.0, 2.0]);
    let diag = (16.0f64 + 49.0 + 2.25).sqrt();
    assert!((s.extent() - 0.5 * diag).abs() < 1e-15);
    assert_eq!(FeatureGaussians::<f32>::default().bounds(), None);
    assert_eq!(FeatureGaussians::<f32>::default().extent(), 0.0);
}

#[test]
fn extent_from_cameras_follows_3dgs() {
    let k = Intrinsics {
        fx: 10.0,
        fy: 10.0,
        cx: 5.0,
        cy: 5.0,
        width: 10,
        height: 10,
    };
    let centres = [
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::new(-1.0, 0.0, 0.0),
        DVec3::new(0.0, 3.0, 0.0),
        DVec3::new(0.0, 1.0, 4.0),
    ];
    let rot = DMat3::from_axis_angle(DVec3::new(0.3, 0.4, 0.5).normalize(), 0.7);
    let cams: Vec<Camera> = centres
        .iter()
        .map(|&c| Camera::from_rotation_center(k, rot, c))
        .collect();
    // Mean centre (0, 1, 1); farthest is (0, 1, 4) at distance 3.
    let e = scene_extent_from_cameras(&cams);
    assert!((e - 1.1 * 3.0).abs() < 1e-12, "{e}");
    assert_eq!(scene_extent_from_cameras(&[]), 0.0);
}

#[test]
fn subset_extend_retain_keep_arrays_consistent() {
    let s = scene();
    let sub = s.subset(&[2, 0, 2]);
    assert_eq!(sub.validate(), Ok(()));
    assert_eq!(sub.len(), 3);
    assert_eq!(sub.means[0], s.means[2]);
    assert_eq!(sub.means[1], s.means[0]);
    assert_eq!(sub.sh_of(0), s.sh_of(2));
    assert_eq!(sub.sh_of(1), s.sh_of(0));
    assert_eq!(sub.feature_of(2), s.feature_of(2));
    assert_eq!(sub.opacity_logits, vec![-1.0, 0.0, -1.0]);

    let mut a = s.clone();
    a.extend(&sub).unwrap();
    assert_eq!(a.validate(), Ok(()));
    assert_eq!(a.len(), 6);
    assert_eq!(a.sh_of(3), s.sh_of(2));
    assert_eq!(a.feature_of(5), s.feature_of(2));

    let mut wrong = s.clone().with_features(3, 0.0);
    assert!(matches!(wrong.extend(&s), Err(SceneError::Mismatch { .. })));

    a.retain(&[false, true, false, true, false, false]).unwrap();
    assert_eq!(a.validate(), Ok(()));
    assert_eq!(a.means, vec![s.means[1], s.means[2]]);
    assert_eq!(a.sh_of(1), s.sh_of(2));
    assert_eq!(a.features, [s.feature_of(1), s.feature_of(2)].concat());
    assert!(matches!(
        a.retain(&[true]),
        Err(SceneError::MaskLength { .. })
    ));
}

#[test]
fn with_features_and_cast() {
    let s = scene().with_features(5, 0.25);
    assert_eq!(s.feature_dim, 5);
    assert_eq!(s.features, vec![0.25; 15]);
    assert_eq!(s.validate(), Ok(()));
    let f: FeatureGaussians<f32> = s.cast();
    assert_eq!(f.validate(), Ok(()));
    assert_eq!(f.means[1], [-1.0f32, 5.0, 0.5]);
    assert_eq!(
        f.sh,
        s.sh.iter().map(|r| r.map(|v| v as f32)).collect::<Vec<_>>()
    );
    // Every value here is exact in f32, so the round trip is lossless.
    let back: FeatureGaussians<f64> = f.cast();
    assert_eq!(back, s);
}
