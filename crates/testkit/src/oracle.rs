//! The oracle's fixture files (`oracle/fixtures/*.safetensors` in the shared directory) and what
//! their cases hold beyond plain tensors.

use crate::Fixture;

/// The networks fixture: the 1/8-width AdaIN encoder, decoder and lifter with their inputs,
/// outputs, gradients and optimiser steps.
pub const NETS: &str = "oracle/fixtures/nets.safetensors";
/// The rasterizer fixture: five scenes at the camera and at the rasterizer level.
pub const RASTER: &str = "oracle/fixtures/raster.safetensors";
/// PyTorch's outputs of the real pretrained networks (stored as float32).
pub const REAL_WEIGHTS: &str = "oracle/fixtures/real_weights.safetensors";

/// The five cases of [`RASTER`].
pub const RASTER_CASES: [&str; 5] = ["basic", "features", "saturated", "edges", "sh3"];

pub fn nets_fixture() -> Fixture {
    Fixture::shared(NETS)
}

pub fn raster_fixture() -> Fixture {
    Fixture::shared(RASTER)
}

pub fn real_weights_fixture() -> Fixture {
    Fixture::shared(REAL_WEIGHTS)
}

/// The camera of one case of [`RASTER`], as stored. [`crate::oracle_camera!`] makes it a
/// `gaussian::Camera`.
#[derive(Clone, Debug)]
pub struct OracleCamera {
    /// The intrinsic matrix `K`, row-major 3x3.
    pub k: [f64; 9],
    /// The image size `[W, H]` in pixels.
    pub size_wh: [f64; 2],
    /// `viewmat`, camera_from_world, row-major 4x4.
    pub viewmat: [f64; 16],
}

impl OracleCamera {
    pub fn load(f: &Fixture, case: &str) -> OracleCamera {
        let get = |name: &str| f.get(&format!("{case}.{name}")).data.as_slice();
        OracleCamera {
            k: get("K").try_into().expect("K is 3x3"),
            size_wh: get("size_wh").try_into().expect("size_wh is [W, H]"),
            viewmat: get("viewmat").try_into().expect("viewmat is 4x4"),
        }
    }
}

/// `oracle_camera!(&fixture, case)`: the `gaussian::Camera` of a case of [`oracle::RASTER`].
///
/// A macro rather than a function so that the testkit does not depend on `gaussian`, whose own
/// tests use it (that would be a dependency cycle): it expands in the caller, which must have the
/// crates `gaussian` and `glam`.
///
/// [`oracle::RASTER`]: crate::oracle::RASTER
#[macro_export]
macro_rules! oracle_camera {
    ($fixture:expr, $case:expr) => {{
        let $crate::oracle::OracleCamera {
            k,
            size_wh,
            viewmat,
        } = $crate::oracle::OracleCamera::load($fixture, $case);
        gaussian::Camera::new(
            gaussian::Intrinsics {
                fx: k[0],
                fy: k[4],
                cx: k[2],
                cy: k[5],
                width: size_wh[0] as u32,
                height: size_wh[1] as u32,
            },
            // from_cols_array reads column-major, so the row-major array needs a transpose.
            glam::DMat4::from_cols_array(&viewmat).transpose(),
        )
    }};
}
