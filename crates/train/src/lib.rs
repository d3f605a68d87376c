//! Training loops of dsgs.
//!
//! This part holds the geometry stage: a faithful CPU version of the 3D Gaussian Splatting
//! trainer (Kerbl et al. 2023) with its original defaults, and the building blocks the later
//! stages reuse.
//!
//! * [`adam`]: `torch.optim.Adam` semantics, per-tensor learning rates, row-wise state surgery.
//! * [`schedule`]: the log-linear position learning-rate schedule.
//! * [`ssim`], [`loss`]: SSIM and the `0.8 L1 + 0.2 (1 - SSIM)` loss, forward and backward; PSNR.
//! * [`init`]: initial Gaussians from a point cloud (k-d tree neighbour scales).
//! * [`model`]: the trainable scene with its Adam groups; [`density`]: clone, split, prune and
//!   opacity reset, keeping the optimiser state consistent.
//! * [`render`]: colour rendering (projection, SH, rasterization) and its backward pass.
//! * [`geometry`]: the training loop ([`GeometryTrainer`], [`GeometryConfig`]);
//!   [`checkpoint`]: exact, atomic checkpoints.
//!
//! The style stages:
//!
//! * [`image_folder`]: content and style images from folders and files, training and evaluation
//!   crops, batches.
//! * [`decoder_training`]: AdaIN decoder training ([`DecoderTrainer`], [`DecoderTrainConfig`]).
//! * [`features`]: feature training on frozen geometry, the third stage ([`FeatureTrainer`],
//!   [`FeatureTrainConfig`]), producing a [`SceneBundle`].
//! * [`bake`](mod@bake): fitting SH colours to the stylized views of a bundle.
//!
//! Running them:
//!
//! * [`driver`]: the one training-loop driver ([`drive`], [`TrainingLoop`]) under every loop:
//!   stop flag, periodic and stop checkpoints, progress and log events, the final output.
//! * [`event`]: the typed [`Event`]s every loop reports to a caller's [`Sink`]; nothing in this
//!   crate prints.

pub mod adam;
pub mod bake;
pub mod bundle;
pub mod checkpoint;
pub mod decoder_training;
pub mod density;
pub mod driver;
pub mod error;
pub mod event;
pub mod features;
pub mod geometry;
pub mod image_folder;
pub mod init;
pub mod loss;
pub mod model;
pub mod render;
pub mod schedule;
pub mod ssim;

pub use adam::{Adam, AdamConfig, ParamState};
pub use bake::{bake, BakeCameras, BakeConfig, BakeReport};
pub use bundle::{BundleInfo, CameraRecord, SceneBundle, Variant};
pub use checkpoint::GeometryCheckpoint;
pub use decoder_training::{DecoderTrainConfig, DecoderTrainer};
pub use density::{DensifyConfig, DensifyReport};
pub use driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
pub use error::TrainError;
pub use event::{Event, Metric, Quiet, Sink, Stage};
pub use features::{FeatureInputs, FeatureTrainConfig, FeatureTrainer};
pub use geometry::{Evaluation, GeometryConfig, GeometryTrainer, StepReport, TrainSummary, View};
pub use image_folder::ImageSet;
pub use init::{gaussians_from_points, random_points_in_box, PointCloud};
pub use model::{GaussianGrads, GaussianModel, LearningRates};
pub use schedule::ExponentialLr;
pub use ssim::ImageShape;
