//! Errors of the `nets` crate.

use std::path::PathBuf;

/// What went wrong building, running or loading a network.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A tensor the layout requires is absent.
    #[error("missing tensor `{name}`")]
    MissingTensor {
        /// The tensor's state-dict name (e.g. `encoder.conv1_1.weight`).
        name: String,
    },
    /// A tensor has the wrong shape.
    #[error("tensor `{name}` has shape {found:?}, expected {expected}")]
    TensorShape {
        /// The tensor's state-dict name.
        name: String,
        /// Its actual shape.
        found: Vec<usize>,
        /// The expected shape, in words (e.g. `[O, 64, 3, 3] for conv1_2`).
        expected: String,
    },
    /// The state dict matches none of the known layouts, or is inconsistent within one.
    #[error("weight layout: {0}")]
    Layout(String),
    /// An input tensor (or tape, or cotangent) does not fit the network.
    #[error("{0}")]
    Input(String),
    /// Reading or writing a file failed.
    #[error("{path}: {error}")]
    Io {
        /// The file being read or written.
        path: PathBuf,
        /// The underlying I/O error.
        error: std::io::Error,
    },
    /// A weights file is malformed or inconsistent.
    #[error("{path}: {detail}")]
    File {
        /// The weights file.
        path: PathBuf,
        /// What is malformed or inconsistent.
        detail: String,
    },
    /// A PyTorch checkpoint could not be imported.
    #[error(transparent)]
    Checkpoint(#[from] crate::checkpoint::CheckpointError),
}
