//! Fixture access shared by the integration tests: tensors as arrays, networks from the oracle's
//! weights, and error reporting.
#![allow(dead_code)]

pub mod pattern;

use base::Real;
use dsgs_testkit::{max_rel_err, Fixture, Tensor};
use ndarray::{Array1, Array4, Dimension};
use nets::{ConvLayer, Decoder, Encoder, Lifter, Resolution, StateDict, TensorF32};

pub fn nets_fixture() -> Fixture {
    Fixture::shared("oracle/fixtures/nets.safetensors")
}

/// A 4-D fixture tensor in precision `T`.
pub fn arr4<T: Real>(t: &Tensor) -> Array4<T> {
    let s = &t.shape;
    assert_eq!(s.len(), 4, "not a 4-D tensor: {s:?}");
    Array4::from_shape_vec(
        (s[0], s[1], s[2], s[3]),
        t.data.iter().map(|&v| T::lit(v)).collect(),
    )
    .expect("shape")
}

/// The tensors `{prefix}*` as an `f32` state dict, prefix removed.
pub fn state_dict(fx: &Fixture, prefix: &str) -> StateDict {
    fx.names()
        .into_iter()
        .filter_map(|n| {
            n.strip_prefix(prefix).map(|k| {
                let t = fx.get(n);
                let data = t.data.iter().map(|&v| v as f32).collect();
                (
                    k.to_string(),
                    TensorF32::new(t.shape.clone(), data).expect("shape"),
                )
            })
        })
        .collect()
}

/// Replaces every layer's parameters by the fixture's values `{prefix}{source}.{weight,bias}` in
/// precision `T` (for `f64`, the exact oracle weights rather than their `f32` rounding).
fn set_weights<'a, T: Real>(
    layers: impl Iterator<Item = &'a mut ConvLayer<T>>,
    fx: &Fixture,
    prefix: &str,
) {
    for l in layers {
        let w = fx.get(&format!("{prefix}{}.weight", l.source));
        assert_eq!(w.shape, l.weight.shape(), "{prefix}{}", l.source);
        l.weight = arr4(w);
        let b = fx.get(&format!("{prefix}{}.bias", l.source));
        l.bias = Array1::from_iter(b.data.iter().map(|&v| T::lit(v)));
    }
}

/// The oracle's encoder (to relu4_1) and decoder, in precision `T` and the given variant.
pub fn networks<T: Real>(fx: &Fixture, resolution: Resolution) -> (Encoder<T>, Decoder<T>) {
    let enc: Encoder<f32> = Encoder::from_state_dict(&state_dict(fx, "vgg.")).expect("encoder");
    let mut enc = enc
        .with_depth(4)
        .expect("relu4_1")
        .with_resolution(resolution)
        .cast::<T>();
    set_weights(enc.layers_mut(), fx, "vgg.");
    let dec: Decoder<f32> = Decoder::from_state_dict(&state_dict(fx, "decoder.")).expect("decoder");
    let mut dec = dec.with_resolution(resolution).cast::<T>();
    set_weights(dec.layers_mut(), fx, "decoder.");
    (enc, dec)
}

/// The oracle's lifter in precision `T`.
pub fn lifter<T: Real>(fx: &Fixture) -> Lifter<T> {
    Lifter::new(
        arr4(fx.get("lifter.weight")),
        Array1::from_iter(fx.get("lifter.bias").data.iter().map(|&v| T::lit(v))),
    )
    .expect("lifter")
}

/// `max_rel_err` of an array against a fixture tensor, after checking the shape.
pub fn rel_err<T: Real, D: Dimension>(a: &ndarray::Array<T, D>, e: &Tensor) -> f64 {
    assert_eq!(a.shape(), e.shape.as_slice(), "shape mismatch");
    let v: Vec<f64> = a.iter().map(|x| x.to_f64_exact()).collect();
    max_rel_err(&v, &e.data)
}

/// `max_rel_err` of an array against a reference array of the same shape.
pub fn rel_err_arr<T: Real, D: Dimension>(
    a: &ndarray::Array<T, D>,
    e: &ndarray::Array<f64, D>,
) -> f64 {
    assert_eq!(a.shape(), e.shape(), "shape mismatch");
    let v: Vec<f64> = a.iter().map(|x| x.to_f64_exact()).collect();
    let w: Vec<f64> = e.iter().copied().collect();
    max_rel_err(&v, &w)
}

/// Relative error of a scalar.
pub fn rel_err_scalar<T: Real>(a: T, e: &Tensor) -> f64 {
    max_rel_err(&[a.to_f64_exact()], &[e.scalar()])
}

/// Collects `(key, error)` rows, prints them, and asserts each is within `tol`.
#[derive(Default)]
pub struct Report(pub Vec<(String, f64)>);

impl Report {
    pub fn add(&mut self, key: &str, err: f64) {
        self.0.push((key.to_string(), err));
    }

    pub fn check(&self, label: &str, tol: f64) {
        for (k, e) in &self.0 {
            println!("{label} {k}: max rel err {e:.2e}");
        }
        for (k, e) in &self.0 {
            assert!(
                *e <= tol,
                "{label} {k}: max relative error {e:.3e} exceeds {tol:.1e}"
            );
        }
    }
}
