//! Reading one rasterizer case of the oracle (`raster.safetensors`) into the crate's types.
//!
//! The fixture stores `viewmat` (camera_from_world) as a row-major 4x4, `K` as a row-major 3x3
//! and `size_wh = [W, H]`; per-Gaussian tensors are row-major `[N, D]`.

#![allow(dead_code)]

use dsgs_testkit::Fixture;
use gaussian::Camera;

// The testkit's helpers the test files use (each file some of them).
#[allow(unused_imports)]
pub use dsgs_testkit::{
    flat,
    oracle::{raster_fixture as fixture, RASTER_CASES as CASES},
};

pub fn rows<const D: usize>(f: &Fixture, name: &str) -> Vec<[f64; D]> {
    f.rows(name)
}

pub fn camera(f: &Fixture, case: &str) -> Camera {
    dsgs_testkit::oracle_camera!(f, case)
}

pub struct Inputs {
    pub camera: Camera,
    pub means: Vec<[f64; 3]>,
    pub quats: Vec<[f64; 4]>,
    pub log_scales: Vec<[f64; 3]>,
}

pub fn inputs(f: &Fixture, case: &str) -> Inputs {
    Inputs {
        camera: camera(f, case),
        means: rows(f, &format!("{case}.means")),
        quats: rows(f, &format!("{case}.quats")),
        log_scales: rows(f, &format!("{case}.log_scales")),
    }
}
