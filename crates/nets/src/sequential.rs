//! A straight-line network program (convolutions with optional ReLU, max-pools, upsamplings and
//! feature outputs), run forward with an optional tape and backward from cotangents on any of its
//! outputs. The encoder, decoder and lifter are each such a program.

use base::Real;
use ndarray::{Array4, ArrayView4};

use crate::error::NetError;
use crate::layer::{ConvGrad, ConvLayer};
use crate::mask::ReluMask;
use crate::pool::{max_pool2x2, max_pool2x2_backward, PoolArgmax, PoolRounding};
use crate::upsample::{upsample2x, upsample2x_backward};

/// One step of a program.
pub(crate) enum Step<'a, T: Real> {
    /// A convolution, followed by ReLU when `relu`.
    Conv { layer: &'a ConvLayer<T>, relu: bool },
    /// 2x2 max-pool with stride 2.
    Pool(PoolRounding),
    /// Nearest 2x upsampling.
    Up,
    /// Emit the current activation as the next output.
    Output,
}

/// What one step saved for backward.
#[derive(Clone, Debug)]
enum Saved<T: Real> {
    Conv {
        /// The conv's input, kept only when parameter gradients are wanted: reflection-padded
        /// for a 3x3 layer (the copy its forward pass made), as it was for a 1x1 layer.
        input: Option<Array4<T>>,
        mask: Option<ReluMask>,
    },
    Pool(PoolArgmax),
    Up,
    Output,
}

/// Everything a program's backward pass needs from its forward pass.
#[derive(Clone, Debug)]
pub(crate) struct Tape<T: Real> {
    saved: Vec<Saved<T>>,
    input_dim: (usize, usize, usize, usize),
    output_dims: Vec<(usize, usize, usize, usize)>,
}

