//! Spherical-harmonic colours against the float64 oracle and against central differences.

mod oracle_case;

use dsgs_testkit::{assert_close_verbose, max_rel_err, Fixture};
use gaussian::sh::{eval_bases, num_bases, sh_colors, sh_colors_backward};
use oracle_case::{camera, fixture, flat, rows};
use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;

/// Float64 against float64 with the same operations up to association: 1e-9 leaves orders of
/// magnitude of room for rounding while any wrong constant or sign shows at 1e-3 or more.
const TOL_F64: f64 = 1e-9;

/// The sh3 case: the camera centre, the means and the SH coefficients (degree 3, 16 a Gaussian).
fn sh3(f: &Fixture) -> ([f64; 3], Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let center = camera(f, "sh3").center().to_array();
    (center, rows(f, "sh3.means"), rows(f, "sh3.sh_coeffs"))
}

#[test]
fn sh3_colors_match_oracle() {
    let f = fixture();
    let (center, means, sh) = sh3(&f);
    assert_eq!(f.get("sh3.sh_degree").scalar(), 3.0);
    let colors = sh_colors(3, 16, &sh, &means, center);
    let expected = rows::<3>(&f, "sh3.colors");
    assert_close_verbose("sh3 colors", &flat(&colors), &flat(&expected), TOL_F64);
    // The case must exercise the clamp at zero for the mask test below to mean something.
    assert!(expected.iter().flatten().any(|&c| c == 0.0));
}

/// The oracle's SH coefficient gradient is `basis_k(d) * v_colour` (masked by the clamp). The
/// DC basis is the constant C0, so `grad.sh_coeffs[:, 0]` gives the masked colour cotangent;
/// feeding it back must reproduce the gradients of all 15 higher coefficients, which tests
/// every basis function's value and the mask.
#[test]
fn sh3_coefficient_gradients_match_oracle() {
    let f = fixture();
    let (center, means, sh) = sh3(&f);
    let expected = rows::<3>(&f, "sh3.grad.sh_coeffs");
    let c0 = eval_bases::<f64>(1, [0.0, 0.0, 1.0])[0];
    let v_colors: Vec<[f64; 3]> = (0..means.len())
        .map(|i| expected[i * 16].map(|v| v / c0))
        .collect();
    assert!(v_colors.iter().flatten().any(|&v| v != 0.0));
    let (d_sh, _) = sh_colors_backward(3, 16, &sh, &means, center, &v_colors);
    assert_close_verbose(
        "sh3 grad.sh_coeffs",
        &flat(&d_sh),
        &flat(&expected),
        TOL_F64,
    );
}

#[test]
fn lower_active_degree_ignores_higher_coefficients() {
    let (center, means, sh) = sh3(&fixture());
    for degree in 0..3 {
        let nb = num_bases(degree);
        let truncated: Vec<[f64; 3]> = sh.chunks(16).flat_map(|c| c[..nb].to_vec()).collect();
        let a = sh_colors(degree, 16, &sh, &means, center);
        let b = sh_colors(degree, nb, &truncated, &means, center);
        assert_eq!(a, b);
        let v = vec![[1.0, -0.5, 0.25]; means.len()];
        let (d_sh, _) = sh_colors_backward(degree, 16, &sh, &means, center, &v);
        assert!(d_sh
            .chunks(16)
            .all(|c| c[nb..].iter().all(|x| *x == [0.0; 3])));
    }
}

