//! EWA projection against the float64 oracle and against central differences.

mod oracle_case;

use dsgs_testkit::{assert_close_verbose, max_rel_err, Fixture};
use gaussian::project::{project, project_backward, ProjectSettings, Projected, ProjectionGrads};
use gaussian::{Camera, Intrinsics};
use glam::{DMat3, DQuat, DVec3};
use oracle_case::{fixture, flat, inputs, rows, Inputs, CASES};
use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;

/// Float64 reference, float64 computation: only rounding differs (the operations are the same
/// up to association), so 1e-9 leaves orders of magnitude of room and still catches any
/// convention error, which shows up at 1e-3 or above.
const TOL_F64: f64 = 1e-9;

#[test]
fn forward_matches_oracle_in_f64() {
    let f = fixture();
    for case in CASES {
        let x = inputs(&f, case);
        let p = project(
            &x.camera,
            &x.means,
            &x.quats,
            &x.log_scales,
            &ProjectSettings::default(),
        );
        let e_means2d = rows::<2>(&f, &format!("{case}.means2d"));
        let e_conics = rows::<3>(&f, &format!("{case}.conics"));
        let e_depths = &f.get(&format!("{case}.depths")).data;
        let e_radii = rows::<2>(&f, &format!("{case}.radii"));
        let check = |what: &str, actual: &[f64], expected: &[f64]| {
            assert_close_verbose(&format!("{case} {what}"), actual, expected, TOL_F64);
        };
        check("means2d", &flat(&p.means2d), &flat(&e_means2d));
        check("conics", &flat(&p.conics), &flat(&e_conics));
        check("depths", &p.depths, e_depths);
        let radii: Vec<[f64; 2]> = p.radii.iter().map(|r| r.map(f64::from)).collect();
        assert_eq!(radii, e_radii, "{case}: radii differ");
    }
}

#[test]
fn oracle_cases_exercise_culling() {
    // The edges case must contain culled and visible Gaussians, or the radii check says little.
    let f = fixture();
    let r = rows::<2>(&f, "edges.radii");
    let culled = r.iter().filter(|r| r[0] == 0.0).count();
    assert!(culled >= 10 && culled < r.len(), "{culled} culled");
}

/// f32 production path against the f64 oracle. Inputs rounded to f32 (eps 6e-8) and a dozen
/// f32 operations, amplified by the conditioning of the 2x2 inverse, give errors of a few 1e-7
/// in these cases (printed); 1e-5 leaves more than a factor 10 and still catches any formula
/// error, which shows at 1e-3 or more. Radii could differ only where 3.33 sigma lies within
/// f32 rounding of an integer, which these cases do not hit, so they are compared exactly.
#[test]
fn forward_in_f32_is_close_to_oracle() {
    let f = fixture();
    for case in CASES {
        let x = inputs(&f, case);
        let means: Vec<[f32; 3]> = x.means.iter().map(|m| m.map(|v| v as f32)).collect();
        let quats: Vec<[f32; 4]> = x.quats.iter().map(|m| m.map(|v| v as f32)).collect();
        let scales: Vec<[f32; 3]> = x.log_scales.iter().map(|m| m.map(|v| v as f32)).collect();
        let p = project(
            &x.camera,
            &means,
            &quats,
            &scales,
            &ProjectSettings::default(),
        );
        let up = |v: Vec<f32>| v.iter().map(|&a| a as f64).collect::<Vec<_>>();
        let vis: Vec<usize> = (0..p.radii.len()).filter(|&i| p.is_visible(i)).collect();
        let pick = |v: Vec<f64>, d: usize| -> Vec<f64> {
            vis.iter()
                .flat_map(|&i| v[i * d..(i + 1) * d].to_vec())
                .collect()
        };
        let e_m = pick(f.get(&format!("{case}.means2d")).data.clone(), 2);
        let e_c = pick(f.get(&format!("{case}.conics")).data.clone(), 3);
        let a_m = pick(up(p.means2d.iter().flatten().copied().collect()), 2);
        let a_c = pick(up(p.conics.iter().flatten().copied().collect()), 3);
        assert_close_verbose(&format!("{case} f32 means2d"), &a_m, &e_m, 1e-5);
        assert_close_verbose(&format!("{case} f32 conics"), &a_c, &e_c, 1e-5);
        let e_r = rows::<2>(&f, &format!("{case}.radii"));
        let radii: Vec<[f64; 2]> = p.radii.iter().map(|r| r.map(f64::from)).collect();
        assert_eq!(radii, e_r, "{case}: f32 radii differ");
    }
}

