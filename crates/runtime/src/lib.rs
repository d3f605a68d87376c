//! The trained-scene runtime of dsgs: a scene bundle opened once, and stylized frames from it.
//!
//! * [`bundle`]: the bundle on disk and in memory ([`SceneBundle`], [`BundleInfo`]): frozen
//!   Gaussians with learned features, the lifter trained on them, the encoder and decoder they
//!   were trained against, the scene's feature statistics and the training cameras; loading
//!   checks every part and names the file and key at fault.
//! * [`frame`]: one stylized view, top down: rasterize the features, lift, transform to a
//!   style's statistics, decode in tiles within a memory budget, clamp ([`SceneBundle::frame`]).
//!   Training (`dsgs-train`) writes bundles; stylization, evaluation, baking and the viewer
//!   (`dsgs-pipeline`, `dsgs-viewer`) read them through this crate.
//!
//! Nothing here prints; errors are [`RuntimeError`], with the lower crates' errors as typed
//! variants.
//!
//! # Example
//!
//! Open a bundle written by `dsgs fit-features`, encode a painting with its encoder, and
//! stylize the first training camera:
//!
//! ```no_run
//! use runtime::{SceneBundle, DEFAULT_TILE_BUDGET_BYTES};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let bundle = SceneBundle::load(std::path::Path::new("out/bundle"))?;
//! // A painting as `[1, 3, H, W]` in [0, 1] (here a flat grey).
//! let painting = ndarray::Array4::<f32>::from_elem((1, 3, 256, 256), 0.5);
//! let style = style::encode_style(&bundle.encoder, &painting)?;
//! let camera = bundle.cameras()[0];
//! let frame = bundle.frame(&camera, style.deepest(), 1.0, DEFAULT_TILE_BUDGET_BYTES)?;
//! let k = camera.intrinsics;
//! assert_eq!((frame.image.width, frame.image.height), (k.width, k.height));
//! # Ok(())
//! # }
//! ```

pub mod bundle;
pub mod error;
pub mod frame;

pub use bundle::{BundleInfo, CameraRecord, DecoderMode, SceneBundle, Variant};
pub use error::RuntimeError;
pub use frame::{FeatureView, Frame, StageSeconds, DEFAULT_TILE_BUDGET_BYTES};
