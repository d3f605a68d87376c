//! The dsgs pipeline: the stages of DS-StyleGaussian as functions the `dsgs` program calls.
//!
//! Each module maps onto one group of subcommands and speaks in files: it reads inputs, reports
//! clear errors naming the file and the problem, and writes outputs atomically.
//!
//! * [`weights`]: importing and describing network weights (`dsgs weights`).
//! * [`config`]: TOML configurations of the training commands, saved beside their outputs.
//! * [`fit_geometry`]: the geometry stage on a dataset (`dsgs fit-geometry`).
//! * [`pretrain_decoder`]: AdaIN decoder training on content and style images
//!   (`dsgs pretrain-decoder`).
//! * [`fit_features`]: feature training on frozen geometry into a scene bundle
//!   (`dsgs fit-features`).
//! * [`bake`]: baking a style into a plain 3DGS `.ply` (`dsgs bake`).
//! * [`cameras`]: camera sequences (dataset, held-out, interpolated path, orbit).
//! * [`render`]: colour, depth, alpha and feature renders of a scene (`dsgs render`).
//! * [`stylize`]: zero-shot stylization of a scene bundle (`dsgs stylize`).
//! * [`consistency`]: multi-view consistency by depth warping; [`eval`]: the evaluation
//!   report (`dsgs eval`).
//! * [`demo`]: the whole pipeline on the lego scene at low resolution (`dsgs demo`).
//! * [`image_io`]: PNG, GIF, contact sheets, MP4 through `ffmpeg`.
//! * [`error`]: the crate's [`Error`] (a message, a message explaining an underlying error, or
//!   an error of a crate below) and the [`Context`](error::Context) extension that adds the
//!   explaining text.

pub mod bake;
pub mod cameras;
pub mod config;
pub mod consistency;
pub mod demo;
pub mod error;
pub mod eval;
pub mod fit_features;
pub mod fit_geometry;
pub mod image_io;
pub mod pretrain_decoder;
pub mod render;
pub mod stylize;
pub mod weights;

pub use error::{Error, Result};
