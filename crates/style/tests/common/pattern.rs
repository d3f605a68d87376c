//! Exact (`f64`) gradients of a fullres network chain for a GIVEN ReLU activation pattern.
//!
//! A ReLU network is piecewise linear in its input; the backward pass depends on the forward pass
//! only through which units are active. When a unit's pre-activation lies within the `f32`
//! forward error of zero (a "tie"), `f32` may land in the neighbouring linear piece, and its
//! gradient then legitimately differs from the oracle's by that unit's contribution. To check the
//! `f32` arithmetic there, the reference must be the exact gradient of the piece `f32` landed in:
//! this module replays the convolutions of a fullres encoder, decoder or lifter (no pooling or
//! upsampling), records the ReLU pattern of one forward pass, and runs an `f64` backward pass
//! with any recorded pattern, using the public convolution kernels of `nets`.
#![allow(dead_code)]

use base::Real;
use ndarray::{Array1, Array4};
use nets::conv::{
    conv1x1, conv1x1_backward_input, conv1x1_backward_params, conv3x3_reflect,
    conv3x3_reflect_backward_input, conv3x3_reflect_backward_params,
};
use nets::{ConvLayer, Decoder, Encoder, Lifter, Resolution};

/// Weight and bias gradients of one conv.
pub type ParamGrad = (Array4<f64>, Array1<f64>);

/// A unit whose activity differs: `(step, index, pre-activation)`.
pub type Flip = (usize, (usize, usize, usize, usize), f64);

/// One conv of a chain: the layer, whether a ReLU follows, whether its (activated) result is an
/// output of the chain.
pub struct Step<'a, T: Real> {
    pub layer: &'a ConvLayer<T>,
    pub relu: bool,
    pub output: bool,
}

/// The steps of a fullres encoder: conv0 (1x1, no ReLU), then 3x3 conv + ReLU, with the first
/// conv of each level (`relu{k}_1`) an output.
pub fn encoder_steps<T: Real>(enc: &Encoder<T>) -> Vec<Step<'_, T>> {
    assert_eq!(enc.resolution(), Resolution::Fullres);
    let mut firsts = vec![1usize];
    for n in enc.convs_per_level() {
        firsts.push(firsts.last().unwrap() + n);
    }
    enc.layers()
        .enumerate()
        .map(|(i, layer)| Step {
            layer,
            relu: i > 0,
            output: firsts[..enc.depth()].contains(&i),
        })
        .collect()
}

/// The steps of a fullres decoder: 3x3 conv + ReLU, the last conv without (unless the weights
/// say so), its result the output.
pub fn decoder_steps<T: Real>(dec: &Decoder<T>) -> Vec<Step<'_, T>> {
    assert_eq!(dec.resolution(), Resolution::Fullres);
    let n = dec.layers().count();
    dec.layers()
        .enumerate()
        .map(|(i, layer)| Step {
            layer,
            relu: i + 1 < n || dec.final_relu(),
            output: i + 1 == n,
        })
        .collect()
}

/// The lifter as a one-step chain.
pub fn lifter_steps<T: Real>(l: &Lifter<T>) -> Vec<Step<'_, T>> {
    vec![Step {
        layer: l.layer(),
        relu: true,
        output: true,
    }]
}

/// A forward pass: the outputs, every conv's input, and the ReLU pattern (`true` = active).
pub struct Forward<T: Real> {
    pub outputs: Vec<Array4<T>>,
    pub inputs: Vec<Array4<T>>,
    pub pattern: Vec<Option<Array4<bool>>>,
    pub pre: Vec<Array4<T>>,
}

