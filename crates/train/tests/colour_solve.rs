//! The closed-form colour fit of a bake (`train::colour_solve`) on small scenes in `f64`:
//! it recovers colours that generated the targets exactly, it equals the dense least-squares
//! solution of the normal equations built column by column from the rasterizer (at degree 0,
//! and at degree 1 with its ridge, the columns from the renderer's SH path), through the
//! views' blend weights and through the rasterizer alike, it leaves Gaussians no view sees
//! alone, and it gives the same bits for any number of threads.

use gaussian::{camera_path::look_at, Camera, FeatureGaussians, Intrinsics, Real};
use glam::DVec3;
use raster::{render, Channels, RenderOptions};
use train::colour_solve::{solve_colours, SolveSettings, SolveTarget, DEFAULT_WEIGHTS_BUDGET};

/// A small deterministic generator in `[0, 1)`.
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// `n` Gaussians in a cube around the origin, some translucent, sizes large enough to overlap.
fn scene<T: Real>(n: usize, seed: u64) -> FeatureGaussians<T> {
    let mut r = Lcg(seed);
    let mut s = FeatureGaussians::<T> {
        sh_degree: 0,
        ..Default::default()
    };
    for _ in 0..n {
        let p = [0, 1, 2].map(|_| T::lit(1.2 * r.next() - 0.6));
        s.means.push(p);
        s.log_scales
            .push([0, 1, 2].map(|_| T::lit(-1.6 + 0.6 * r.next())));
        s.quats.push([0, 1, 2, 3].map(|_| T::lit(r.next() - 0.3)));
        s.opacity_logits.push(T::lit(3.0 * r.next() - 1.0));
        s.sh.push([T::zero(); 3]);
    }
    s
}

/// `k` 20x20 cameras on a ring looking at the origin.
fn cameras(k: usize) -> Vec<Camera> {
    let intr = Intrinsics {
        fx: 24.0,
        fy: 24.0,
        cx: 10.0,
        cy: 10.0,
        width: 20,
        height: 20,
    };
    (0..k)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / k as f64;
            let eye = DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 1.0 + 0.3 * (i % 2) as f64);
            look_at(intr, eye, DVec3::ZERO, DVec3::Z).unwrap()
        })
        .collect()
}

/// The image of `scene` with per-Gaussian `colours` over `background`, as the linear model sees
/// it (colours as a 3-channel feature).
fn image<T: Real>(
    scene: &FeatureGaussians<T>,
    colours: &[[T; 3]],
    camera: &Camera,
    background: [T; 3],
) -> Vec<T> {
    let s = FeatureGaussians {
        feature_dim: 3,
        features: colours.iter().flatten().copied().collect(),
        ..scene.clone()
    };
    render(
        camera,
        &s,
        &RenderOptions::new(Channels::Features, background.to_vec()),
    )
    .unwrap()
    .raster
    .image
}

/// Enough iterations to converge to rounding on these small scenes.
const EXACT: SolveSettings = SolveSettings {
    iterations: 20_000,
    tolerance: 1e-12,
    degree: 0,
    ridge: 0.1,
    weights_budget: DEFAULT_WEIGHTS_BUDGET,
};

/// [`EXACT`] with no room for blend weights: every pass through the rasterizer.
const EXACT_RASTER: SolveSettings = SolveSettings {
    weights_budget: 0,
    ..EXACT
};

fn targets<'a, T>(cams: &'a [Camera], images: &'a [Vec<T>]) -> Vec<SolveTarget<'a, T>> {
    cams.iter()
        .zip(images)
        .map(|(camera, image)| SolveTarget {
            camera,
            image: image.as_slice(),
        })
        .collect()
}

#[test]
fn colours_that_made_the_targets_are_recovered() {
    let (n, bg) = (12, [0.2, 0.5, 0.9]);
    let s = scene::<f64>(n, 3);
    let cams = cameras(6);
    let mut r = Lcg(11);
    let truth: Vec<[f64; 3]> = (0..n).map(|_| [0, 1, 2].map(|_| r.next())).collect();
    let images: Vec<Vec<f64>> = cams.iter().map(|c| image(&s, &truth, c, bg)).collect();
    let start = vec![[0.5; 3]; n];
    let out = solve_colours(&s, &targets(&cams, &images), bg, &start, EXACT).unwrap();
    assert_eq!(out.unseen, 0);
    // The colours agree to the stopping tolerance amplified by the system's condition.
    for (a, b) in out.colours.iter().zip(&truth) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-7, "{a:?} vs {b:?}");
        }
    }
    assert!(
        out.energy[1] < 1e-20 * out.energy[0].max(1.0),
        "{:?}",
        out.energy
    );
    assert!(out.residuals.windows(2).all(|w| w[1].is_finite()));
}

