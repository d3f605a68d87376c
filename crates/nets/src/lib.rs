//! Convolutional networks of dsgs on CPU: the normalised VGG encoder (standard and fullres), the
//! AdaIN-style decoder, the MLP lifter, their backward passes, and checkpoint import.

pub mod state_dict;

pub use state_dict::{StateDict, TensorF32};
