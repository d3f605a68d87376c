//! The dsgs pipeline: the stages of DS-StyleGaussian as functions the `dsgs` program calls.
//!
//! Each module maps onto one group of subcommands and speaks in files: it reads inputs, reports
//! clear errors naming the file and the problem, and writes outputs atomically.

pub mod weights;