/// The projection of `x` (default settings) and its backward pass with the given cotangents.
fn project_with_backward(
    x: &Inputs,
    v_means2d: &[[f64; 2]],
    v_conics: &[[f64; 3]],
    v_depths: &[f64],
) -> (Projected<f64>, ProjectionGrads<f64>) {
    let s = ProjectSettings::default();
    let p = project(&x.camera, &x.means, &x.quats, &x.log_scales, &s);
    let g = project_backward(
        &x.camera,
        &x.means,
        &x.quats,
        &x.log_scales,
        &s,
        &p,
        v_means2d,
        v_conics,
        v_depths,
    );
    (p, g)
}

/// The inputs of `case` and the projection backward with the oracle's cotangents of means2d and
/// conics (and none of the depths).
fn backward_from_oracle_cotangents(f: &Fixture, case: &str) -> (Inputs, ProjectionGrads<f64>) {
    let x = inputs(f, case);
    let v_means2d = rows::<2>(f, &format!("{case}.grad.means2d"));
    let v_conics = rows::<3>(f, &format!("{case}.grad.conics"));
    let zeros = vec![0.0; x.means.len()];
    let (_, g) = project_with_backward(&x, &v_means2d, &v_conics, &zeros);
    (x, g)
}

/// `grad.quats` and `grad.log_scales` reach the inputs only through the conics, and the
/// fixture records the conic (and means2d) cotangents, so the projection backward alone must
/// reproduce them.
#[test]
fn backward_matches_oracle_for_quats_and_log_scales() {
    let f = fixture();
    for case in CASES {
        let (_, g) = backward_from_oracle_cotangents(&f, case);
        let e_q = rows::<4>(&f, &format!("{case}.grad.quats"));
        let e_s = rows::<3>(&f, &format!("{case}.grad.log_scales"));
        let check = |what: &str, actual: &[f64], expected: &[f64]| {
            assert_close_verbose(&format!("{case} {what}"), actual, expected, TOL_F64);
        };
        check("grad.quats", &flat(&g.quats), &flat(&e_q));
        check("grad.log_scales", &flat(&g.log_scales), &flat(&e_s));
    }
}

/// `grad.means` also collects the depth cotangent (and, for sh3, the SH colour gradient), which
/// only the rasterizer can supply. A depth cotangent moves a mean only along the camera's view
/// axis, so whatever `grad.means` holds beyond our means2d/conic (and SH) contributions must be
/// parallel to that axis. That checks two of the three components of every mean gradient
/// against the oracle without inventing the depth cotangent.
#[test]
fn mean_gradients_agree_with_oracle_up_to_the_depth_direction() {
    let f = fixture();
    for case in CASES {
        let (x, g) = backward_from_oracle_cotangents(&f, case);
        let mut ours = g.means.clone();
        if case == "sh3" {
            let d_sh_means = sh_mean_gradient_from_oracle(&f, &x.camera, &x.means);
            for (o, d) in ours.iter_mut().zip(d_sh_means) {
                for a in 0..3 {
                    o[a] += d[a];
                }
            }
        }
        let e = rows::<3>(&f, &format!("{case}.grad.means"));
        let axis = x.camera.view_direction();
        let mut residual_perp = Vec::new();
        let mut along = 0usize;
        for (o, e) in ours.iter().zip(&e) {
            let r = DVec3::from(*e) - DVec3::from(*o);
            let perp = r - r.dot(axis) * axis;
            residual_perp.extend_from_slice(&perp.to_array());
            if r.dot(axis).abs() > 1e-6 * DVec3::from(*e).length() {
                along += 1;
            }
        }
        let scale = flat(&e).iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = residual_perp.iter().fold(0.0f64, |m, v| m.max(v.abs())) / scale;
        println!("{case}: grad means off the view axis {err:.2e} ({along} with a depth part)");
        assert!(
            err <= TOL_F64,
            "{case}: mean gradient residual {err:.3e} off the view axis"
        );
        // The check is only meaningful if the depth part is really there.
        assert!(along > 0, "{case}: no depth contribution found");
    }
}

