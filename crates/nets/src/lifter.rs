//! The MLP lifter: a per-pixel linear map from the rasterized `F`-dimensional features (F = 32)
//! to the encoder width, followed by ReLU, i.e. `relu(conv1x1(x))` with weights `[C, F, 1, 1]` and
//! bias `[C]`.

use base::Real;
use ndarray::{Array1, Array4, ArrayView4};

use crate::error::NetError;
use crate::layer::{ConvGrad, ConvLayer};
use crate::layout::{read_conv, LayerRef};
use crate::sequential::{self, Step, Tape};
use crate::state_dict::StateDict;

/// `relu(W x + b)` per pixel.
#[derive(Clone, Debug)]
pub struct Lifter<T: Real = f32> {
    conv: ConvLayer<T>,
}

/// What [`Lifter::backward`] needs: the input and the ReLU mask.
#[derive(Clone, Debug)]
pub struct LifterTape<T: Real = f32>(Tape<T>);

/// Gradients of a scalar loss through the lifter.
#[derive(Clone, Debug)]
pub struct LifterGrads<T: Real = f32> {
    /// With respect to the input features.
    pub input: Array4<T>,
    /// With respect to the weight `[C, F, 1, 1]` and bias `[C]` (named `lifter`).
    pub params: ConvGrad<T>,
}

impl<T: Real> Lifter<T> {
    /// A lifter from its weight `[C, F, 1, 1]` and bias `[C]`.
    pub fn new(weight: Array4<T>, bias: Array1<T>) -> Result<Lifter<T>, NetError> {
        let (o, _, kh, kw) = weight.dim();
        if kh != 1 || kw != 1 || o == 0 {
            return Err(NetError::TensorShape {
                name: "lifter.weight".into(),
                found: weight.shape().to_vec(),
                expected: "[C, F, 1, 1]".into(),
            });
        }
        if bias.len() != o {
            return Err(NetError::TensorShape {
                name: "lifter.bias".into(),
                found: bias.shape().to_vec(),
                expected: format!("[{o}]"),
            });
        }
        Ok(Lifter {
            conv: ConvLayer {
                name: "lifter".into(),
                source: "lifter".into(),
                weight: weight.as_standard_layout().into_owned(),
                bias,
            },
        })
    }

    /// A lifter from the tensors `weight` and `bias` of a state dict (use
    /// [`crate::state_dict::sub_dict`] to select e.g. `lifter.*`).
    pub fn from_state_dict(sd: &StateDict) -> Result<Lifter<T>, NetError> {
        let r = LayerRef {
            name: "lifter".into(),
            source: String::new(),
        };
        // Keys are `weight` and `bias`, i.e. an empty layer prefix.
        let sd2: StateDict = sd
            .iter()
            .map(|(k, v)| (format!(".{k}"), v.clone()))
            .collect();
        let mut conv: ConvLayer<T> = read_conv(&sd2, &r, 1, None).map_err(|e| match e {
            NetError::MissingTensor { name } => NetError::MissingTensor {
                name: name.trim_start_matches('.').to_string(),
            },
            NetError::TensorShape {
                name,
                found,
                expected,
            } => NetError::TensorShape {
                name: name.trim_start_matches('.').to_string(),
                found,
                expected,
            },
            other => other,
        })?;
        conv.source = "lifter".into();
        Ok(Lifter { conv })
    }

    /// Input features `F`.
    pub fn in_channels(&self) -> usize {
        self.conv.in_channels()
    }

    /// Output channels `C`.
    pub fn out_channels(&self) -> usize {
        self.conv.out_channels()
    }

    /// The underlying 1x1 conv (weight `[C, F, 1, 1]`, bias `[C]`).
    pub fn layer(&self) -> &ConvLayer<T> {
        &self.conv
    }

    /// The underlying conv, mutably (for optimisers).
    pub fn layer_mut(&mut self) -> &mut ConvLayer<T> {
        &mut self.conv
    }

    /// The same lifter in another precision.
    pub fn cast<U: Real>(&self) -> Lifter<U> {
        Lifter {
            conv: self.conv.cast(),
        }
    }

    fn steps(&self) -> [Step<'_, T>; 2] {
        [
            Step::Conv {
                layer: &self.conv,
                relu: true,
            },
            Step::Output,
        ]
    }

    /// `relu(conv1x1(x))` for `x [N, F, H, W]`.
    pub fn forward(&self, x: ArrayView4<T>) -> Result<Array4<T>, NetError> {
        let (mut outs, _) = sequential::forward(&self.steps(), x, false, false, "lifter")?;
        Ok(outs.pop().expect("one output"))
    }

    /// [`Lifter::forward`], also returning the tape for [`Lifter::backward`].
    pub fn forward_with_tape(
        &self,
        x: ArrayView4<T>,
    ) -> Result<(Array4<T>, LifterTape<T>), NetError> {
        let (mut outs, tape) = sequential::forward(&self.steps(), x, true, true, "lifter")?;
        Ok((
            outs.pop().expect("one output"),
            LifterTape(tape.expect("tape requested")),
        ))
    }

    /// Gradients of `<dy, lifter(x)>` with respect to the input, weight and bias.
    pub fn backward(
        &self,
        tape: &LifterTape<T>,
        dy: ArrayView4<T>,
    ) -> Result<LifterGrads<T>, NetError> {
        let mut b = sequential::backward(&self.steps(), &tape.0, &[Some(dy)], true, "lifter")?;
        Ok(LifterGrads {
            input: b.input,
            params: b.params.pop().expect("one conv"),
        })
    }
}