/// Checks that an input of `dim` can run through `steps`; returns the output shapes.
pub(crate) fn check_shapes<T: Real>(
    steps: &[Step<'_, T>],
    dim: (usize, usize, usize, usize),
    what: &str,
) -> Result<Vec<(usize, usize, usize, usize)>, NetError> {
    let (n, mut c, mut h, mut w) = dim;
    if n == 0 {
        return Err(NetError::Input(format!("{what}: empty batch")));
    }
    let mut outs = Vec::new();
    for step in steps {
        match step {
            Step::Conv { layer, .. } => {
                if layer.in_channels() != c {
                    return Err(NetError::Input(format!(
                        "{what}: layer {} expects {} channels, got {c}",
                        layer.name,
                        layer.in_channels()
                    )));
                }
                if layer.kernel() == 3 && (h < 2 || w < 2) {
                    return Err(NetError::Input(format!(
                        "{what}: layer {} needs at least 2x2 pixels for reflection padding, got {h}x{w}",
                        layer.name
                    )));
                }
                c = layer.out_channels();
            }
            Step::Pool(r) => {
                let (ph, pw) = (r.pooled(h), r.pooled(w));
                if ph == 0 || pw == 0 {
                    return Err(NetError::Input(format!(
                        "{what}: a {h}x{w} activation is too small to max-pool"
                    )));
                }
                (h, w) = (ph, pw);
            }
            Step::Up => (h, w) = (2 * h, 2 * w),
            Step::Output => outs.push((n, c, h, w)),
        }
    }
    Ok(outs)
}

/// The outputs of a forward run and, when requested, its tape.
pub(crate) type ForwardResult<T> = Result<(Vec<Array4<T>>, Option<Tape<T>>), NetError>;

/// Runs a program forward. Returns its outputs and, when `tape` is set, what backward needs
/// (conv inputs only when `keep_conv_inputs`).
pub(crate) fn forward<T: Real>(
    steps: &[Step<'_, T>],
    x: ArrayView4<T>,
    tape: bool,
    keep_conv_inputs: bool,
    what: &str,
) -> ForwardResult<T> {
    let output_dims = check_shapes(steps, x.dim(), what)?;
    let mut saved = Vec::with_capacity(if tape { steps.len() } else { 0 });
    let mut outputs = Vec::new();
    let mut cur: Option<Array4<T>> = None; // None means "still the input view"
    for (i, step) in steps.iter().enumerate() {
        let view = cur.as_ref().map_or(x.view(), |a| a.view());
        match step {
            Step::Conv { layer, relu } => {
                // A taped forward's ReLU decisions are the masks of the backward pass: they are
                // made as the exact sum would make them (see `crate::winograd`).
                let keep = tape && keep_conv_inputs;
                let (y, padded) = if keep {
                    layer.forward_keeping_input(view, *relu, tape)
                } else {
                    (layer.forward(view, *relu, tape), None)
                };
                if tape {
                    // A 3x3 layer's input is kept as the padded copy its convolution made; a 1x1
                    // layer's by moving the previous step's activation, not copying it.
                    let input = keep.then(|| {
                        padded.unwrap_or_else(|| cur.take().unwrap_or_else(|| x.to_owned()))
                    });
                    let mask = relu.then(|| ReluMask::of_output(y.as_slice().expect("fresh")));
                    saved.push(Saved::Conv { input, mask });
                }
                cur = Some(y);
            }
            Step::Pool(r) => {
                let (y, arg) = max_pool2x2(view, *r);
                if tape {
                    saved.push(Saved::Pool(arg));
                }
                cur = Some(y);
            }
            Step::Up => {
                let y = upsample2x(view);
                if tape {
                    saved.push(Saved::Up);
                }
                cur = Some(y);
            }
            Step::Output => {
                // The last step's output is the activation itself, moved rather than copied.
                outputs.push(match cur.take() {
                    Some(a) if i + 1 == steps.len() => a,
                    other => {
                        let copy = match &other {
                            Some(a) => a.to_owned(),
                            None => x.to_owned(),
                        };
                        cur = other;
                        copy
                    }
                });
                if tape {
                    saved.push(Saved::Output);
                }
            }
        }
    }
    let tape = tape.then_some(Tape {
        saved,
        input_dim: x.dim(),
        output_dims,
    });
    Ok((outputs, tape))
}

/// The result of a backward pass.
pub(crate) struct Backward<T: Real> {
    /// Gradient with respect to the program input.
    pub(crate) input: Array4<T>,
    /// Per convolution, in program order, when parameter gradients were requested.
    pub(crate) params: Vec<ConvGrad<T>>,
}

/// Runs a program backward from cotangents on any subset of its outputs (`None` = zero).
pub(crate) fn backward<T: Real>(
    steps: &[Step<'_, T>],
    tape: &Tape<T>,
    cotangents: &[Option<ArrayView4<T>>],
    want_params: bool,
    what: &str,
) -> Result<Backward<T>, NetError> {
    if tape.saved.len() != steps.len() {
        return Err(NetError::Input(format!(
            "{what}: the tape comes from another network"
        )));
    }
    if cotangents.len() > tape.output_dims.len() {
        return Err(NetError::Input(format!(
            "{what}: {} cotangents for {} outputs",
            cotangents.len(),
            tape.output_dims.len()
        )));
    }
    for (i, ct) in cotangents.iter().enumerate() {
        if let Some(ct) = ct {
            if ct.dim() != tape.output_dims[i] {
                return Err(NetError::Input(format!(
                    "{what}: cotangent {i} has shape {:?}, the output has {:?}",
                    ct.dim(),
                    tape.output_dims[i]
                )));
            }
        }
    }
    if want_params
        && tape
            .saved
            .iter()
            .any(|s| matches!(s, Saved::Conv { input: None, .. }))
    {
        return Err(NetError::Input(format!(
            "{what}: parameter gradients need a tape that kept the conv inputs"
        )));
    }
    let mut g: Option<Array4<T>> = None;
    let mut params = Vec::new();
    let mut out_index = tape.output_dims.len();
    for (step, saved) in steps.iter().zip(&tape.saved).rev() {
        match (step, saved) {
            (Step::Output, Saved::Output) => {
                out_index -= 1;
                if let Some(Some(ct)) = cotangents.get(out_index) {
                    g = Some(match g.take() {
                        Some(acc) => acc + ct,
                        None => ct.as_standard_layout().into_owned(),
                    });
                }
            }
            (Step::Conv { layer, .. }, Saved::Conv { input, mask }) => match g.as_mut() {
                None => {
                    if want_params {
                        params.push(layer.zero_grad());
                    }
                }
                Some(gr) => {
                    if let Some(m) = mask {
                        m.apply(gr.as_slice_mut().expect("standard layout"));
                    }
                    if want_params {
                        let x = input.as_ref().expect("checked above");
                        params.push(layer.backward_params(x.view(), gr.view()));
                    }
                    g = Some(layer.backward_input(gr.view()));
                }
            },
            (Step::Pool(_), Saved::Pool(arg)) => {
                if let Some(gr) = g.as_ref() {
                    g = Some(max_pool2x2_backward(gr.view(), arg));
                }
            }
            (Step::Up, Saved::Up) => {
                if let Some(gr) = g.as_ref() {
                    g = Some(upsample2x_backward(gr.view()));
                }
            }
            _ => {
                return Err(NetError::Input(format!(
                    "{what}: the tape comes from another network"
                )))
            }
        }
    }
    params.reverse();
    let input = g.unwrap_or_else(|| Array4::zeros(tape.input_dim));
    Ok(Backward { input, params })
}
