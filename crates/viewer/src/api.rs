//! The HTTP API of the viewer: its routes, and the JSON bodies they take and return.
//!
//! | route | answer |
//! |---|---|
//! | `GET /` and `GET /assets/{name}` | the page ([`crate::assets`]) |
//! | `GET /api/scene` | [`SceneInfo`] |
//! | `GET /api/gaussians` | the Gaussians, [`crate::scene::pack_gaussians`] |
//! | `GET /api/styles/{id}/thumbnail.png` | a PNG thumbnail of a style |
//! | `POST /api/styles?name=NAME` | body: an image file; `201` [`StyleInfo`] |
//! | `POST /api/stylize` | body: [`StylizeRequest`]; a PNG |
//! | `POST /api/bake` | body: [`BakeRequest`]; `202` [`JobStarted`] |
//! | `GET /api/jobs/{id}` | [`JobInfo`] |
//! | `GET /api/jobs/{id}/gaussians` | the baked scene, as `/api/gaussians` |
//!
//! Every error is a 4xx or 5xx status with [`ErrorBody`]: 400 for a malformed or invalid
//! request (including a view smaller than the networks decode and more than
//! [`MAX_REQUEST_STYLES`] styles), 404 for an unknown style, job or route, 405 for a wrong
//! method, 409 for what the scene or the server's state does not allow (stylizing a `.ply`, a
//! second bake), 413 for an upload beyond the size or pixel limits, 414 for a URI longer than
//! [`MAX_URI_BYTES`], 503 when the server's memory budget for work in flight is full (try again
//! shortly).

use serde::{Deserialize, Serialize};

use crate::scene::CameraJson;

/// Most entries in the `styles` list of a stylize or bake request. Entries naming the same
/// style are merged (their weights added) before any work.
pub const MAX_REQUEST_STYLES: usize = 8;

/// Longest request URI (path and query) answered; longer ones get 414.
pub const MAX_URI_BYTES: usize = 8 << 10;

/// The body of every error answer.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ErrorBody {
    /// What was wrong, for the page to show.
    pub error: String,
}

/// A style the page can choose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StyleInfo {
    /// Its identifier in requests.
    pub id: String,
    /// Its name (the file stem, or the upload's name).
    pub name: String,
}

/// `GET /api/scene`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneInfo {
    /// The scene's name (its file or folder name).
    pub name: String,
    /// Number of Gaussians.
    pub gaussians: usize,
    /// SH degree of the colours.
    pub sh_degree: usize,
    /// Floats per Gaussian in `/api/gaussians` ([`crate::scene::stride`]).
    pub stride: usize,
    /// Background colour behind the Gaussians.
    pub background: [f32; 3],
    /// Whether the scene can be stylized (a scene bundle with its networks).
    pub stylize: bool,
    /// The bundle's network variant (`standard`, `fullres`), for a bundle.
    pub variant: Option<String>,
    /// The scene's cameras (a bundle's own; an orbit for a `.ply`).
    pub cameras: Vec<CameraJson>,
    /// The styles offered.
    pub styles: Vec<StyleInfo>,
}

/// One style of a request and its weight in the mixture.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WeightedStyle {
    /// The style's identifier.
    pub id: String,
    /// Its weight (0 or more; the weights are normalised to sum 1).
    #[serde(default = "one")]
    pub weight: f64,
}

fn one() -> f64 {
    1.0
}

/// `POST /api/stylize`: stylize the view of `camera`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StylizeRequest {
    /// The view.
    pub camera: CameraJson,
    /// One style, or several mixed by weight.
    pub styles: Vec<WeightedStyle>,
    /// Style strength, 0 (the scene) to 1 (the full style).
    #[serde(default = "one")]
    pub alpha: f64,
    /// Match the style's colours to the view's colour render first.
    #[serde(default)]
    pub preserve_colour: bool,
    /// Reduce the view (intrinsics scaled) so its longer side is at most this, for a quick
    /// preview; `None` keeps its size.
    #[serde(default)]
    pub max_side: Option<u32>,
}

/// `POST /api/bake`: bake a style into the scene's SH colours (`train::bake`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BakeRequest {
    /// One style, or several mixed by weight.
    pub styles: Vec<WeightedStyle>,
    /// Style strength.
    #[serde(default = "one")]
    pub alpha: f64,
    /// Optimisation iterations after the colour solve (0, the solve alone, to 100,000).
    pub iterations: u64,
}

/// The answer to a started job.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobStarted {
    /// The job's identifier.
    pub job: String,
}

/// `GET /api/jobs/{id}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobInfo {
    /// What the job does (`bake`).
    pub kind: String,
    /// `running`, `done` or `failed`.
    pub state: String,
    /// Units of the current stage done.
    pub done: u64,
    /// Units of the current stage.
    pub total: u64,
    /// The current stage, or the error of a failed job.
    pub message: String,
}