/// The normal equations built from the rasterizer one Gaussian at a time (column `i` of `A` is
/// the image of Gaussian `i` alone at unit colour, the others at zero, over a black
/// background) and solved densely by Gaussian elimination: the solve's colours are that
/// solution, for targets no colours reproduce exactly (the images of colours in [0.3, 0.7] plus
/// noise of up to 0.05, whose least-squares colours stay positive, so that the non-negative
/// solution the solve finds is the unconstrained one).
#[test]
fn the_solve_is_the_dense_least_squares_solution() {
    let (n, bg) = (10, [0.1, 0.0, 0.3]);
    let s = scene::<f64>(n, 5);
    let cams = cameras(5);
    let mut r = Lcg(17);
    let truth: Vec<[f64; 3]> = (0..n)
        .map(|_| [0, 1, 2].map(|_| 0.3 + 0.4 * r.next()))
        .collect();
    let images: Vec<Vec<f64>> = cams
        .iter()
        .map(|c| {
            image(&s, &truth, c, bg)
                .into_iter()
                .map(|v| v + 0.1 * (r.next() - 0.5))
                .collect()
        })
        .collect();
    // Through the blend weights and through the rasterizer.
    let outs = [EXACT, EXACT_RASTER].map(|settings| {
        solve_colours(
            &s,
            &targets(&cams, &images),
            bg,
            &vec![[0.0; 3]; n],
            settings,
        )
        .unwrap()
    });
    let mut positive = 0;
    for ch in 0..3 {
        // Columns of A for this channel (every view stacked), and rhs = y - T b.
        let mut cols = Vec::new();
        for i in 0..n {
            let mut c = vec![[0.0; 3]; n];
            c[i] = [1.0; 3];
            let col: Vec<f64> = cams
                .iter()
                .flat_map(|cam| image(&s, &c, cam, [0.0; 3]))
                .skip(ch)
                .step_by(3)
                .collect();
            cols.push(col);
        }
        let tb: Vec<f64> = cams
            .iter()
            .flat_map(|cam| image(&s, &vec![[0.0; 3]; n], cam, bg))
            .skip(ch)
            .step_by(3)
            .collect();
        let y: Vec<f64> = images
            .iter()
            .flatten()
            .copied()
            .skip(ch)
            .step_by(3)
            .collect();
        let rhs: Vec<f64> = y.iter().zip(&tb).map(|(a, b)| a - b).collect();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let normal: Vec<Vec<f64>> = (0..n)
            .map(|i| (0..n).map(|j| dot(&cols[i], &cols[j])).collect())
            .collect();
        let b: Vec<f64> = cols.iter().map(|c| dot(c, &rhs)).collect();
        let x = dense_solve(normal, &b);
        for (i, &xi) in x.iter().enumerate() {
            let want = xi;
            positive += usize::from(xi > 0.0);
            for out in &outs {
                assert!(
                    (out.colours[i][ch] - want).abs() < 1e-7 * (1.0 + want.abs()),
                    "Gaussian {i} channel {ch}: {} vs {want}",
                    out.colours[i][ch]
                );
            }
        }
    }
    // The least-squares solution is positive, so the constraint is not what the two share.
    assert_eq!(positive, 3 * n);
}

#[test]
fn gaussians_no_view_sees_keep_their_colour() {
    let (n, bg) = (9, [0.0; 3]);
    let mut s = scene::<f64>(n, 7);
    // Gaussian 0 far outside every camera's view (above the ring, behind the up axis).
    s.means[0] = [0.0, 0.0, 40.0];
    let cams = cameras(4);
    let images: Vec<Vec<f64>> = cams.iter().map(|_| vec![0.4; 20 * 20 * 3]).collect();
    let start: Vec<[f64; 3]> = (0..n).map(|i| [0.1 * i as f64, 0.2, 0.3]).collect();
    let out = solve_colours(&s, &targets(&cams, &images), bg, &start, EXACT).unwrap();
    assert_eq!(out.unseen, 1);
    assert_eq!(out.colours[0], start[0]);
    assert!(out.energy[1] < out.energy[0]);
}