/// The SH part of the sh3 mean gradient. The colour cotangent (after the clamp mask) is read
/// from the DC coefficient's gradient, `d sh_0 = C0 * v_colour`, which the oracle records.
fn sh_mean_gradient_from_oracle(f: &Fixture, camera: &Camera, means: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let sh = rows::<3>(f, "sh3.sh_coeffs");
    let d_sh = rows::<3>(f, "sh3.grad.sh_coeffs");
    let k = 16;
    let c0 = 0.2820947917738781;
    let v_colors: Vec<[f64; 3]> = (0..means.len())
        .map(|i| d_sh[i * k].map(|v| v / c0))
        .collect();
    let center = camera.center().to_array();
    let (_, d_means) = gaussian::sh_colors_backward(3, k, &sh, means, center, &v_colors);
    d_means
}

#[test]
fn culled_gaussians_get_zero_gradient() {
    let f = fixture();
    let x = inputs(&f, "edges");
    let n = x.means.len();
    let (p, g) = project_with_backward(&x, &vec![[1.0; 2]; n], &vec![[1.0; 3]; n], &vec![1.0; n]);
    let mut culled = 0;
    for i in 0..n {
        if !p.is_visible(i) {
            culled += 1;
            assert_eq!(g.means[i], [0.0; 3]);
            assert_eq!(g.quats[i], [0.0; 4]);
            assert_eq!(g.log_scales[i], [0.0; 3]);
        } else {
            assert_ne!(g.means[i], [0.0; 3]);
        }
    }
    assert!(culled > 0);
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let f = fixture();
    let x = inputs(&f, "saturated");
    let s = ProjectSettings::default();
    let run = |threads: usize| -> (Projected<f64>, Vec<[f64; 3]>) {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            // Replicate the case so that the work is split across tasks.
            let rep = 40;
            let means: Vec<_> = x
                .means
                .iter()
                .cycle()
                .take(rep * x.means.len())
                .copied()
                .collect();
            let quats: Vec<_> = x.quats.iter().cycle().take(means.len()).copied().collect();
            let ls: Vec<_> = x
                .log_scales
                .iter()
                .cycle()
                .take(means.len())
                .copied()
                .collect();
            let p = project(&x.camera, &means, &quats, &ls, &s);
            let n = means.len();
            let g = project_backward(
                &x.camera,
                &means,
                &quats,
                &ls,
                &s,
                &p,
                &vec![[0.3, -0.2]; n],
                &vec![[0.1, 0.2, -0.3]; n],
                &vec![0.5; n],
            );
            (p, g.means)
        })
    };
    assert_eq!(run(1), run(2));
}

// ---------------------------------------------------------------------------------------------
// Central differences.

/// A random camera and one Gaussian placed relative to it.
#[derive(Clone, Debug)]
struct Case {
    camera: Camera,
    mean: [f64; 3],
    quat: [f64; 4],
    log_scale: [f64; 3],
    v_mean2d: [f64; 2],
    v_conic: [f64; 3],
    v_depth: f64,
}

/// Where the view-space `x / z` (or `y / z`) of the Gaussian sits relative to the clamp
/// `[-lim_neg, lim_pos]` of the EWA Jacobian: well inside, or beyond either bound, always at
/// least 5% of the bound away from it so that the central difference never crosses the kink.
/// Half of the draws fall inside; beyond the bounds, Gaussians are kept close enough to the
/// image (up to 1.25 times the bound) that many of them still overlap it and are not culled.
fn place(region: u8, t: f64, lim_neg: f64, lim_pos: f64) -> f64 {
    match region {
        0 | 1 => -0.95 * lim_neg + t * 0.95 * (lim_neg + lim_pos),
        2 => lim_pos * (1.05 + 0.2 * t),
        _ => -lim_neg * (1.05 + 0.2 * t),
    }
}

