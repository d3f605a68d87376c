//! Shared helpers of the `nets` integration tests: fixture tensors as arrays and state dicts.
#![allow(dead_code)]

use dsgs_testkit::arrays::conv_params;
use dsgs_testkit::{Fixture, SplitMix64};
use ndarray::{Array4, ArrayView4, Dimension};
use nets::{ConvLayer, StateDict, TensorF32};

// The testkit's helpers the test files use (each file some of them).
#[allow(unused_imports)]
pub use dsgs_testkit::{
    arrays::{arr4, rel_err},
    oracle::nets_fixture,
    to_f64,
};

/// The tensors named `{prefix}*` as an `f32` state dict with the prefix removed.
pub fn state_dict(fx: &Fixture, prefix: &str) -> StateDict {
    fx.f32_tensors(prefix, TensorF32::new)
}

/// Overwrites every layer's parameters with the exact (float64) fixture values
/// `{prefix}{source}.weight` / `.bias`, so an `f64` network carries no `f32` rounding.
pub fn exact_weights<'a>(
    layers: impl Iterator<Item = &'a mut ConvLayer<f64>>,
    fx: &Fixture,
    prefix: &str,
) {
    for l in layers {
        (l.weight, l.bias) = conv_params(fx, prefix, &l.source, l.weight.shape());
    }
}

/// The oracle's encoder (to relu4_1) and decoder in `f64` with the exact float64 weights.
pub fn networks_f64(res: nets::Resolution) -> (nets::Encoder<f64>, nets::Decoder<f64>) {
    let fx = nets_fixture();
    let mut enc: nets::Encoder<f64> = nets::Encoder::from_state_dict(&state_dict(&fx, "vgg."))
        .unwrap()
        .with_depth(4)
        .unwrap()
        .with_resolution(res);
    exact_weights(enc.layers_mut(), &fx, "vgg.");
    let mut dec: nets::Decoder<f64> = nets::Decoder::from_state_dict(&state_dict(&fx, "decoder."))
        .unwrap()
        .with_resolution(res);
    exact_weights(dec.layers_mut(), &fx, "decoder.");
    (enc, dec)
}

/// Per-channel mean and standard deviation over H*W with the unbiased variance plus 1e-5 (the
/// AdaIN statistics of the oracle), and the gradient of `sum(gm*mean) + sum(gs*std)` w.r.t. x.
pub fn mean_std(x: ArrayView4<f64>) -> (Vec<f64>, Vec<f64>) {
    let (n, c, h, w) = x.dim();
    let hw = (h * w) as f64;
    let mut m = vec![0.0; n * c];
    let mut s = vec![0.0; n * c];
    for i in 0..n {
        for j in 0..c {
            let p = x.slice(ndarray::s![i, j, .., ..]);
            let mean = p.sum() / hw;
            let var = p.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (hw - 1.0);
            m[i * c + j] = mean;
            s[i * c + j] = (var + 1e-5).sqrt();
        }
    }
    (m, s)
}

/// The cotangent on `x` of `sum(gm * mean(x)) + sum(gs * std(x))` (statistics as in [`mean_std`]).
pub fn mean_std_backward(x: ArrayView4<f64>, gm: &[f64], gs: &[f64]) -> Array4<f64> {
    let (n, c, h, w) = x.dim();
    let hw = (h * w) as f64;
    let (m, s) = mean_std(x);
    let mut g = Array4::zeros(x.dim());
    for i in 0..n {
        for j in 0..c {
            let k = i * c + j;
            for y in 0..h {
                for xx in 0..w {
                    let d = x[[i, j, y, xx]] - m[k];
                    g[[i, j, y, xx]] = gm[k] / hw + gs[k] * d / ((hw - 1.0) * s[k]);
                }
            }
        }
    }
    g
}

/// A small deterministic generator (splitmix64) for test tensors.
pub struct TestRng(SplitMix64);

impl TestRng {
    pub fn new(seed: u64) -> TestRng {
        TestRng(SplitMix64(seed ^ 0x9E37_79B9_7F4A_7C15))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }

    /// Uniform in `[-1, 1)`.
    pub fn uniform(&mut self) -> f64 {
        self.0.unit() * 2.0 - 1.0
    }

    pub fn array4(&mut self, dim: (usize, usize, usize, usize)) -> Array4<f64> {
        Array4::from_shape_simple_fn(dim, || self.uniform())
    }

    pub fn array1(&mut self, n: usize) -> ndarray::Array1<f64> {
        ndarray::Array1::from_shape_simple_fn(n, || self.uniform())
    }

    /// A random conv tensor pair `{name}.weight [o, c, k, k]` (He-like scale) and `{name}.bias`.
    pub fn conv_into(&mut self, sd: &mut StateDict, name: &str, o: usize, c: usize, k: usize) {
        let scale = (2.0 / (c * k * k) as f64).sqrt();
        let w: Vec<f32> = (0..o * c * k * k)
            .map(|_| (self.uniform() * scale * 1.7) as f32)
            .collect();
        let b: Vec<f32> = (0..o).map(|_| (self.uniform() * 0.1) as f32).collect();
        sd.insert(
            format!("{name}.weight"),
            TensorF32::new(vec![o, c, k, k], w).unwrap(),
        );
        sd.insert(format!("{name}.bias"), TensorF32::new(vec![o], b).unwrap());
    }
}

/// `sum(a * b)`.
pub fn dot<D: Dimension>(a: &ndarray::Array<f64, D>, b: &ndarray::Array<f64, D>) -> f64 {
    a.iter().zip(b.iter()).map(|(x, y)| x * y).sum()
}
