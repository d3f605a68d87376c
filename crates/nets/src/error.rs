//! Errors of the `nets` crate.

use std::path::PathBuf;

/// What went wrong building, running or loading a network.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A tensor the layout requires is absent.
    #[error("missing tensor `{name}`")]
    MissingTensor { name: String },
    /// A tensor has the wrong shape.
    #[error("tensor `{name}` has shape {found:?}, expected {expected}")]
    TensorShape {
        name: String,
        found: Vec<usize>,
        expected: String,
    },
    /// The state dict matches none of the known layouts, or is inconsistent within one.
    #[error("weight layout: {0}")]
    Layout(String),
    /// An input tensor (or tape, or cotangent) does not fit the network.
    #[error("{0}")]
    Input(String),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A weights file is malformed or inconsistent.
    #[error("{path}: {detail}")]
    File { path: PathBuf, detail: String },
    /// A PyTorch checkpoint could not be imported.
    #[error(transparent)]
    Checkpoint(#[from] crate::checkpoint::CheckpointError),
}
