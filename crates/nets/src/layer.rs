//! A convolution layer with its names, and the gradient of one.
//!
//! Weights are OIHW (`[O, C, K, K]`, `K` = 1 or 3) and biases `[O]`, as in PyTorch. A 3x3 layer
//! always uses reflection padding 1; a 1x1 layer uses none.

use base::Real;
use ndarray::{Array1, Array4, ArrayView4};

use crate::conv;

/// One convolution of a network.
#[derive(Clone, Debug)]
pub struct ConvLayer<T: Real = f32> {
    /// Canonical name, e.g. `conv0` (the encoder's 1x1 input conv) or `conv3_1`.
    pub name: String,
    /// The key prefix of this layer in the state dict it was built from, e.g. `16`, `conv31` or
    /// `conv3_1` (the tensors were `{source}.weight` and `{source}.bias`).
    pub source: String,
    /// `[O, C, K, K]`.
    pub weight: Array4<T>,
    /// `[O]`.
    pub bias: Array1<T>,
}

impl<T: Real> ConvLayer<T> {
    /// Output channels.
    pub fn out_channels(&self) -> usize {
        self.weight.dim().0
    }

    /// Input channels.
    pub fn in_channels(&self) -> usize {
        self.weight.dim().1
    }

    /// Kernel size (1 or 3).
    pub fn kernel(&self) -> usize {
        self.weight.dim().2
    }

    /// The same layer in another precision.
    pub fn cast<U: Real>(&self) -> ConvLayer<U> {
        ConvLayer {
            name: self.name.clone(),
            source: self.source.clone(),
            weight: self.weight.mapv(|v| U::lit(v.to_f64_exact())),
            bias: self.bias.mapv(|v| U::lit(v.to_f64_exact())),
        }
    }

    /// Forward, optionally followed by ReLU; with `exact_relu`, a 3x3 layer's ReLU decides as
    /// the exact sum would ([`conv::conv3x3_reflect_exact_relu`]).
    pub(crate) fn forward(&self, x: ArrayView4<T>, relu: bool, exact_relu: bool) -> Array4<T> {
        if self.kernel() == 1 {
            conv::conv1x1(x, self.weight.view(), self.bias.view(), relu)
        } else {
            let (w, b) = (self.weight.view(), self.bias.view());
            conv::conv3x3_reflect_with(x, w, b, relu, exact_relu)
        }
    }

    /// [`ConvLayer::forward`], also returning what [`ConvLayer::backward_params`] takes
    /// of the input, when the convolution made it: the reflection-padded input of a 3x3 layer
    /// (`None` for a 1x1 layer, whose parameter gradient takes the input itself).
    pub(crate) fn forward_keeping_input(
        &self,
        x: ArrayView4<T>,
        relu: bool,
        exact_relu: bool,
    ) -> (Array4<T>, Option<Array4<T>>) {
        if self.kernel() == 1 {
            (self.forward(x, relu, exact_relu), None)
        } else {
            let (w, b) = (self.weight.view(), self.bias.view());
            let (y, xp) = conv::conv3x3_reflect_padded(x, w, b, relu, exact_relu);
            (y, Some(xp))
        }
    }

    /// Input gradient (of the convolution alone).
    pub(crate) fn backward_input(&self, dy: ArrayView4<T>) -> Array4<T> {
        if self.kernel() == 1 {
            conv::conv1x1_backward_input(dy, self.weight.view())
        } else {
            conv::conv3x3_reflect_backward_input(dy, self.weight.view())
        }
    }

    /// Parameter gradients (of the convolution alone) given its input as the tape keeps it:
    /// reflection-padded for a 3x3 layer (see [`ConvLayer::forward_keeping_input`]), as it is
    /// for a 1x1 layer.
    pub(crate) fn backward_params(&self, kept: ArrayView4<T>, dy: ArrayView4<T>) -> ConvGrad<T> {
        let (weight, bias) = if self.kernel() == 1 {
            conv::conv1x1_backward_params(kept, dy)
        } else {
            conv::conv3x3_padded_backward_params(kept, dy)
        };
        ConvGrad {
            name: self.name.clone(),
            source: self.source.clone(),
            weight,
            bias,
        }
    }

    /// A zero gradient of this layer's shape.
    pub(crate) fn zero_grad(&self) -> ConvGrad<T> {
        ConvGrad {
            name: self.name.clone(),
            source: self.source.clone(),
            weight: Array4::zeros(self.weight.dim()),
            bias: Array1::zeros(self.bias.dim()),
        }
    }
}

/// The gradient of a scalar loss with respect to one layer's parameters.
#[derive(Clone, Debug)]
pub struct ConvGrad<T: Real = f32> {
    /// Canonical name of the layer (see [`ConvLayer::name`]).
    pub name: String,
    /// Key prefix of the layer in its source state dict (see [`ConvLayer::source`]).
    pub source: String,
    /// `[O, C, K, K]`.
    pub weight: Array4<T>,
    /// `[O]`.
    pub bias: Array1<T>,
}