/// Orthonormality of the basis on the sphere, a check independent of the oracle:
/// the integral of `basis_i basis_j` over the unit sphere is `delta_ij`. Integrated with a
/// Gauss-Legendre rule in cos(theta) times a uniform rule in phi, which is exact for the
/// polynomials of degree <= 6 involved (8 nodes in z are exact to degree 15; 16 phi samples
/// integrate trigonometric polynomials of degree < 16 exactly).
#[test]
fn basis_is_orthonormal_on_the_sphere() {
    // 8-point Gauss-Legendre nodes and weights on [-1, 1].
    let nodes: [(f64, f64); 4] = [
        (0.1834346424956498, 0.362683783378362),
        (0.525532409916329, 0.3137066458778873),
        (0.7966664774136267, 0.2223810344533745),
        (0.9602898564975363, 0.1012285362903763),
    ];
    let n_phi = 16;
    let mut gram = [[0.0f64; 16]; 16];
    for &(z0, w) in &nodes {
        for z in [z0, -z0] {
            for k in 0..n_phi {
                let phi = std::f64::consts::TAU * k as f64 / n_phi as f64;
                let r = (1.0 - z * z).sqrt();
                let b = eval_bases(16, [r * phi.cos(), r * phi.sin(), z]);
                let dw = w * std::f64::consts::TAU / n_phi as f64;
                for i in 0..16 {
                    for j in 0..16 {
                        gram[i][j] += dw * b[i] * b[j];
                    }
                }
            }
        }
    }
    for (i, row) in gram.iter().enumerate() {
        for (j, &g) in row.iter().enumerate() {
            let e = if i == j { 1.0 } else { 0.0 };
            // The constants are printed to ~15 digits in the reference.
            assert!((g - e).abs() < 1e-12, "<b{i}, b{j}> = {g}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Central differences.

#[derive(Clone, Debug)]
struct Case {
    degree: usize,
    stored: usize,
    sh: Vec<[f64; 3]>,
    mean: [f64; 3],
    center: [f64; 3],
    v: [f64; 3],
}

fn case_strategy() -> impl Strategy<Value = Case> {
    (0usize..4, 0usize..4)
        .prop_flat_map(|(degree, extra)| {
            let stored = (degree + extra).min(3);
            (
                Just(degree),
                Just(stored),
                prop::collection::vec(prop::array::uniform3(-0.6f64..0.6), num_bases(stored)),
                prop::array::uniform3(-2.0f64..2.0),
                prop::array::uniform3(-2.0f64..2.0),
                prop::array::uniform3(-1.0f64..1.0),
            )
        })
        .prop_map(|(degree, stored, sh, mean, center, v)| Case {
            degree,
            stored,
            sh,
            mean,
            center,
            v,
        })
}

fn loss(c: &Case, sh: &[[f64; 3]], mean: [f64; 3]) -> f64 {
    let col = sh_colors(c.degree, num_bases(c.stored), sh, &[mean], c.center);
    (0..3).map(|k| c.v[k] * col[0][k]).sum()
}

fn raw_colour(c: &Case) -> [f64; 3] {
    let d: [f64; 3] = std::array::from_fn(|a| c.mean[a] - c.center[a]);
    let n = d.iter().map(|v| v * v).sum::<f64>().sqrt();
    let b = eval_bases(num_bases(c.degree), d.map(|v| v / n));
    std::array::from_fn(|ch| {
        (0..num_bases(c.degree))
            .map(|k| b[k] * c.sh[k][ch])
            .sum::<f64>()
            + 0.5
    })
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 512,
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource("proptest-regressions"))),
        ..ProptestConfig::default()
    })]

    /// Analytic SH gradients against central differences in f64, for active degrees 0..=3 and
    /// stored degrees at or above them.
    ///
    /// The kink of max(., 0) is avoided by rejecting cases with a pre-clamp colour within 0.02
    /// of zero (a step of 1e-6 moves it by far less), and the mean is kept at least 0.2 from the
    /// camera centre so the direction is well conditioned. Both sides of the kink are still
    /// drawn, so the mask is tested too.
    ///
    /// Step 1e-6: the colour is linear in the coefficients (exact differences up to rounding)
    /// and a polynomial of degree <= 3 in the unit direction, whose third derivative w.r.t. the
    /// mean is O(1/|d|^3) <= ~1e3 here; truncation h^2/6 * 1e3 ~ 2e-10 and rounding
    /// eps / h ~ 1e-10 against gradients of order 0.1..1, so 1e-6 has wide margin.
    #[test]
    fn backward_matches_central_differences(c in case_strategy()) {
        let dist = (0..3).map(|a| (c.mean[a] - c.center[a]).powi(2)).sum::<f64>().sqrt();
        prop_assume!(dist > 0.2);
        prop_assume!(raw_colour(&c).iter().all(|r| r.abs() > 0.02));
        let k = num_bases(c.stored);
        let (d_sh, d_mean) = sh_colors_backward(c.degree, k, &c.sh, &[c.mean], c.center, &[c.v]);
        let h = 1e-6;
        let mut numeric = Vec::new();
        for i in 0..k {
            for ch in 0..3 {
                let mut plus = c.sh.clone();
                let mut minus = c.sh.clone();
                plus[i][ch] += h;
                minus[i][ch] -= h;
                numeric.push((loss(&c, &plus, c.mean) - loss(&c, &minus, c.mean)) / (2.0 * h));
            }
        }
        for a in 0..3 {
            let mut plus = c.mean;
            let mut minus = c.mean;
            plus[a] += h;
            minus[a] -= h;
            numeric.push((loss(&c, &c.sh, plus) - loss(&c, &c.sh, minus)) / (2.0 * h));
        }
        let analytic: Vec<f64> = flat(&d_sh).into_iter().chain(d_mean[0]).collect();
        let err = max_rel_err(&analytic, &numeric);
        prop_assert!(err <= 1e-6, "relative error {err:.3e}\nanalytic {analytic:?}\nnumeric {numeric:?}");
    }
}
