//! Convolutional networks of dsgs on CPU: the normalised VGG encoder (standard and fullres), the
//! AdaIN-style decoder, the MLP lifter, their backward passes, the convolution engine they run on,
//! and their canonical safetensors weights format.
//!
//! Tensors are `ndarray::Array4` in NCHW order. Networks and kernels are generic over the
//! workspace's numeric trait [`base::Real`] (`f32` in production, the default type parameter;
//! `f64` for checking gradients, so that central differences are accurate enough to check them
//! tightly and forward passes match the float64 oracle almost exactly). Matrix products go
//! through [`matmul`], which picks the GEMM library.
//!
//! * [`Encoder`]: features `relu1_1 ..= relu{depth}_1`, forward with tape, backward from
//!   cotangents on any subset of the features.
//! * [`Decoder`]: forward with tape, backward to the input and every parameter.
//! * [`Lifter`]: `relu(conv1x1(x))`, forward and backward.
//! * Built from a [`StateDict`] in the AdaIN/WCT Sequential layout or the compressed named layout
//!   ([`layout`]), imported from PyTorch checkpoints ([`checkpoint`], [`Encoder::from_checkpoint`]),
//!   or loaded from canonical safetensors files ([`weights_file`]).
//!
//! Gradients of a loss on encoder features of a decoded image, as the style losses need them:
//!
//! ```
//! # use ndarray::Array4;
//! # use nets::{Decoder, Encoder, NetError, Resolution};
//! fn decoder_gradients(
//!     enc: &Encoder,
//!     dec: &Decoder,
//!     t: &Array4<f32>,
//! ) -> Result<nets::DecoderGrads, NetError> {
//!     let (image, dec_tape) = dec.forward_with_tape(t.view())?;
//!     let (feats, enc_tape) = enc.forward_with_tape(image.view())?;
//!     // d loss / d relu{k}_1; here a cotangent on relu1_1 only (None = no loss on that level).
//!     let cot = feats[0].mapv(|v| 2.0 * v);
//!     let d_image = enc.backward(&enc_tape, &[Some(cot.view())])?;
//!     dec.backward(&dec_tape, d_image.view()) // .input and .params (one per decoder conv)
//! }
//! ```

pub mod checkpoint;
pub mod conv;
pub mod decoder;
pub mod encoder;
pub mod error;
pub mod layer;
pub mod layout;
pub mod lifter;
mod mask;
pub mod matmul;
pub mod pool;
mod sequential;
pub mod state_dict;
pub mod upsample;
pub mod weights_file;

pub use decoder::{Decoder, DecoderGrads, DecoderTape};
pub use encoder::{Encoder, EncoderTape};
pub use error::NetError;
pub use layer::{ConvGrad, ConvLayer};
pub use layout::Layout;
pub use lifter::{Lifter, LifterGrads, LifterTape};
pub use pool::PoolRounding;
pub use state_dict::{StateDict, TensorF32};
pub use weights_file::NetWeights;

/// Whether the encoder pools and the decoder upsamples between levels (`Standard`) or both keep
/// the input resolution throughout (`Fullres`, pooling and upsampling replaced by identity).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Resolution {
    /// The original networks.
    #[default]
    Standard,
    /// No pooling in the encoder and no upsampling in the decoder.
    Fullres,
}