#[test]
fn the_solve_is_the_same_for_any_number_of_threads() {
    let (n, bg) = (40, [0.3f32, 0.3, 0.3]);
    let s = scene::<f32>(n, 9);
    let cams = cameras(3);
    let mut r = Lcg(23);
    let images: Vec<Vec<f32>> = cams
        .iter()
        .map(|_| (0..20 * 20 * 3).map(|_| r.next() as f32).collect())
        .collect();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                solve_colours(
                    &s,
                    &targets(&cams, &images),
                    bg,
                    &vec![[0.5; 3]; n],
                    // Through the rasterizer (the degree-1 test below goes through the weights).
                    SolveSettings {
                        weights_budget: 0,
                        ..SolveSettings::default()
                    },
                )
                .unwrap()
            })
    };
    let one = run(1);
    // Random targets pull some colours to the constraint; none goes below it.
    assert!(one.colours.iter().flatten().all(|&c| c >= 0.0));
    assert!(one.energy[1] < one.energy[0]);
    for t in [2, 3] {
        let other = run(t);
        assert_eq!(other.iterations, one.iterations);
        let bits = |o: &train::colour_solve::SolveOutcome<f32>| -> Vec<u32> {
            o.colours.iter().flatten().map(|v| v.to_bits()).collect()
        };
        assert_eq!(bits(&other), bits(&one), "{t} threads");
    }
}

#[test]
fn bad_inputs_are_refused() {
    let s = scene::<f64>(3, 1);
    let cams = cameras(1);
    let short = vec![0.0; 10];
    let t = [SolveTarget {
        camera: &cams[0],
        image: short.as_slice(),
    }];
    let e = solve_colours(&s, &t, [0.0; 3], &[[0.0; 3]; 3], EXACT).unwrap_err();
    assert!(e.to_string().contains("10 values"), "{e}");
    let good = vec![0.0; 20 * 20 * 3];
    let t = [SolveTarget {
        camera: &cams[0],
        image: good.as_slice(),
    }];
    let e = solve_colours(&s, &t, [0.0; 3], &[[0.0; 3]; 2], EXACT).unwrap_err();
    assert!(e.to_string().contains("2 initial colours"), "{e}");
    assert!(solve_colours(&s, &[], [0.0; 3], &[[0.0; 3]; 3], EXACT).is_err());
}

/// The colour render of `scene` at SH degree 1 with coefficients `sh` (four RGB triples per
/// Gaussian) over `background`: the renderer's own SH path.
fn sh_image(
    scene: &FeatureGaussians<f64>,
    sh: &[[f64; 3]],
    camera: &Camera,
    background: [f64; 3],
) -> Vec<f64> {
    let s = FeatureGaussians {
        sh_degree: 1,
        sh: sh.to_vec(),
        ..scene.clone()
    };
    render(
        camera,
        &s,
        &RenderOptions::new(Channels::Color { sh_degree: 1 }, background.to_vec()),
    )
    .unwrap()
    .raster
    .image
}

/// The solution of the dense system `a x = b` by Gaussian elimination with partial pivoting.
fn dense_solve(mut a: Vec<Vec<f64>>, b: &[f64]) -> Vec<f64> {
    let n = b.len();
    for (row, &v) in a.iter_mut().zip(b) {
        row.push(v);
    }
    for k in 0..n {
        let p = (k..n)
            .max_by(|&x, &y| a[x][k].abs().total_cmp(&a[y][k].abs()))
            .unwrap();
        a.swap(k, p);
        assert!(a[k][k].abs() > 1e-9, "the test scene's system is singular");
        let pivot = a[k].clone();
        for row in a.iter_mut().skip(k + 1) {
            let f = row[k] / pivot[k];
            for (x, y) in row.iter_mut().zip(&pivot).skip(k) {
                *x -= f * y;
            }
        }
    }
    let mut x = vec![0.0; n];
    for k in (0..n).rev() {
        x[k] = (a[k][n] - (k + 1..n).map(|j| a[k][j] * x[j]).sum::<f64>()) / a[k][k];
    }
    x
}

const C0: f64 = 0.2820947917738781;

