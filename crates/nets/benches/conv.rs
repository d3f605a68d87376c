//! One 3x3 reflection-padded convolution at 256x256 for every `(in, out)` width pair of the
//! fullres relu3_1 and relu4_1 encoders and the relu3_1 and relu4_1 decoders, in each pass
//! (forward with bias and ReLU, input gradient, weight and bias gradient) and with each GEMM
//! backend (`gemm` and `matrixmultiply`, see `nets::matmul`), next to the raw `sgemm` of the
//! forward matrix product (`m = out`, `k = 9 * in`, `n = 256 * 256`) with its operands already
//! laid out (no padding, no bias), split into column blocks of 2048 run on the same rayon pool.
//! FLOPs count 2 per multiply-add; every pass has the forward's `2 * out * 9 * in * 256 * 256`.
//!
//! With `NETS_CONV_TABLE=1` it first prints a table of every shape and pass with both backends,
//! timed alternately in the same process (best of `NETS_CONV_REPS`, default 3, runs each), and
//! the ratio of the `gemm` time to the `matrixmultiply` time (`NETS_CONV_PASSES=fwd,dw` restricts
//! it to some passes). With `NETS_CONV_TABLE=algorithms` it prints the same kind of table for the
//! two 3x3 algorithms (`nets::conv::ConvAlgorithm`: direct implicit GEMM and Winograd F(2x2, 3x3)),
//! forward, input gradient and weight gradient, with the default backend. Criterion then times
//! `conv3x3_256/{fwd,dx,dw}_{in}_{out}/{gemm,mm}`, `conv_{in}_{out}` (the forward with the default
//! backend) and `sgemm_{in}_{out}`.

mod common;

use std::time::Instant;

use common::*;
use criterion::{criterion_group, criterion_main, Criterion};
use ndarray::{Array1, Array4};
use nets::conv::{
    conv3x3_reflect, conv3x3_reflect_backward_input, conv3x3_reflect_backward_params,
};
use nets::conv::{with_algorithm, ConvAlgorithm};
use nets::matmul::{with_backend, GemmBackend};
use rayon::prelude::*;

const SIZE: usize = 256;

/// The distinct `(in, out)` widths of the relu4_1 encoder (which contains relu3_1's), then those
/// of the decoders not already listed (the relu4_1 decoder mirrors that encoder, from 512->256,
/// and ends in the relu3_1 decoder).
fn shapes() -> Vec<(usize, usize)> {
    let encoder = conv_shapes("relu4_1");
    let decoder = encoder.iter().rev().map(|&(c, o)| (o, c));
    let mut shapes = Vec::new();
    for s in encoder.iter().copied().chain(decoder) {
        if !shapes.contains(&s) {
            shapes.push(s);
        }
    }
    shapes
}

const BACKENDS: [(GemmBackend, &str); 2] = [
    (GemmBackend::Gemm, "gemm"),
    (GemmBackend::MatrixMultiply, "mm"),
];

const PASSES: [&str; 3] = ["fwd", "dx", "dw"];

/// Columns per block of the raw GEMM.
const BLOCK: usize = 2048;

/// Distinct `B` operands cycled through, so the raw GEMM streams its operand from memory as a
/// convolution does instead of finding it in cache.
const OPERANDS: usize = 8;

/// The raw GEMM `out (o x n) = a (o x 9c) * b (9c x n)`, one column block per task.
fn tiled_sgemm(o: usize, c: usize, a: &[f32], bs: &[Vec<f32>], out: &mut [f32]) {
    let k = 9 * c;
    out.par_chunks_mut(o * BLOCK)
        .enumerate()
        .for_each(|(t, cblock)| unsafe {
            let b = &bs[t % OPERANDS];
            matrixmultiply::sgemm(
                o,
                k,
                BLOCK,
                1.0,
                a.as_ptr(),
                k as isize,
                1,
                b.as_ptr(),
                BLOCK as isize,
                1,
                0.0,
                cblock.as_mut_ptr(),
                BLOCK as isize,
                1,
            );
        });
}

/// The operands of one shape.
struct Case {
    x: Array4<f32>,
    w: Array4<f32>,
    b: Array1<f32>,
    dy: Array4<f32>,
}

impl Case {
    fn new(rng: &mut Lcg, ci: usize, co: usize) -> Case {
        Case {
            x: rng.image(ci, SIZE, SIZE),
            w: Array4::from_shape_vec((co, ci, 3, 3), rng.vec(co * ci * 9, 0.1)).unwrap(),
            b: Array1::from_vec(rng.vec(co, 0.1)),
            dy: rng.image(co, SIZE, SIZE),
        }
    }

