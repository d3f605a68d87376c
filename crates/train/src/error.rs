//! Errors of the training crate.
//!
//! An error of a crate below is kept as a value, never turned into text: a variant either is
//! that error ([`TrainError::Net`], [`TrainError::Style`], [`TrainError::Raster`], ...,
//! displayed as itself) or says what was being done and returns the error from
//! [`std::error::Error::source`] ([`TrainError::Scene`], [`TrainError::Array`], ...). A few
//! variants write a cause's text into their own message instead ([`TrainError::Io`]); none does
//! both, so [`base::error::chain`] reports every text once. [`TrainError::Shape`] is for sizes
//! this crate finds to disagree, with a message written here.

use std::path::{Path, PathBuf};

/// Everything that can go wrong while training, checkpointing or resuming.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Arrays whose sizes disagree, found by this crate (the message says which and how).
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
    /// A problem with one image of a set ([`crate::image_folder::ImageSet`]), e.g. too small
    /// for the crop asked for; displays only the image's name, the problem is the source.
    #[error("{name}")]
    InImage {
        /// The image's file (or the name given to it).
        name: String,
        /// What is wrong with it.
        #[source]
        error: Box<TrainError>,
    },
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
    /// A network refused its input, its weights or a weights file.
    #[error(transparent)]
    Net(#[from] nets::NetError),
    /// A feature-space operation, loss or style statistic refused its input.
    #[error(transparent)]
    Style(#[from] style::StyleError),
    /// A scene that is not valid ([`gaussian::FeatureGaussians::validate`]); displays only
    /// `what`, the scene error is the source.
    #[error("{what} is not a valid scene")]
    Scene {
        /// Which scene, e.g. `the geometry`.
        what: String,
        /// What is wrong with it.
        #[source]
        error: gaussian::SceneError,
    },
    /// An array that could not be built or joined in the shape asked for; displays only `what`,
    /// the array error is the source.
    #[error("{what}")]
    Array {
        /// What was being built, e.g. `cannot stack the images`.
        what: String,
        /// The array library's error.
        #[source]
        error: ndarray::ShapeError,
    },
    /// A tensor that could not be laid out for a safetensors file; displays only `what`, the
    /// format's error is the source.
    #[error("{what}")]
    Tensor {
        /// Which tensor of which file, e.g. `checkpoint tensor means`.
        what: String,
        /// The format's error.
        #[source]
        error: safetensors::SafeTensorError,
    },
    /// Tensors and metadata that the canonical weights-file writer refused
    /// ([`nets::weights_file::canonical`], which reports its problems as text).
    #[error("cannot serialise {what}: {problem}")]
    Serialize {
        /// What was being written, e.g. `the checkpoint`.
        what: &'static str,
        /// The writer's message.
        problem: String,
    },
    /// The initial point cloud could not be put in a k-d tree; displays only the step, the
    /// tree's error is the source.
    #[error("cannot index the initial point cloud")]
    PointIndex(#[source] kiddo::kd_tree::ConstructionError),
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
