//! Random networks of the real shapes for the benchmarks (timing does not depend on the values).
#![allow(dead_code)]

use ndarray::Array4;
use nets::{StateDict, TensorF32};

/// A small deterministic generator.
pub struct Lcg(u64);

impl Lcg {
    pub fn new(seed: u64) -> Lcg {
        Lcg(seed)
    }

    pub fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    pub fn vec(&mut self, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| self.next() * scale).collect()
    }

    pub fn image(&mut self, c: usize, h: usize, w: usize) -> Array4<f32> {
        Array4::from_shape_vec((1, c, h, w), self.vec(c * h * w, 1.0))
            .unwrap()
            .mapv(|v| 0.5 + 0.5 * v)
    }
}

fn conv(sd: &mut StateDict, rng: &mut Lcg, key: usize, o: usize, c: usize, k: usize) {
    let scale = (6.0 / (c * k * k) as f32).sqrt();
    let w = rng.vec(o * c * k * k, scale);
    sd.insert(
        format!("{key}.weight"),
        TensorF32::new(vec![o, c, k, k], w).unwrap(),
    );
    sd.insert(
        format!("{key}.bias"),
        TensorF32::new(vec![o], rng.vec(o, 0.01)).unwrap(),
    );
}

/// The normalised VGG-19 in the Sequential layout up to `relu{depth}_1`, with the real widths.
pub fn vgg(depth: usize, rng: &mut Lcg) -> StateDict {
    let mut sd = StateDict::new();
    conv(&mut sd, rng, 0, 3, 3, 1);
    // (index, out, in) of the public vgg_normalised up to conv4_1.
    let layers = [
        (2, 64, 3),
        (5, 64, 64),
        (9, 128, 64),
        (12, 128, 128),
        (16, 256, 128),
        (19, 256, 256),
        (22, 256, 256),
        (25, 256, 256),
        (29, 512, 256),
    ];
    let last = match depth {
        3 => 16,
        4 => 29,
        _ => panic!("benchmarks use relu3_1 or relu4_1"),
    };
    for (i, o, c) in layers.into_iter().filter(|l| l.0 <= last) {
        conv(&mut sd, rng, i, o, c, 3);
    }
    sd
}

/// The WCT relu3_1 decoder (`feature_invertor_conv3_1.pth` shapes) in the Sequential layout.
pub fn wct_decoder(rng: &mut Lcg) -> StateDict {
    let mut sd = StateDict::new();
    for (i, o, c) in [
        (1, 128, 256),
        (5, 128, 128),
        (8, 64, 128),
        (12, 64, 64),
        (15, 3, 64),
    ] {
        conv(&mut sd, rng, i, o, c, 3);
    }
    sd
}

/// `(in, out)` channels of the 3x3 convs run by each network, for FLOP counts.
pub fn conv_shapes(net: &str) -> Vec<(usize, usize)> {
    match net {
        "relu3_1" => vec![(3, 64), (64, 64), (64, 128), (128, 128), (128, 256)],
        "relu4_1" => vec![
            (3, 64),
            (64, 64),
            (64, 128),
            (128, 128),
            (128, 256),
            (256, 256),
            (256, 256),
            (256, 256),
            (256, 512),
        ],
        "decoder3_1" => vec![(256, 128), (128, 128), (128, 64), (64, 64), (64, 3)],
        _ => unreachable!(),
    }
}

/// Multiply-add FLOPs (2 per MAC) of the 3x3 convs at `h x w` (fullres: all at full size).
pub fn gflop(net: &str, h: usize, w: usize) -> f64 {
    conv_shapes(net)
        .iter()
        .map(|&(c, o)| 2.0 * (o * c * 9 * h * w) as f64)
        .sum::<f64>()
        / 1e9
}
