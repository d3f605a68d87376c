//! The convolution engine on shapes that span several tiles and images: against a direct
//! (quadruple-loop) convolution in `f64`, and bitwise identical for any number of threads, with
//! each GEMM backend and each 3x3 algorithm.

mod common;

use common::*;
use ndarray::{Array1, Array4};
use nets::conv::*;
use nets::matmul::{with_backend, GemmBackend};

const BACKENDS: [GemmBackend; 2] = [GemmBackend::MatrixMultiply, GemmBackend::Gemm];

/// Direct 3x3 convolution with reflection padding, written independently of the engine.
fn direct_conv3x3(x: &Array4<f64>, w: &Array4<f64>, b: &Array1<f64>) -> Array4<f64> {
    let (n, c, h, wd) = x.dim();
    let o = w.dim().0;
    let refl = |i: isize, len: usize| -> usize {
        if i < 0 {
            (-i) as usize
        } else if i as usize >= len {
            2 * len - 2 - i as usize
        } else {
            i as usize
        }
    };
    Array4::from_shape_fn((n, o, h, wd), |(img, oc, y, xx)| {
        let mut acc = b[oc];
        for ci in 0..c {
            for i in 0..3 {
                for j in 0..3 {
                    let yy = refl(y as isize + i as isize - 1, h);
                    let xs = refl(xx as isize + j as isize - 1, wd);
                    acc += w[[oc, ci, i, j]] * x[[img, ci, yy, xs]];
                }
            }
        }
        acc
    })
}

#[test]
fn multi_tile_convolution_matches_a_direct_convolution() {
    for backend in BACKENDS {
        with_backend(backend, check_multi_tile_convolution);
    }
}

fn check_multi_tile_convolution() {
    // 70 rows of 40 pixels: 51 rows per tile, so two tiles per image, two images.
    let mut rng = TestRng::new(7);
    let x = rng.array4((2, 5, 70, 40));
    let w = rng.array4((6, 5, 3, 3));
    let b = rng.array1(6);
    let y = conv3x3_reflect(x.view(), w.view(), b.view(), false);
    let want = direct_conv3x3(&x, &w, &b);
    let err = dsgs_testkit::max_rel_err(&to_f64(&y), &to_f64(&want));
    assert!(err <= 1e-13, "multi-tile conv error {err:.2e}");
    // The backward passes are adjoint to the forward: <dy, conv(x) - b> = <conv^T dy, x> and
    // the weight gradient pairs with w the same way.
    let dy = rng.array4(y.dim());
    let dx = conv3x3_reflect_backward_input(dy.view(), w.view());
    let (dw, db) = conv3x3_reflect_backward_params(x.view(), dy.view());
    let lin = dot(
        &(&y - &b.view().into_shape_with_order((1, 6, 1, 1)).unwrap()),
        &dy,
    );
    assert!((lin - dot(&dx, &x)).abs() <= 1e-11 * lin.abs().max(1.0));
    assert!((lin - dot(&dw, &w)).abs() <= 1e-11 * lin.abs().max(1.0));
    let db_want: Vec<f64> = (0..6)
        .map(|o| dy.slice(ndarray::s![.., o, .., ..]).sum())
        .collect();
    assert!(dsgs_testkit::max_rel_err(&db.to_vec(), &db_want) <= 1e-13);
}

