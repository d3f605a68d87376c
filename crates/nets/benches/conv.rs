//! One 3x3 reflection-padded convolution at 256x256 for every `(in, out)` width pair of the
//! benchmarked networks, next to the raw `sgemm` of the same matrix product (`m = out`,
//! `k = 9 * in`, `n = 256 * 256`) with its operands already laid out (no padding, no bias), split
//! into column blocks of 2048 run on the same rayon pool. The ratio of the two is the engine's
//! overhead over the matrix product itself. FLOPs count 2 per multiply-add.

mod common;

use std::time::Instant;

use common::*;
use criterion::{criterion_group, criterion_main, Criterion};
use ndarray::Array1;
use nets::conv::conv3x3_reflect;
use rayon::prelude::*;

const SIZE: usize = 256;

const SHAPES: [(usize, usize); 10] = [
    (3, 64),
    (64, 64),
    (64, 128),
    (128, 128),
    (128, 256),
    (256, 256),
    (256, 512),
    (256, 128),
    (128, 64),
    (64, 3),
];

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

fn best_of<F: FnMut()>(n: usize, mut f: F) -> f64 {
    (0..n)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn conv(c: &mut Criterion) {
    let mut rng = Lcg::new(2);
    let mut group = c.benchmark_group("conv3x3_256");
    group.sample_size(10);
    group.warm_up_time(std::time::Duration::from_secs(1));
    group.measurement_time(std::time::Duration::from_secs(3));
    println!("in->out   conv s  conv GFLOP/s  sgemm s  sgemm GFLOP/s  conv/sgemm");
    for (ci, co) in SHAPES {
        let x = rng.image(ci, SIZE, SIZE);
        let w = ndarray::Array4::from_shape_vec((co, ci, 3, 3), rng.vec(co * ci * 9, 0.1)).unwrap();
        let b = Array1::from_vec(rng.vec(co, 0.1));
        let flop = 2.0 * (co * ci * 9 * SIZE * SIZE) as f64 / 1e9;
        let a = rng.vec(co * 9 * ci, 0.1);
        let bs: Vec<Vec<f32>> = (0..OPERANDS)
            .map(|_| rng.vec(9 * ci * BLOCK, 1.0))
            .collect();
        let mut out = vec![0f32; co * SIZE * SIZE];
        let t_conv = best_of(3, || {
            std::hint::black_box(conv3x3_reflect(x.view(), w.view(), b.view(), true));
        });
        let t_gemm = best_of(3, || tiled_sgemm(co, ci, &a, &bs, &mut out));
        println!(
            "{ci:>3}->{co:<3}  {t_conv:7.4}  {:12.1}  {t_gemm:7.4}  {:13.1}  {:10.2}",
            flop / t_conv,
            flop / t_gemm,
            t_conv / t_gemm
        );
        group.bench_function(format!("conv_{ci}_{co}"), |bch| {
            bch.iter(|| conv3x3_reflect(x.view(), w.view(), b.view(), true))
        });
        group.bench_function(format!("sgemm_{ci}_{co}"), |bch| {
            bch.iter(|| tiled_sgemm(co, ci, &a, &bs, &mut out))
        });
    }
    group.finish();
}

criterion_group!(benches, conv);
criterion_main!(benches);
