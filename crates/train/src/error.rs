//! Errors of the training crate.

use std::path::{Path, PathBuf};

/// Everything that can go wrong while training, checkpointing or resuming.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Arrays whose sizes disagree.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// A configuration value that cannot work.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Reading or writing a file failed. The message includes the I/O error's text, so it is
    /// not also returned as the `source()` (a front end printing the chain shows it once).
    #[error("{}: {error}", path.display())]
    Io {
        /// The file or directory that could not be read, written or created.
        path: PathBuf,
        /// The underlying I/O error.
        error: std::io::Error,
    },
    /// A checkpoint, weights file or scene bundle that is not what this crate writes (no
    /// safetensors header, wrong format tag, missing or malformed metadata or tensors, a bundle
    /// whose parts do not fit together or whose encoder fingerprint differs), or weights or a
    /// bundle description that could not be written.
    #[error("checkpoint {}: {message}", path.display())]
    Checkpoint {
        /// The file or bundle directory rejected, or the file being written.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// The dataset has nothing to train on, or an image does not fit its camera.
    #[error("dataset: {0}")]
    Dataset(String),
    /// A set of training images (content or style, [`crate::image_folder`]) that is empty or
    /// names a missing, unreadable or non-image file; the message names the file.
    #[error("{0}")]
    Images(String),
    /// A dataset that could not be loaded.
    #[error(transparent)]
    DatasetLoad(#[from] gaussian::dataset::DatasetError),
    /// A PLY file that could not be written or read.
    #[error(transparent)]
    Ply(#[from] gaussian::ply::PlyError),
    /// The rasterizer refused its input.
    #[error(transparent)]
    Raster(#[from] raster::RasterError),
    /// A stop request ended a step that leaves nothing usable behind.
    #[error("interrupted while {0}")]
    Interrupted(String),
}

impl TrainError {
    /// The [`TrainError::Io`] error of `path`.
    pub fn io(path: &Path, error: std::io::Error) -> TrainError {
        TrainError::Io {
            path: path.to_path_buf(),
            error,
        }
    }
}