/// At degree 1 the solve is the dense solution of the ridge-regularised normal equations whose
/// columns come from the renderer's SH colour path, one unknown at a time: the column of a
/// Gaussian's colour is its image at unit colour (the others black), the column of its degree-1
/// coefficient `k` is its image with that coefficient at 1 less its image with all zero (the
/// colour stays inside `(0, 1)`, so the renderer's clamp never acts and the difference is
/// exactly the linear term). The targets are degree-1 renders plus noise, with colours in
/// `[0.3, 0.7]` so that the constraint is not active.
#[test]
fn at_degree_one_the_solve_is_the_dense_ridge_least_squares_solution() {
    let (n, bg) = (8, [0.1, 0.0, 0.3]);
    let ridge = 0.05;
    let s = scene::<f64>(n, 13);
    let cams = cameras(7);
    let mut r = Lcg(29);
    // SH coefficients: DC for a colour in [0.3, 0.7], degree 1 up to 0.15.
    let truth: Vec<[f64; 3]> = (0..n)
        .flat_map(|_| {
            let dc = [0, 1, 2].map(|_| (0.3 + 0.4 * r.next() - 0.5) / C0);
            let rest: Vec<[f64; 3]> = (0..3)
                .map(|_| [0, 1, 2].map(|_| 0.3 * r.next() - 0.15))
                .collect();
            std::iter::once(dc).chain(rest)
        })
        .collect();
    let images: Vec<Vec<f64>> = cams
        .iter()
        .map(|c| {
            sh_image(&s, &truth, c, bg)
                .into_iter()
                .map(|v| v + 0.05 * (r.next() - 0.5))
                .collect()
        })
        .collect();
    // Through the blend weights and through the rasterizer.
    let outs = [EXACT, EXACT_RASTER].map(|exact| {
        let settings = SolveSettings {
            degree: 1,
            ridge,
            ..exact
        };
        solve_colours(
            &s,
            &targets(&cams, &images),
            bg,
            &vec![[0.0; 3]; n],
            settings,
        )
        .unwrap()
    });
    for out in &outs {
        assert_eq!(out.degree_one.len(), n);
        assert_eq!(out.unseen, 0);
    }

    // The colour that an all-zero SH renders (0.5 per Gaussian over the background) is the
    // offset of the columns of the degree-1 unknowns.
    let zero_sh = vec![[0.0; 3]; 4 * n];
    let offset: Vec<f64> = cams
        .iter()
        .flat_map(|c| sh_image(&s, &zero_sh, c, [0.0; 3]))
        .collect();
    for ch in 0..3 {
        let channel = |v: Vec<f64>| -> Vec<f64> { v.into_iter().skip(ch).step_by(3).collect() };
        let mut cols = Vec::new();
        let mut total_weight = Vec::new();
        for i in 0..n {
            let mut c = vec![[0.0; 3]; n];
            c[i] = [1.0; 3];
            let col = channel(
                cams.iter()
                    .flat_map(|cam| image(&s, &c, cam, [0.0; 3]))
                    .collect(),
            );
            total_weight.push(col.iter().sum::<f64>());
            cols.push(col);
            for k in 1..4 {
                let mut sh = zero_sh.clone();
                sh[4 * i + k] = [1.0; 3];
                let with: Vec<f64> = cams
                    .iter()
                    .flat_map(|cam| sh_image(&s, &sh, cam, [0.0; 3]))
                    .zip(&offset)
                    .map(|(a, b)| a - b)
                    .collect();
                cols.push(channel(with));
            }
        }
        let tb = channel(
            cams.iter()
                .flat_map(|cam| image(&s, &vec![[0.0; 3]; n], cam, bg))
                .collect(),
        );
        let y = channel(images.iter().flatten().copied().collect());
        let rhs: Vec<f64> = y.iter().zip(&tb).map(|(a, b)| a - b).collect();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let m = cols.len();
        let normal: Vec<Vec<f64>> = (0..m)
            .map(|p| {
                (0..m)
                    .map(|q| {
                        let ridge_term = if p == q && p % 4 != 0 {
                            ridge * total_weight[p / 4]
                        } else {
                            0.0
                        };
                        dot(&cols[p], &cols[q]) + ridge_term
                    })
                    .collect()
            })
            .collect();
        let b: Vec<f64> = cols.iter().map(|c| dot(c, &rhs)).collect();
        let x = dense_solve(normal, &b);
        for i in 0..n {
            let colour = x[4 * i];
            assert!(
                colour > 0.0,
                "a negative least-squares colour: the constraint would act"
            );
            for out in &outs {
                assert!(
                    (out.colours[i][ch] - colour).abs() < 1e-7 * (1.0 + colour.abs()),
                    "Gaussian {i} channel {ch}: colour {} vs {colour}",
                    out.colours[i][ch]
                );
                for k in 1..4 {
                    let want = x[4 * i + k];
                    let got = out.degree_one[i][k - 1][ch];
                    assert!(
                        (got - want).abs() < 1e-7 * (1.0 + want.abs()),
                        "Gaussian {i} channel {ch} coefficient {k}: {got} vs {want}"
                    );
                }
            }
        }
    }
}

