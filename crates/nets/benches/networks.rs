//! Whole-network timings at 256x256, fullres (no pooling/upsampling): the VGG encoder to relu3_1
//! with the WCT widths 64/128/256, to relu4_1 with 64/128/256/512, and the WCT relu3_1 decoder.
//! Weights are random with the real shapes. The GFLOP/s of each run (3x3 convs only, 2 FLOPs per
//! multiply-add) is printed with the time.

mod common;

use std::time::Instant;

use common::*;
use criterion::{criterion_group, criterion_main, Criterion};
use nets::{Decoder, Encoder, Resolution};

const SIZE: usize = 256;

fn report(name: &str, net: &str, secs: f64) {
    let g = gflop(net, SIZE, SIZE);
    println!("{name}: {secs:.3} s, {g:.1} GFLOP, {:.1} GFLOP/s", g / secs);
}

fn networks(c: &mut Criterion) {
    let mut rng = Lcg::new(1);
    let x = rng.image(3, SIZE, SIZE);
    let mut group = c.benchmark_group("networks");
    group.sample_size(10);
    for (depth, net) in [(3, "relu3_1"), (4, "relu4_1")] {
        let enc: Encoder = Encoder::from_state_dict(&vgg(depth, &mut rng))
            .unwrap()
            .with_resolution(Resolution::Fullres);
        let t = Instant::now();
        let feats = enc.forward(x.view()).unwrap();
        report(
            &format!("vgg {net} fullres forward (single run)"),
            net,
            t.elapsed().as_secs_f64(),
        );
        assert_eq!(
            feats[depth - 1].dim(),
            (1, enc.widths()[depth - 1], SIZE, SIZE)
        );
        group.bench_function(format!("vgg_{net}_fullres_forward_{SIZE}"), |b| {
            b.iter(|| enc.forward(x.view()).unwrap())
        });
    }
    let dec: Decoder = Decoder::from_state_dict(&wct_decoder(&mut rng))
        .unwrap()
        .with_resolution(Resolution::Fullres);
    let feat = rng.image(256, SIZE, SIZE);
    let t = Instant::now();
    let y = dec.forward(feat.view()).unwrap();
    report(
        "decoder relu3_1 fullres forward (single run)",
        "decoder3_1",
        t.elapsed().as_secs_f64(),
    );
    assert_eq!(y.dim(), (1, 3, SIZE, SIZE));
    group.bench_function(format!("decoder_relu3_1_fullres_forward_{SIZE}"), |b| {
        b.iter(|| dec.forward(feat.view()).unwrap())
    });
    group.finish();
}

criterion_group!(benches, networks);
criterion_main!(benches);