pub fn forward<T: Real>(steps: &[Step<'_, T>], x: &Array4<T>) -> Forward<T> {
    let mut f = Forward {
        outputs: vec![],
        inputs: vec![],
        pattern: vec![],
        pre: vec![],
    };
    let mut x = x.clone();
    for s in steps {
        let l = s.layer;
        let pre = if l.kernel() == 1 {
            conv1x1(x.view(), l.weight.view(), l.bias.view(), false)
        } else {
            conv3x3_reflect(x.view(), l.weight.view(), l.bias.view(), false)
        };
        f.inputs.push(x);
        let (act, pat) = if s.relu {
            let pat = pre.mapv(|v| v > T::zero());
            (
                pre.mapv(|v| if v > T::zero() { v } else { T::zero() }),
                Some(pat),
            )
        } else {
            (pre.clone(), None)
        };
        f.pattern.push(pat);
        f.pre.push(pre);
        if s.output {
            f.outputs.push(act.clone());
        }
        x = act;
    }
    f
}

/// Backward in `f64` through `steps` with the ReLU `pattern` and the conv inputs `inputs`, from
/// cotangents on the outputs (in output order). Returns the input gradient and, per step, the
/// gradients of weight and bias.
pub fn backward(
    steps: &[Step<'_, f64>],
    pattern: &[Option<Array4<bool>>],
    inputs: &[Array4<f64>],
    cotangents: &[Array4<f64>],
) -> (Array4<f64>, Vec<ParamGrad>) {
    let mut k = cotangents.len();
    let mut g: Option<Array4<f64>> = None;
    let mut params = Vec::new();
    for (i, s) in steps.iter().enumerate().rev() {
        if s.output {
            k -= 1;
            g = Some(match g {
                Some(g) => g + &cotangents[k],
                None => cotangents[k].clone(),
            });
        }
        let mut gi = g.take().expect("a cotangent reaches every step");
        if let Some(p) = &pattern[i] {
            gi.zip_mut_with(p, |v, &on| {
                if !on {
                    *v = 0.0
                }
            });
        }
        let l = s.layer;
        let (gw, gb, gx) = if l.kernel() == 1 {
            let (gw, gb) = conv1x1_backward_params(inputs[i].view(), gi.view());
            (gw, gb, conv1x1_backward_input(gi.view(), l.weight.view()))
        } else {
            let (gw, gb) = conv3x3_reflect_backward_params(inputs[i].view(), gi.view());
            (
                gw,
                gb,
                conv3x3_reflect_backward_input(gi.view(), l.weight.view()),
            )
        };
        params.push((gw, gb));
        g = Some(gx);
    }
    params.reverse();
    (g.expect("at least one step"), params)
}

/// Units whose activity differs between two patterns: `(step, index, pre-activation in a)`.
pub fn flips<T: Real>(a: &Forward<f64>, b: &Forward<T>) -> Vec<Flip> {
    let mut out = Vec::new();
    for (i, (pa, pb)) in a.pattern.iter().zip(&b.pattern).enumerate() {
        if let (Some(pa), Some(pb)) = (pa, pb) {
            for ((idx, &x), &y) in pa.indexed_iter().zip(pb.iter()) {
                if x != y {
                    out.push((i, idx, a.pre[i][idx]));
                }
            }
        }
    }
    out
}

/// The largest magnitude of step `i`'s pre-activations.
pub fn scale(f: &Forward<f64>, i: usize) -> f64 {
    f.pre[i].iter().fold(0.0, |m, v| m.max(v.abs()))
}

/// A chain whose passes in `f64` and in `T` are compared: its name, its steps, and the two passes.
pub type Chain<'a, T> = (
    &'a str,
    &'a [Step<'a, f64>],
    &'a Forward<f64>,
    &'a Forward<T>,
);

/// The flips between the `f64` and `f32` passes of each chain, described; asserts that each is a
/// tie at `f32` resolution (a pre-activation within 1e-5 of its layer's scale), where `f32` may
/// legitimately land in the other linear piece.
pub fn ties<T: Real>(chains: &[Chain<'_, T>]) -> Vec<String> {
    let mut ties = Vec::new();
    for &(name, steps, a, b) in chains {
        for (i, idx, pre) in flips(a, b) {
            let scale = scale(a, i);
            let what = format!(
                "{name} {} unit {idx:?}: pre-activation {pre:.2e} (layer scale {scale:.2e})",
                steps[i].layer.name
            );
            assert!(
                pre.abs() <= 1e-5 * scale,
                "not a tie at f32 resolution: {what}"
            );
            ties.push(what);
        }
    }
    ties
}
