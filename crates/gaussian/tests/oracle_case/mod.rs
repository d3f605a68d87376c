//! Reading one rasterizer case of the oracle (`raster.safetensors`) into the crate's types.
//!
//! The fixture stores `viewmat` (camera_from_world) as a row-major 4x4, `K` as a row-major 3x3
//! and `size_wh = [W, H]`; per-Gaussian tensors are row-major `[N, D]`.

#![allow(dead_code)]

use dsgs_testkit::Fixture;
use gaussian::{Camera, Intrinsics};
use glam::DMat4;

pub const RASTER: &str = "oracle/fixtures/raster.safetensors";
pub const CASES: [&str; 5] = ["basic", "features", "saturated", "edges", "sh3"];

pub fn fixture() -> Fixture {
    Fixture::shared(RASTER)
}

pub fn rows<const D: usize>(f: &Fixture, name: &str) -> Vec<[f64; D]> {
    let t = f.get(name);
    assert_eq!(
        t.shape.last().copied(),
        Some(D),
        "{name} has shape {:?}",
        t.shape
    );
    t.data
        .chunks_exact(D)
        .map(|c| std::array::from_fn(|i| c[i]))
        .collect()
}

pub fn flat<const D: usize>(v: &[[f64; D]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

pub fn camera(f: &Fixture, case: &str) -> Camera {
    let k = &f.get(&format!("{case}.K")).data;
    let wh = &f.get(&format!("{case}.size_wh")).data;
    let vm = &f.get(&format!("{case}.viewmat")).data;
    let rows: [f64; 16] = std::array::from_fn(|i| vm[i]);
    Camera::new(
        Intrinsics {
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            width: wh[0] as u32,
            height: wh[1] as u32,
        },
        // from_cols_array reads column-major, so a row-major array needs a transpose.
        DMat4::from_cols_array(&rows).transpose(),
    )
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