/// Winograd F(2x2, 3x3), forced in `f64`, on odd sizes (partial edge tiles) and enough channels
/// that an image splits into several jobs, one of them starting inside a tile row: the forward
/// pass (with bias and ReLU) equals the direct convolution, the input gradient is its adjoint,
/// and so is the weight gradient (and it equals the direct implicit GEMM's).
/// The transforms only add up to four terms per axis and the kernel transform is rounded once,
/// so in `f64` an output carries a few more roundings of its partial sums than the direct
/// sum's; 1e-13 of the largest output bounds that with a margin of about 70 at these sizes
/// (measured 1.4e-15).
#[test]
fn winograd_matches_the_direct_convolution() {
    let mut rng = TestRng::new(5);
    let x = rng.array4((2, 48, 69, 39));
    let w = rng.array4((64, 48, 3, 3));
    let b = rng.array1(64);
    assert!(nets::winograd::tiles_per_job::<f64>(48, 64) < 35 * 20);
    let want = direct_conv3x3(&x, &w, &b);
    for backend in BACKENDS {
        with_backend(backend, || {
            with_algorithm(ConvAlgorithm::Winograd, || {
                let y = conv3x3_reflect(x.view(), w.view(), b.view(), true);
                let relu = want.mapv(|v| v.max(0.0));
                let err = dsgs_testkit::max_rel_err(&to_f64(&y), &to_f64(&relu));
                assert!(err <= 1e-13, "{backend:?}: winograd conv error {err:.2e}");
                let y = conv3x3_reflect(x.view(), w.view(), b.view(), false);
                let dy = rng.array4(y.dim());
                let dx = conv3x3_reflect_backward_input(dy.view(), w.view());
                let lin = dot(
                    &(&y - &b.view().into_shape_with_order((1, 64, 1, 1)).unwrap()),
                    &dy,
                );
                assert!((lin - dot(&dx, &x)).abs() <= 1e-11 * lin.abs().max(1.0));
                let (dw, db) = conv3x3_reflect_backward_params(x.view(), dy.view());
                let (dw_direct, db_direct) = with_algorithm(ConvAlgorithm::Direct, || {
                    conv3x3_reflect_backward_params(x.view(), dy.view())
                });
                assert!((lin - dot(&dw, &w)).abs() <= 1e-11 * lin.abs().max(1.0));
                let err = dsgs_testkit::max_rel_err(&to_f64(&dw), &to_f64(&dw_direct));
                assert!(
                    err <= 1e-13,
                    "{backend:?}: winograd weight gradient error {err:.2e}"
                );
                assert_eq!(db, db_direct);
            })
        });
    }
}

fn run_all(x: &Array4<f32>, w: &Array4<f32>, b: &Array1<f32>, dy: &Array4<f32>) -> Vec<Vec<f32>> {
    let y = conv3x3_reflect(x.view(), w.view(), b.view(), true);
    let dx = conv3x3_reflect_backward_input(dy.view(), w.view());
    let (dw, db) = conv3x3_reflect_backward_params(x.view(), dy.view());
    let w1 = w.slice(ndarray::s![.., .., 1..2, 1..2]).to_owned();
    let y1 = conv1x1(x.view(), w1.view(), b.view(), false);
    let (dw1, _) = conv1x1_backward_params(x.view(), dy.view());
    [y, dx, dw, y1, dw1]
        .iter()
        .map(|a| a.iter().copied().collect())
        .chain(std::iter::once(db.to_vec()))
        .collect()
}

#[test]
fn results_are_bitwise_identical_for_any_thread_count() {
    let mut rng = TestRng::new(11);
    let f = |a: Array4<f64>| a.mapv(|v| v as f32);
    let x = f(rng.array4((2, 24, 70, 40)));
    let w = f(rng.array4((16, 24, 3, 3)));
    let b = rng.array1(16).mapv(|v| v as f32);
    let dy = f(rng.array4((2, 16, 70, 40)));
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    for algorithm in [ConvAlgorithm::Direct, ConvAlgorithm::Winograd] {
        for backend in BACKENDS {
            let run = |n| {
                pool(n).install(|| {
                    with_algorithm(algorithm, || {
                        with_backend(backend, || run_all(&x, &w, &b, &dy))
                    })
                })
            };
            let (one, three) = (run(1), run(3));
            for (i, (a, c)) in one.iter().zip(&three).enumerate() {
                assert!(
                    a.iter().zip(c).all(|(p, q)| p.to_bits() == q.to_bits()),
                    "{algorithm:?}, {backend:?}: output {i} differs between 1 and 3 threads"
                );
            }
        }
    }
}
