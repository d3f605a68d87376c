//! Whole-network timings at 256x256, fullres (no pooling/upsampling): the VGG encoder to relu3_1
//! with the WCT widths 64/128/256, to relu4_1 with 64/128/256/512, and the WCT relu3_1 decoder,
//! forward and forward+backward (tape, then gradients of the input and every parameter from a
//! cotangent on the image). Weights are random with the real shapes. The GFLOP/s of each run (3x3
//! convs only, 2 FLOPs per multiply-add, three times the forward's for forward+backward) is
//! printed with the time.
//!
//! With `NETS_NET_TABLE=1` it first prints, for each network, the best of `NETS_NET_REPS`
//! (default 3) runs with each GEMM backend (`gemm` and `matrixmultiply`, see `nets::matmul`),
//! timed alternately in the same process. Criterion then times each network with the default
//! backend.

mod common;

use std::time::Instant;

use common::*;
use criterion::{criterion_group, criterion_main, Criterion};
use ndarray::Array4;
use nets::matmul::{with_backend, GemmBackend};
use nets::{Decoder, Encoder, Resolution};

const SIZE: usize = 256;

fn report(name: &str, net: &str, passes: f64, secs: f64) {
    let g = passes * gflop(net, SIZE, SIZE);
    println!("{name}: {secs:.3} s, {g:.1} GFLOP, {:.1} GFLOP/s", g / secs);
}

/// The benchmarked networks and their inputs.
struct Nets {
    enc3: Encoder,
    enc4: Encoder,
    dec: Decoder,
    x: Array4<f32>,
    feat: Array4<f32>,
    cot: Array4<f32>,
}

impl Nets {
    fn new() -> Nets {
        let mut rng = Lcg::new(1);
        let x = rng.image(3, SIZE, SIZE);
        let enc = |depth, rng: &mut Lcg| {
            Encoder::from_state_dict(&vgg(depth, rng))
                .unwrap()
                .with_resolution(Resolution::Fullres)
        };
        let enc3 = enc(3, &mut rng);
        let enc4 = enc(4, &mut rng);
        let dec = Decoder::from_state_dict(&wct_decoder(&mut rng))
            .unwrap()
            .with_resolution(Resolution::Fullres);
        let feat = rng.image(256, SIZE, SIZE);
        let cot = rng.image(3, SIZE, SIZE);
        Nets {
            enc3,
            enc4,
            dec,
            x,
            feat,
            cot,
        }
    }

    /// Runs one of the benchmarked passes.
    fn run(&self, which: &str) {
        match which {
            "relu3_1" => {
                std::hint::black_box(self.enc3.forward(self.x.view()).unwrap());
            }
            "relu4_1" => {
                std::hint::black_box(self.enc4.forward(self.x.view()).unwrap());
            }
            "decoder" => {
                std::hint::black_box(self.dec.forward(self.feat.view()).unwrap());
            }
            _ => {
                let (_, tape) = self.dec.forward_with_param_tape(self.feat.view()).unwrap();
                std::hint::black_box(
                    self.dec
                        .backward_with_params(&tape, self.cot.view())
                        .unwrap(),
                );
            }
        }
    }
}

/// `(name, pass key, FLOP table, passes)` of every benchmark.
const CASES: [(&str, &str, &str, f64); 4] = [
    ("vgg_relu3_1_fullres_forward", "relu3_1", "relu3_1", 1.0),
    ("vgg_relu4_1_fullres_forward", "relu4_1", "relu4_1", 1.0),
    (
        "decoder_relu3_1_fullres_forward",
        "decoder",
        "decoder3_1",
        1.0,
    ),
    (
        "decoder_relu3_1_fullres_forward_backward",
        "decoder_fb",
        "decoder3_1",
        3.0,
    ),
];

fn table(nets: &Nets) {
    let reps: usize = std::env::var("NETS_NET_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    println!("network                                     gemm s   mm s     gemm/mm  (best of {reps}, alternating)");
    for (name, key, _, _) in CASES {
        let mut best = [f64::INFINITY; 2];
        for _ in 0..reps {
            for (i, backend) in [GemmBackend::Gemm, GemmBackend::MatrixMultiply]
                .into_iter()
                .enumerate()
            {
                let t = Instant::now();
                with_backend(backend, || nets.run(key));
                best[i] = best[i].min(t.elapsed().as_secs_f64());
            }
        }
        println!(
            "{name:<42}  {:7.3}  {:7.3}  {:7.3}",
            best[0],
            best[1],
            best[0] / best[1]
        );
    }
}

fn networks(c: &mut Criterion) {
    let nets = Nets::new();
    if std::env::var("NETS_NET_TABLE").is_ok_and(|v| v == "1") {
        table(&nets);
    }
    assert_eq!(
        nets.enc4.forward(nets.x.view()).unwrap()[3].dim(),
        (1, 512, SIZE, SIZE)
    );
    let mut group = c.benchmark_group("networks");
    group.sample_size(10);
    for (name, key, flops, passes) in CASES {
        let t = Instant::now();
        nets.run(key);
        report(
            &format!("{name} (single run)"),
            flops,
            passes,
            t.elapsed().as_secs_f64(),
        );
        group.bench_function(format!("{name}_{SIZE}"), |b| b.iter(|| nets.run(key)));
    }
    group.finish();
}

criterion_group!(benches, networks);
criterion_main!(benches);
