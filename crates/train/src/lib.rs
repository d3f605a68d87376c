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
//!   [`FeatureTrainConfig`]), producing a `runtime::SceneBundle`.
//! * [`bake`](mod@bake): fitting SH colours to the stylized views of a bundle.
//!
//! Running them:
//!
//! * [`driver`]: the one training-loop driver ([`drive`], [`TrainingLoop`]) under every loop:
//!   stop flag, periodic and stop checkpoints, progress and log events, the final output.
//! * `base::event`: the typed events every loop reports to a caller's sink; nothing in this
//!   crate prints.
//!
//! # Example
//!
//! A geometry run: ground-truth views of a small known scene, rendered with the rasterizer, are
//! fitted from random initial points for 30 iterations through the driver, with a closure as the
//! event sink.
//!
//! ```
//! use std::sync::Mutex;
//!
//! use gaussian::{camera_path::look_at, Intrinsics};
//! use glam::DVec3;
//! use train::render::render_color;
//! use train::{gaussians_from_points, random_points_in_box, Event, Run};
//! use train::{GeometryConfig, GeometryTrainer, View};
//!
//! // The scene to recover: 40 opaque, coloured Gaussians in a cube.
//! let mut cloud = random_points_in_box(40, [-0.6; 3], [0.6; 3], 1);
//! for (i, c) in cloud.colors.iter_mut().enumerate() {
//!     *c = [(i % 3) as f32 / 2.0, (i % 5) as f32 / 4.0, (i % 7) as f32 / 6.0];
//! }
//! let mut truth = gaussians_from_points(&cloud, 0)?;
//! truth.opacity_logits.fill(2.0);
//!
//! // Six 24x24 views of it from a ring of cameras.
//! let k = Intrinsics { fx: 30.0, fy: 30.0, cx: 12.0, cy: 12.0, width: 24, height: 24 };
//! let mut views = Vec::new();
//! for i in 0..6 {
//!     let a = i as f64 * std::f64::consts::PI / 3.0;
//!     let eye = DVec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.5);
//!     let camera = look_at(k, eye, DVec3::ZERO, DVec3::Z).expect("a valid camera");
//!     let image = render_color(&camera, &truth, 0, [0.0; 3])?.raster.image;
//!     views.push(View { name: format!("view{i}"), camera, image });
//! }
//!
//! // 30 iterations from 200 random points, a log line every 10.
//! let config = GeometryConfig {
//!     iterations: 30,
//!     sh_degree: 0,
//!     test_iterations: vec![],
//!     save_iterations: vec![],
//!     log_interval: 10,
//!     ..GeometryConfig::default()
//! };
//! let initial = gaussians_from_points(&random_points_in_box(200, [-1.0; 3], [1.0; 3], 2), 0)?;
//! let mut trainer = GeometryTrainer::new(config, initial, views.clone(), vec![])?;
//! let before = trainer.evaluate_views(&views)?.expect("views given");
//!
//! let events = Mutex::new(Vec::new());
//! let sink = |e: Event| events.lock().unwrap().push(e);
//! let summary = trainer.train(&Run { sink: &sink, ..Run::in_memory() })?;
//!
//! let after = trainer.evaluate_views(&views)?.expect("views given");
//! assert_eq!(summary.run.step, 30);
//! assert!(after.psnr > before.psnr && after.l1 < before.l1);
//! let events = events.into_inner().unwrap();
//! let count = |f: fn(&Event) -> bool| events.iter().filter(|e| f(e)).count();
//! assert_eq!(count(|e| matches!(e, Event::Progress { .. })), 30);
//! assert_eq!(count(|e| matches!(e, Event::Log { .. })), 3);
//! assert!(matches!(events.last(), Some(Event::StageFinished { done: 30, .. })));
//! # Ok::<(), train::TrainError>(())
//! ```

#![warn(missing_docs)]

pub mod adam;
pub mod bake;
pub mod checkpoint;
pub mod colour_solve;
pub mod decoder_training;
pub mod density;
pub mod driver;
pub mod error;
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
pub use base::event::{Event, Metric, Quiet, Sink, Stage};
pub use checkpoint::GeometryCheckpoint;
pub use decoder_training::{DecoderTrainConfig, DecoderTrainer};
pub use density::{DensifyConfig, DensifyReport};
pub use driver::{drive, Cadence, Run, RunOutcome, TrainingLoop};
pub use error::TrainError;
pub use features::{FeatureEvaluation, FeatureInputs, FeatureTrainConfig, FeatureTrainer};
pub use geometry::{Evaluation, GeometryConfig, GeometryTrainer, StepReport, TrainSummary, View};
pub use image_folder::ImageSet;
pub use init::{gaussians_from_points, random_points_in_box, PointCloud};
pub use model::{ColourGrads, GaussianGrads, GaussianModel, LearningRates};
pub use runtime::{DecoderMode, Variant};
pub use schedule::ExponentialLr;
pub use ssim::ImageShape;
pub use style::FeatureNorm;
