//! The rasterizer against the float64 oracle (`oracle/fixtures/raster.safetensors`): forward
//! images and the gradients of every rasterizer input, for all five cases, from the projected
//! inputs stored in the fixture.

mod common;

use common::{flat, logit_grads, raster_fixture, to_f64, RasterCase, CASES};
use dsgs_testkit::assert_close_verbose;

/// Tolerance in `f64`: the oracle is float64 too; sums run in a different order, so agreement is
/// to a few hundred ulps of the largest magnitude, far below 1e-9.
const TOL_F64: f64 = 1e-9;

/// Tolerance in `f32`. The inputs are rounded to `f32` (relative 6e-8), `exp(-sigma)` with `sigma`
/// up to about 5.5 amplifies a relative conic error by `sigma`, transmittance is a product of up
/// to a few hundred factors, and gradients sum a few hundred pixel contributions with
/// cancellation: the expected error is 1e-6..1e-5 of the largest magnitude. 1e-4 leaves a margin
/// for an unlucky cancellation while still catching any wrong term (those are O(1e-2) or more).
const TOL_F32: f64 = 1e-4;

fn check_case<T: gaussian::Real>(f: &dsgs_testkit::Fixture, name: &str, tol: f64) {
    let case = RasterCase::load(f, name);
    let (out, grads) = case.run::<T>();
    // Asserts agreement with the fixture's `{name}.{key}` and prints the error
    // (`cargo test -- --nocapture` shows the figures).
    let check = |key: &str, actual: &[f64]| {
        let what = format!("{name} ({}) {key}", std::any::type_name::<T>());
        assert_close_verbose(&what, actual, &f.get(&format!("{name}.{key}")).data, tol);
    };
    check("image", &to_f64(&out.image));
    check("alpha", &to_f64(&out.alpha));
    check("depth", &to_f64(&out.depth));
    check("grad.means2d", &flat(&grads.means2d));
    check("grad.conics", &flat(&grads.conics));
    let v_logits = logit_grads(&grads.opacities, &case.opacity_logits);
    check("grad.opacity_logits", &v_logits);
    // For sh3 the channels are SH colours, whose gradient the fixture does not store (it is
    // checked through the SH chain in the render tests).
    if f.has(&format!("{name}.grad.features")) {
        check("grad.features", &to_f64(&grads.channels));
    }
    // Every pixel of the alpha image agrees with its blend count: no blends, no coverage.
    for (a, &n) in out.alpha.iter().zip(&out.blended) {
        assert_eq!(n == 0, a.to_f64_exact() == 0.0, "{name}: count vs alpha");
    }
}

#[test]
fn all_cases_match_the_oracle_in_f64() {
    let f = raster_fixture();
    for name in CASES {
        check_case::<f64>(&f, name, TOL_F64);
    }
}

#[test]
fn all_cases_match_the_oracle_in_f32() {
    let f = raster_fixture();
    for name in CASES {
        check_case::<f32>(&f, name, TOL_F32);
    }
}

/// The early-termination case really terminates early, the culled case really culls, and the
/// counts and the normalised depth are consistent with the other outputs.
#[test]
fn fixture_cases_exercise_the_stop_and_culling() {
    let f = raster_fixture();
    let sat = RasterCase::load(&f, "saturated");
    let (out, _) = sat.run::<f64>();
    // A pixel that stopped has transmittance just above 1e-4 but alpha < 1 - 1e-4.
    let stopped = out.alpha.iter().filter(|&&a| a > 1.0 - 1e-3).count();
    assert!(stopped > 100, "only {stopped} saturated pixels");
    for ((&z, &a), &nz) in out.depth.iter().zip(&out.alpha).zip(&out.normalized_depth) {
        if a > 0.0 {
            assert!((nz - z / a).abs() <= 1e-12 * nz.abs().max(1.0));
        } else {
            assert_eq!(nz, 0.0);
        }
    }
    let edges = RasterCase::load(&f, "edges");
    let culled = edges.scene.radii.iter().filter(|r| r[0] == 0).count();
    assert!(culled >= 10, "edges case culls only {culled}");
    let (_, g) = edges.run::<f64>();
    for (i, r) in edges.scene.radii.iter().enumerate() {
        if r[0] == 0 || r[1] == 0 {
            assert_eq!(g.means2d[i], [0.0, 0.0]);
            assert_eq!(g.opacities[i], 0.0);
        }
    }
}