    /// Runs one pass with the current backend.
    fn run(&self, pass: &str) {
        match pass {
            "fwd" => {
                std::hint::black_box(conv3x3_reflect(
                    self.x.view(),
                    self.w.view(),
                    self.b.view(),
                    true,
                ));
            }
            "dx" => {
                std::hint::black_box(conv3x3_reflect_backward_input(
                    self.dy.view(),
                    self.w.view(),
                ));
            }
            _ => {
                std::hint::black_box(conv3x3_reflect_backward_params(
                    self.x.view(),
                    self.dy.view(),
                ));
            }
        }
    }
}

fn seconds<F: FnOnce()>(f: F) -> f64 {
    let t = Instant::now();
    f();
    t.elapsed().as_secs_f64()
}

/// The table of both 3x3 algorithms (default backend) for the forward pass, the input gradient
/// and the weight gradient, alternating runs of the two.
fn algorithm_table(rng: &mut Lcg) {
    let reps: usize = std::env::var("NETS_CONV_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    println!(
        "shape     pass  direct s  GFLOP/s  winograd s  GFLOP/s  winograd/direct time  (best of {reps}, alternating)"
    );
    for (ci, co) in shapes() {
        let case = Case::new(rng, ci, co);
        let flop = 2.0 * (co * ci * 9 * SIZE * SIZE) as f64 / 1e9;
        for pass in PASSES {
            let mut best = [f64::INFINITY; 2];
            for _ in 0..reps {
                for (i, algorithm) in [ConvAlgorithm::Direct, ConvAlgorithm::Winograd]
                    .into_iter()
                    .enumerate()
                {
                    let t = seconds(|| with_algorithm(algorithm, || case.run(pass)));
                    best[i] = best[i].min(t);
                }
            }
            println!(
                "{ci:>3}->{co:<3}  {pass:<4}  {:8.4}  {:7.1}  {:10.4}  {:7.1}  {:20.3}",
                best[0],
                flop / best[0],
                best[1],
                flop / best[1],
                best[1] / best[0]
            );
        }
    }
}

/// The table of both backends, alternating runs of the two.
fn table(rng: &mut Lcg) {
    let reps: usize = std::env::var("NETS_CONV_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let passes = std::env::var("NETS_CONV_PASSES").unwrap_or_else(|_| "fwd,dx,dw".into());
    println!(
        "shape     pass  gemm s   gemm GFLOP/s  mm s     mm GFLOP/s  gemm/mm time  (best of {reps}, alternating)"
    );
    for (ci, co) in shapes() {
        let case = Case::new(rng, ci, co);
        let flop = 2.0 * (co * ci * 9 * SIZE * SIZE) as f64 / 1e9;
        for pass in PASSES.into_iter().filter(|p| passes.contains(p)) {
            let mut best = [f64::INFINITY; 2];
            for _ in 0..reps {
                for (i, (backend, _)) in BACKENDS.iter().enumerate() {
                    let t = seconds(|| with_backend(*backend, || case.run(pass)));
                    best[i] = best[i].min(t);
                }
            }
            println!(
                "{ci:>3}->{co:<3}  {pass:<4}  {:7.4}  {:12.1}  {:7.4}  {:10.1}  {:12.3}",
                best[0],
                flop / best[0],
                best[1],
                flop / best[1],
                best[0] / best[1]
            );
        }
    }
}

fn conv(c: &mut Criterion) {
    let mut rng = Lcg::new(2);
    match std::env::var("NETS_CONV_TABLE").as_deref() {
        Ok("1") => table(&mut rng),
        Ok("algorithms") => algorithm_table(&mut rng),
        _ => {}
    }
    let mut group = c.benchmark_group("conv3x3_256");
    group.sample_size(10);
    group.warm_up_time(std::time::Duration::from_secs(1));
    group.measurement_time(std::time::Duration::from_secs(3));
    for (ci, co) in shapes() {
        let case = Case::new(&mut rng, ci, co);
        let a = rng.vec(co * 9 * ci, 0.1);
        let bs: Vec<Vec<f32>> = (0..OPERANDS)
            .map(|_| rng.vec(9 * ci * BLOCK, 1.0))
            .collect();
        let mut out = vec![0f32; co * SIZE * SIZE];
        group.bench_function(format!("conv_{ci}_{co}"), |bch| {
            bch.iter(|| case.run("fwd"))
        });
        for pass in PASSES {
            for (backend, name) in BACKENDS {
                group.bench_function(format!("{pass}_{ci}_{co}/{name}"), |bch| {
                    bch.iter(|| with_backend(backend, || case.run(pass)))
                });
            }
        }
        group.bench_function(format!("sgemm_{ci}_{co}"), |bch| {
            bch.iter(|| tiled_sgemm(co, ci, &a, &bs, &mut out))
        });
    }
    group.finish();
}

criterion_group!(benches, conv);
criterion_main!(benches);
