//! A framework-neutral state dict: named `f32` tensors with row-major shapes.
//!
//! Checkpoint importers produce one; network constructors consume one. Convolution weights are
//! OIHW, biases are `[O]`, exactly as PyTorch stores them.

use std::collections::BTreeMap;

/// One dense `f32` tensor, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct TensorF32 {
    /// Dimensions, outermost first (e.g. OIHW `[O, I, kH, kW]` for a conv weight).
    pub shape: Vec<usize>,
    /// The `shape.iter().product()` elements, row-major (last dimension fastest).
    pub data: Vec<f32>,
}

impl TensorF32 {
    /// A tensor from a shape and data; `None` if the element count does not match the shape.
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Option<TensorF32> {
        (shape.iter().product::<usize>() == data.len()).then_some(TensorF32 { shape, data })
    }

    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.data.len()
    }
}

/// Tensors by name, in sorted order.
pub type StateDict = BTreeMap<String, TensorF32>;

impl TensorF32 {
    /// A tensor from an `ndarray` array of any dimension (copied in row-major order).
    pub fn from_array<D: ndarray::Dimension>(a: &ndarray::Array<f32, D>) -> TensorF32 {
        TensorF32 {
            shape: a.shape().to_vec(),
            data: a.iter().copied().collect(),
        }
    }
}

/// The tensors whose names start with `prefix`, with the prefix removed, e.g.
/// `sub_dict(&sd, "vgg.")` turns `vgg.0.weight` into `0.weight`.
pub fn sub_dict(sd: &StateDict, prefix: &str) -> StateDict {
    sd.iter()
        .filter_map(|(k, v)| k.strip_prefix(prefix).map(|s| (s.to_string(), v.clone())))
        .collect()
}