fn case_strategy() -> impl Strategy<Value = Case> {
    let cam = (
        prop::array::uniform4(-1.0f64..1.0),
        prop::array::uniform3(-2.0f64..2.0),
        20.0f64..80.0,
        0.8f64..1.25,
        16u32..64,
        16u32..64,
        0.3f64..0.7,
        0.3f64..0.7,
    );
    let gauss = (
        (0u8..4, 0.0f64..1.0, 0u8..4, 0.0f64..1.0, 0.5f64..6.0),
        prop::array::uniform4(-1.0f64..1.0),
        prop::array::uniform3(-3.5f64..-0.5),
    );
    let cot = (
        prop::array::uniform2(-1.0f64..1.0),
        prop::array::uniform3(-1.0f64..1.0),
        -1.0f64..1.0,
    );
    (cam, gauss, cot).prop_filter_map(
        "degenerate quaternion",
        |(
            (q, t, fx, aspect, w, h, pcx, pcy),
            ((rx, tx_, ry, ty_, z), quat, log_scale),
            (vm, vc, vd),
        )| {
            let qn = DQuat::from_xyzw(q[1], q[2], q[3], q[0]);
            let quat_norm = quat.iter().map(|v| v * v).sum::<f64>().sqrt();
            if qn.length() < 0.1 || quat_norm < 0.1 {
                return None;
            }
            let k = Intrinsics {
                fx,
                fy: fx * aspect,
                cx: pcx * w as f64,
                cy: pcy * h as f64,
                width: w,
                height: h,
            };
            let rot = DMat3::from_quat(qn.normalize());
            let camera = Camera::from_rotation_center(k, rot, DVec3::from(t));
            let (wf, hf) = (w as f64, h as f64);
            let tan_x = 0.5 * wf / k.fx;
            let tan_y = 0.5 * hf / k.fy;
            let ux = place(
                rx,
                tx_,
                k.cx / k.fx + 0.3 * tan_x,
                (wf - k.cx) / k.fx + 0.3 * tan_x,
            );
            let uy = place(
                ry,
                ty_,
                k.cy / k.fy + 0.3 * tan_y,
                (hf - k.cy) / k.fy + 0.3 * tan_y,
            );
            let p_cam = DVec3::new(ux * z, uy * z, z);
            let mean = camera
                .world_from_camera()
                .transform_point3(p_cam)
                .to_array();
            Some(Case {
                camera,
                mean,
                quat,
                log_scale,
                v_mean2d: vm,
                v_conic: vc,
                v_depth: vd,
            })
        },
    )
}

/// The scalar whose gradient the backward computes: the cotangents dotted with the outputs.
fn loss(c: &Case, mean: [f64; 3], quat: [f64; 4], log_scale: [f64; 3]) -> f64 {
    let p = project(
        &c.camera,
        &[mean],
        &[quat],
        &[log_scale],
        &ProjectSettings::default(),
    );
    let m = p.means2d[0];
    let k = p.conics[0];
    c.v_mean2d[0] * m[0]
        + c.v_mean2d[1] * m[1]
        + c.v_conic[0] * k[0]
        + c.v_conic[1] * k[1]
        + c.v_conic[2] * k[2]
        + c.v_depth * p.depths[0]
}