/// Targets with view-dependent colour are fitted far better at degree 1 (a light ridge) than at
/// degree 0, and the degree-1 energy (with its ridge) never rises above its start.
#[test]
fn degree_one_fits_view_dependent_targets_better() {
    let (n, bg) = (10, [0.0; 3]);
    let s = scene::<f64>(n, 31);
    let cams = cameras(8);
    let mut r = Lcg(37);
    let truth: Vec<[f64; 3]> = (0..n)
        .flat_map(|_| {
            // Colour 0.5 from every direction, plus up to 0.6 from the degree-1 terms.
            let dc = [0.0; 3];
            let rest: Vec<[f64; 3]> = (0..3)
                .map(|_| [0, 1, 2].map(|_| 0.8 * r.next() - 0.4))
                .collect();
            std::iter::once(dc).chain(rest)
        })
        .collect();
    let images: Vec<Vec<f64>> = cams.iter().map(|c| sh_image(&s, &truth, c, bg)).collect();
    let solve = |degree| {
        let settings = SolveSettings {
            degree,
            iterations: 200,
            ridge: 1e-3,
            ..SolveSettings::default()
        };
        solve_colours(
            &s,
            &targets(&cams, &images),
            bg,
            &vec![[0.5; 3]; n],
            settings,
        )
        .unwrap()
    };
    let (zero, one) = (solve(0), solve(1));
    assert!(one.energy[1] <= one.energy[0]);
    assert!(
        one.energy[1] < 0.1 * zero.energy[1],
        "degree 1 {:?}, degree 0 {:?}",
        one.energy,
        zero.energy
    );
}

#[test]
fn degree_one_is_the_same_for_any_number_of_threads() {
    let (n, bg) = (30, [0.3f32, 0.3, 0.3]);
    let s = scene::<f32>(n, 41);
    let cams = cameras(4);
    let mut r = Lcg(43);
    let images: Vec<Vec<f32>> = cams
        .iter()
        .map(|_| (0..20 * 20 * 3).map(|_| r.next() as f32).collect())
        .collect();
    let settings = SolveSettings {
        degree: 1,
        ..SolveSettings::default()
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                solve_colours(
                    &s,
                    &targets(&cams, &images),
                    bg,
                    &vec![[0.5; 3]; n],
                    settings,
                )
                .unwrap()
            })
    };
    let bits = |o: &train::colour_solve::SolveOutcome<f32>| -> Vec<u32> {
        o.colours
            .iter()
            .flatten()
            .chain(o.degree_one.iter().flatten().flatten())
            .map(|v| v.to_bits())
            .collect()
    };
    let one = run(1);
    assert!(one.colours.iter().flatten().all(|&c| c >= 0.0));
    for t in [2, 3] {
        assert_eq!(bits(&run(t)), bits(&one), "{t} threads");
    }
}

#[test]
fn settings_out_of_range_are_refused() {
    let s = scene::<f64>(3, 1);
    let cams = cameras(1);
    let good = vec![0.0; 20 * 20 * 3];
    let t = targets(&cams, std::slice::from_ref(&good));
    for (settings, says) in [
        (SolveSettings { degree: 2, ..EXACT }, "degree 0 or 1"),
        (
            SolveSettings {
                ridge: 0.0,
                ..EXACT
            },
            "ridge",
        ),
        (
            SolveSettings {
                ridge: f64::NAN,
                ..EXACT
            },
            "ridge",
        ),
    ] {
        let e = solve_colours(&s, &t, [0.0; 3], &[[0.0; 3]; 3], settings).unwrap_err();
        assert!(e.to_string().contains(says), "{e}");
    }
}
