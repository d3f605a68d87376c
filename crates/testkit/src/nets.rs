//! The oracle's networks as `nets` types (cargo feature `nets`), for the crates downstream of
//! `nets`. The tests of `nets` itself build theirs from the generic helpers
//! ([`Fixture::f32_tensors`], [`conv_params`]), so that the testkit never depends on `nets` there.

use base::Real;
use nets::{ConvLayer, Decoder, Encoder, Lifter, Resolution, StateDict, TensorF32};

use crate::arrays::{arr1, arr4, conv_params};
use crate::Fixture;

/// The tensors `{prefix}*` as an `f32` state dict, prefix removed.
pub fn state_dict(fx: &Fixture, prefix: &str) -> StateDict {
    fx.f32_tensors(prefix, TensorF32::new)
}

/// Replaces every layer's parameters by the fixture's values `{prefix}{source}.{weight,bias}` in
/// precision `T` (for `f64`, the exact oracle weights rather than their `f32` rounding).
pub fn set_weights<'a, T: Real>(
    layers: impl Iterator<Item = &'a mut ConvLayer<T>>,
    fx: &Fixture,
    prefix: &str,
) {
    for l in layers {
        (l.weight, l.bias) = conv_params(fx, prefix, &l.source, l.weight.shape());
    }
}

/// The oracle's encoder (to relu4_1) and decoder (`vgg.*`, `decoder.*` of
/// [`crate::oracle::NETS`]), in precision `T` and the given variant.
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
    Lifter::new(arr4(fx.get("lifter.weight")), arr1(fx.get("lifter.bias"))).expect("lifter")
}
