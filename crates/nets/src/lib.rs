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
//! * [`Decoder`]: forward with tape, backward to the input, and to every parameter too.
//! * [`Lifter`]: `relu(conv1x1(x))`, forward and backward.
//! * [`tiled`]: an encoder level or the decoded image over any [`Region`], from the input region
//!   it depends on, bit-identical to the whole image (`Encoder::forward_region`,
//!   `Decoder::forward_region`, `forward_tiled`): images of any size in bounded memory.
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
//!     let (image, dec_tape) = dec.forward_with_param_tape(t.view())?;
//!     let (feats, enc_tape) = enc.forward_with_tape(image.view())?;
//!     // d loss / d relu{k}_1; here a cotangent on relu1_1 only (None = no loss on that level).
//!     let cot = feats[0].mapv(|v| 2.0 * v);
//!     let d_image = enc.backward(&enc_tape, &[Some(cot.view())])?;
//!     // .input and .params (one per decoder conv); `dec.backward` gives the input gradient alone.
//!     dec.backward_with_params(&dec_tape, d_image.view())
//! }
//! ```
//!
//! # Example
//!
//! A tiny encoder to `relu2_1` (widths 4 and 6) and its decoder, from state dicts in the
//! `nn.Sequential` layout of the public AdaIN/WCT checkpoints, run forward on a 16 x 16 image.
//! Real weights come from PyTorch files: `Encoder::from_checkpoint(path)` (or
//! [`checkpoint::load_checkpoint`] then [`Encoder::from_state_dict`]) imports a `.pth` directly,
//! and [`NetWeights::load`] reads the canonical safetensors file that `dsgs weights import`
//! writes. The crate's `encode` example runs real weights on an image.
//!
//! ```
//! use ndarray::Array4;
//! use nets::{Decoder, Encoder, NetWeights, StateDict, TensorF32};
//!
//! // `{index}.weight` (OIHW) and `{index}.bias`, with small deterministic values.
//! let mut seed = 1u32;
//! let mut conv = |sd: &mut StateDict, index: usize, o: usize, c: usize, k: usize| {
//!     let mut next = || {
//!         seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
//!         (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
//!     };
//!     let w = (0..o * c * k * k).map(|_| next()).collect();
//!     let b = (0..o).map(|_| 0.1 * next()).collect();
//!     sd.insert(format!("{index}.weight"), TensorF32::new(vec![o, c, k, k], w).unwrap());
//!     sd.insert(format!("{index}.bias"), TensorF32::new(vec![o], b).unwrap());
//! };
//! // Encoder: 1x1 input conv at 0, then pad + conv + ReLU blocks (3 indices each) and a
//! // max-pool (one more index) before relu2_1.
//! let mut e = StateDict::new();
//! conv(&mut e, 0, 3, 3, 1);
//! conv(&mut e, 2, 4, 3, 3); // conv1_1
//! conv(&mut e, 5, 4, 4, 3); // conv1_2
//! conv(&mut e, 9, 6, 4, 3); // conv2_1
//! // Decoder: the mirror image, with a nearest 2x upsampling after its first conv.
//! let mut d = StateDict::new();
//! conv(&mut d, 1, 4, 6, 3);
//! conv(&mut d, 5, 4, 4, 3);
//! conv(&mut d, 8, 3, 4, 3);
//! let enc: Encoder = Encoder::from_state_dict(&e)?;
//! let dec: Decoder = Decoder::from_state_dict(&d)?;
//! assert_eq!((enc.depth(), enc.widths()), (2, vec![4, 6]));
//! assert_eq!((dec.in_channels(), dec.out_channels()), (6, 3));
//!
//! // An RGB image in [0, 1], NCHW.
//! let image = Array4::from_shape_fn((1, 3, 16, 16), |(_, c, y, x)| {
//!     ((x + 2 * y + 5 * c) % 16) as f32 / 15.0
//! });
//! let feats = enc.forward(image.view())?; // relu1_1, relu2_1
//! assert_eq!(feats[0].shape(), &[1, 4, 16, 16]);
//! assert_eq!(feats[1].shape(), &[1, 6, 8, 8]); // after the 2x2 max-pool
//! assert!(feats.iter().all(|f| f.iter().all(|&v| v >= 0.0))); // after a ReLU
//! let decoded = dec.forward(feats[1].view())?;
//! assert_eq!(decoded.shape(), image.shape());
//!
//! // The canonical safetensors format stores both; reloading gives the same features.
//! let weights = NetWeights { encoder: Some(enc), decoder: Some(dec), lifter: None };
//! let again = NetWeights::from_bytes(&weights.to_bytes()?)?;
//! assert_eq!(again.encoder.unwrap().forward(image.view())?, feats);
//! # Ok::<(), nets::NetError>(())
//! ```

#![warn(missing_docs)]

pub mod checkpoint;
pub mod conv;
mod conv_parts;
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
pub mod tiled;
pub mod upsample;
pub mod weights_file;
pub mod winograd;

pub use decoder::{Decoder, DecoderGrads, DecoderTape};
pub use encoder::{Encoder, EncoderTape};
pub use error::NetError;
pub use layer::{ConvGrad, ConvLayer};
pub use layout::Layout;
pub use lifter::{Lifter, LifterGrads, LifterTape};
pub use pool::PoolRounding;
pub use state_dict::{StateDict, TensorF32};
pub use tiled::Region;
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
