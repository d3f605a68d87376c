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
    /// A checkpoint or weights file that is not what this crate writes (no safetensors header,
    /// wrong format tag, missing or malformed metadata or tensors), or weights that could not be
    /// written.
    #[error("checkpoint {}: {message}", path.display())]
    Checkpoint {
        /// The file or bundle directory rejected, or the file being written.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// A scene bundle, or one of its files, that is not what this crate writes: a missing
    /// folder or file, a `bundle.json` key of the wrong value (the message names the key), parts
    /// that do not fit together, an encoder fingerprint that differs, a camera the networks
    /// cannot decode; or a bundle file that could not be written. `path` is the file at fault
    /// (`bundle.json`, `nets.safetensors`) or the bundle folder.
    #[error("{}: {message}", path.display())]
    Bundle {
        /// The bundle file or folder rejected, or the file being written.
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
    /// A scene bundle could not be made, saved or run.
    #[error(transparent)]
    Runtime(#[from] runtime::RuntimeError),
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