/// Central difference of `loss` in one of the ten parameters (means 0..3, quat 3..7,
/// log-scale 7..10).
fn central_difference(c: &Case, param: usize, h: f64) -> f64 {
    let eval = |delta: f64| {
        let (mut m, mut q, mut s) = (c.mean, c.quat, c.log_scale);
        match param {
            0..=2 => m[param] += delta,
            3..=6 => q[param - 3] += delta,
            _ => s[param - 7] += delta,
        }
        loss(c, m, q, s)
    };
    (eval(h) - eval(-h)) / (2.0 * h)
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 256,
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource("proptest-regressions"))),
        ..ProptestConfig::default()
    })]

    /// Analytic gradients against central differences in f64.
    ///
    /// Discontinuities are avoided by construction: the view-space position is drawn at least
    /// 5% of the clamp bound away from the EWA clamp (inside it or beyond it on either side),
    /// the determinant clamp at 1e-10 is never reached (the dilation alone gives det >= 0.09),
    /// and the loss is built from means2d, conics and depths, which are computed for culled
    /// Gaussians too, so the integer radii and the culling decision (which carry no gradient)
    /// never enter it. A culled case checks that its gradient is zero instead.
    ///
    /// Step h = 1e-5 times the parameter scale: the truncation error is h^2/6 |f'''| (about
    /// 1e-10 relative for the smooth rational functions here) and the rounding error is
    /// eps |f| / h (about 1e-11 relative), so the difference quotient is good to ~1e-9 of
    /// the gradient's magnitude; 1e-6 leaves three orders of margin and still catches any
    /// wrong term, which would show at 1e-2 or more.
    #[test]
    fn backward_matches_central_differences(c in case_strategy()) {
        let s = ProjectSettings::default();
        let p = project(&c.camera, &[c.mean], &[c.quat], &[c.log_scale], &s);
        let g = project_backward(
            &c.camera, &[c.mean], &[c.quat], &[c.log_scale], &s, &p,
            &[c.v_mean2d], &[c.v_conic], &[c.v_depth],
        );
        let analytic: Vec<f64> = g.means[0].iter().chain(&g.quats[0]).chain(&g.log_scales[0])
            .copied().collect();
        if !p.is_visible(0) {
            prop_assert!(analytic.iter().all(|&v| v == 0.0));
            return Ok(());
        }
        let scale = [c.mean.iter().fold(1.0f64, |m, v| m.max(v.abs())); 3].into_iter()
            .chain([c.quat.iter().fold(0.0f64, |m, v| m.max(v.abs())); 4])
            .chain([1.0; 3]);
        let numeric: Vec<f64> = scale.enumerate()
            .map(|(i, sc)| central_difference(&c, i, 1e-5 * sc))
            .collect();
        let err = max_rel_err(&analytic, &numeric);
        prop_assert!(err <= 1e-6, "relative error {err:.3e}\nanalytic {analytic:?}\nnumeric {numeric:?}");
    }
}

/// The f32 backward against the f64 oracle, with the forward's tolerance and reasoning: a few
/// dozen f32 operations through the 2x2 inverse and the Jacobian give errors below 1e-6 here
/// (printed); 1e-5 leaves a factor 10, and a formula error would show at 1e-3 or more.
#[test]
fn backward_in_f32_is_close_to_oracle() {
    let f = fixture();
    for case in CASES {
        let x = inputs(&f, case);
        let c32 = |v: &[[f64; 3]]| v.iter().map(|r| r.map(|a| a as f32)).collect::<Vec<_>>();
        let means = c32(&x.means);
        let scales = c32(&x.log_scales);
        let quats: Vec<[f32; 4]> = x.quats.iter().map(|r| r.map(|a| a as f32)).collect();
        let s = ProjectSettings::default();
        let p = project(&x.camera, &means, &quats, &scales, &s);
        let v_m: Vec<[f32; 2]> = rows::<2>(&f, &format!("{case}.grad.means2d"))
            .iter()
            .map(|r| r.map(|a| a as f32))
            .collect();
        let v_c = c32(&rows::<3>(&f, &format!("{case}.grad.conics")));
        let zeros = vec![0.0f32; means.len()];
        let g = project_backward(
            &x.camera, &means, &quats, &scales, &s, &p, &v_m, &v_c, &zeros,
        );
        let up = |v: Vec<f32>| v.into_iter().map(f64::from).collect::<Vec<_>>();
        let a_q = up(g.quats.iter().flatten().copied().collect());
        let a_s = up(g.log_scales.iter().flatten().copied().collect());
        let e_q = flat(&rows::<4>(&f, &format!("{case}.grad.quats")));
        let e_s = flat(&rows::<3>(&f, &format!("{case}.grad.log_scales")));
        assert_close_verbose(&format!("{case} f32 grad.quats"), &a_q, &e_q, 1e-5);
        assert_close_verbose(&format!("{case} f32 grad.log_scales"), &a_s, &e_s, 1e-5);
    }
}
