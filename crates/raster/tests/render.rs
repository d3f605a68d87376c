//! The camera-level chain (projection, SH colour or features, rasterization) against the oracle:
//! forward images and the gradients of every scene parameter for all five cases.

mod common;

use common::{cast, flat, raster_fixture, to_f64, SceneCase, CASES};
use dsgs_testkit::assert_close_verbose;
use gaussian::{FeatureGaussians, Real};
use raster::{render, render_backward, Channels, RenderOptions};

/// See `fixture.rs`: the same reasoning; the chain adds a few dozen operations per Gaussian
/// (projection, SH), which stay at rounding level in `f64`.
const TOL_F64: f64 = 1e-9;
/// In `f32` the projection adds a 2x2 inversion and the SH polynomials to the error budget of
/// `fixture.rs`; gradients of means go through the conic derivative, which amplifies relative
/// error by the condition number of the 2D covariance (at most ~1e2 for these scenes). The
/// expected error is still around 1e-5; 1e-4 is the acceptance tolerance.
const TOL_F32: f64 = 1e-4;

fn cast_scene<T: Real>(s: &FeatureGaussians<f64>) -> FeatureGaussians<T> {
    let r3 = |v: &[[f64; 3]]| v.iter().map(|r| r.map(T::lit)).collect::<Vec<_>>();
    FeatureGaussians {
        means: r3(&s.means),
        log_scales: r3(&s.log_scales),
        quats: s.quats.iter().map(|r| r.map(T::lit)).collect(),
        opacity_logits: cast(&s.opacity_logits),
        sh_degree: s.sh_degree,
        sh: r3(&s.sh),
        feature_dim: s.feature_dim,
        features: cast(&s.features),
    }
}

fn check_case<T: Real>(name: &str, tol: f64) {
    let f = raster_fixture();
    let case = SceneCase::load(&f, name);
    let exp = |k: &str| f.get(&format!("{name}.{k}")).data.clone();
    // Asserts agreement with the fixture's `{name}.{key}` and prints the error.
    let check = |key: &str, actual: &[f64]| {
        let what = format!("{name} ({}) {key}", std::any::type_name::<T>());
        assert_close_verbose(&what, actual, &exp(key), tol);
    };
    let scene = cast_scene::<T>(&case.scene);
    let opts = RenderOptions::new(case.channels, cast(&case.background));
    let r = render(&case.camera, &scene, &opts).unwrap();
    check("means2d", &flat(&r.projected.means2d));
    check("conics", &flat(&r.projected.conics));
    check("image", &to_f64(&r.raster.image));
    check("alpha", &to_f64(&r.raster.alpha));
    check("depth", &to_f64(&r.raster.depth));
    let (vi, va, vd) = (
        cast::<T>(&exp("v_image")),
        cast::<T>(&exp("v_alpha")),
        cast::<T>(&exp("v_depth")),
    );
    let g = render_backward(&case.camera, &scene, &opts, &r, &vi, Some(&va), Some(&vd)).unwrap();
    check("grad.means", &flat(&g.means));
    check("grad.quats", &flat(&g.quats));
    check("grad.log_scales", &flat(&g.log_scales));
    check("grad.opacity_logits", &to_f64(&g.opacity_logits));
    check("grad.means2d", &flat(&g.means2d));
    match case.channels {
        Channels::Features => check("grad.features", &to_f64(&g.features)),
        _ => {
            check("colors", &flat(r.colors.as_ref().unwrap()));
            check("grad.sh_coeffs", &flat(&g.sh));
        }
    }
}

#[test]
fn chained_render_matches_the_oracle_in_f64() {
    for name in CASES {
        check_case::<f64>(name, TOL_F64);
    }
}

#[test]
fn chained_render_matches_the_oracle_in_f32() {
    for name in CASES {
        check_case::<f32>(name, TOL_F32);
    }
}
