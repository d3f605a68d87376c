//! What the server holds (the scene, its packed Gaussians, the styles, the bake jobs) and the
//! work behind the API, run off the async threads.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use axum::http::StatusCode;
use base::error::chain;
use gaussian::Camera;
use pipeline::cameras::{CameraRequest, CameraSource};
use pipeline::image_io::{self, RgbImage};
use pipeline::render::{render_colour, SceneInput};
use pipeline::stylize::{self, StyleImage};
use pipeline::{Event, Stage};
use runtime::SceneBundle;
use train::BakeConfig;

use crate::api::{
    BakeRequest, JobInfo, SceneInfo, StyleInfo, StylizeRequest, WeightedStyle, MAX_REQUEST_STYLES,
};
use crate::budget::Budget;
use crate::scene::{pack_gaussians, stride, CameraJson};
use crate::{Activity, ViewerConfig, ViewerError};

/// Side of the style thumbnails, in pixels.
const THUMBNAIL_SIDE: u32 = 128;
/// Orbit cameras offered for a `.ply` (which has no cameras of its own).
const PLY_ORBIT_VIEWS: usize = 8;
/// Most bake iterations a request may ask for.
const MAX_BAKE_ITERATIONS: u64 = 100_000;

/// An API error: a status and a message for the page.
#[derive(Debug)]
pub(crate) struct ApiError(pub StatusCode, pub String);

impl ApiError {
    pub(crate) fn bad(message: impl Into<String>) -> Self {
        ApiError(StatusCode::BAD_REQUEST, message.into())
    }

    fn not_found(message: impl Into<String>) -> Self {
        ApiError(StatusCode::NOT_FOUND, message.into())
    }

    fn conflict(message: impl Into<String>) -> Self {
        ApiError(StatusCode::CONFLICT, message.into())
    }

    fn internal(e: impl std::error::Error) -> Self {
        ApiError(StatusCode::INTERNAL_SERVER_ERROR, chain(&e))
    }
}

/// A style and its thumbnail.
struct StoredStyle {
    info: StyleInfo,
    /// Shared by every request that uses it (never copied per request entry).
    image: Arc<StyleImage>,
    thumbnail: Arc<Vec<u8>>,
    uploaded: bool,
    /// Its statistics at every encoder level, once a request has needed them (without colour
    /// preservation, which depends on the view).
    encoded: Option<stylize::StyleTarget>,
}

/// A bake job's progress and result.
#[derive(Default)]
struct Job {
    state: &'static str,
    stage: String,
    done: u64,
    total: u64,
    error: String,
    gaussians: Option<Arc<Vec<u8>>>,
}

/// Everything the handlers share.
pub(crate) struct State {
    pub config: ViewerConfig,
    scene: SceneInput,
    name: String,
    cameras: Vec<(String, Camera)>,
    pub gaussians: Arc<Vec<u8>>,
    styles: Mutex<Vec<StoredStyle>>,
    next_id: AtomicU64,
    jobs: Mutex<HashMap<String, Arc<Mutex<Job>>>>,
    /// Raised when the server stops: a running bake ends after its current iteration.
    pub stop: AtomicBool,
    /// Stylizations and upload decodes running at once ([`STYLIZE_SLOTS`]); more wait for a
    /// slot.
    pub stylize_slots: tokio::sync::Semaphore,
    /// The memory of the work in flight ([`ViewerConfig::memory_budget`]).
    pub budget: Budget,
}

/// Bytes per pixel an upload takes while it is decoded and converted: the decoded samples (up
/// to 8 bytes a pixel for 16-bit RGBA), the `f32` RGB image (12) and its resized copy (12),
/// rounded up.
const UPLOAD_BYTES_PER_PIXEL: u64 = 40;

/// Most stylizations computed at once: each holds up to the tile budget of network memory, and
/// two already share the cores; more requests wait their turn.
pub(crate) const STYLIZE_SLOTS: usize = 2;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A thumbnail PNG of `img`, longer side at most [`THUMBNAIL_SIDE`].
fn thumbnail(img: &RgbImage) -> Result<Vec<u8>, pipeline::Error> {
    let side = img.width.max(img.height).max(1) as f64;
    let s = (THUMBNAIL_SIDE as f64 / side).min(1.0);
    let w = ((img.width as f64 * s).round() as u32).max(1);
    let h = ((img.height as f64 * s).round() as u32).max(1);
    image_io::encode_png(&image_io::thumbnail(img, w, h))
}

/// The names of the folders and files that the pipeline's own layouts give every scene
/// (`OUT/features/bundle`, `OUT/geometry/point_cloud.ply`, the official
/// `point_cloud/iteration_N/point_cloud.ply`): they say nothing of which scene it is.
const LAYOUT_NAMES: [&str; 5] = [
    "bundle",
    "features",
    "geometry",
    "point_cloud",
    "point_cloud.ply",
];

/// The scene's name for the page: the last component of its path that is not a name of the
/// pipeline's layouts ([`LAYOUT_NAMES`], `iteration_N`), so `dsgs-demo/features/bundle` is
/// `dsgs-demo`; the file or folder name when every component is one.
fn scene_name(path: &Path) -> String {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let names: Vec<String> = absolute
        .components()
        .filter_map(|c| match c {
            std::path::Component::Normal(n) => Some(n.to_string_lossy().into_owned()),
            _ => None,
        })
        .collect();
    let generic = |n: &str| LAYOUT_NAMES.contains(&n) || n.starts_with("iteration_");
    names
        .iter()
        .rev()
        .find(|n| !generic(n))
        .or(names.last())
        .cloned()
        .unwrap_or_else(|| "scene".into())
}

/// An upload's name: its printable characters, at most 64, or `upload`.
fn clean_name(name: &str) -> String {
    let n: String = name
        .chars()
        .filter(|c| c.is_alphanumeric() || " ._-()".contains(*c))
        .take(64)
        .collect();
    let n = n.trim();
    let n = Path::new(n)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    if n.is_empty() {
        "upload".into()
    } else {
        n
    }
}

impl State {
    /// Reads the scene and the style images.
    pub(crate) fn load(config: ViewerConfig) -> Result<State, ViewerError> {
        let scene = SceneInput::open(&config.scene)?;
        let name = scene_name(&config.scene);
        let known = scene.known_cameras();
        let cameras: Vec<(String, Camera)> = if known.cameras.is_empty() {
            let request = CameraRequest {
                frames: Some(PLY_ORBIT_VIEWS),
                ..CameraRequest::new(CameraSource::Orbit)
            };
            pipeline::cameras::select(&request, &known, scene.gaussians())?
                .into_iter()
                .enumerate()
                .map(|(i, c)| (format!("orbit {i}"), c))
                .collect()
        } else {
            known
                .names
                .iter()
                .cloned()
                .zip(known.cameras.iter().copied())
                .collect()
        };
        let gaussians = Arc::new(pack_gaussians(scene.gaussians()));
        let mut styles = Vec::new();
        let loaded = if config.styles.is_empty() {
            Vec::new()
        } else {
            stylize::load_styles(&config.styles, config.style_side)?
        };
        for (i, image) in loaded.into_iter().enumerate() {
            styles.push(StoredStyle {
                info: StyleInfo {
                    id: format!("s{i}"),
                    name: image.name.clone(),
                },
                thumbnail: Arc::new(thumbnail(&image.image)?),
                image: Arc::new(image),
                uploaded: false,
                encoded: None,
            });
        }
        Ok(State {
            next_id: AtomicU64::new(styles.len() as u64),
            scene,
            name,
            cameras,
            gaussians,
            styles: Mutex::new(styles),
            jobs: Mutex::new(HashMap::new()),
            stop: AtomicBool::new(false),
            stylize_slots: tokio::sync::Semaphore::new(STYLIZE_SLOTS),
            budget: Budget::new(config.memory_budget),
            config,
        })
    }

    fn bundle(&self) -> Result<&SceneBundle, ApiError> {
        match &self.scene {
            SceneInput::Bundle { bundle, .. } => Ok(bundle),
            SceneInput::Ply { .. } => Err(ApiError::conflict(
                "this scene is a .ply: stylizing needs a scene bundle (dsgs fit-features)",
            )),
        }
    }

    /// `GET /api/scene`.
    pub(crate) fn info(&self) -> SceneInfo {
        let g = self.scene.gaussians();
        let (stylize, variant) = match &self.scene {
            SceneInput::Bundle { bundle, .. } => (true, Some(bundle.info.variant.as_str().into())),
            SceneInput::Ply { .. } => (false, None),
        };
        SceneInfo {
            name: self.name.clone(),
            gaussians: g.len(),
            sh_degree: g.sh_degree,
            stride: stride(g.sh_degree),
            background: self.scene.background(),
            stylize,
            variant,
            cameras: self
                .cameras
                .iter()
                .map(|(n, c)| CameraJson::new(n, c))
                .collect(),
            styles: lock(&self.styles).iter().map(|s| s.info.clone()).collect(),
        }
    }

    /// A style's thumbnail PNG.
    pub(crate) fn thumbnail(&self, id: &str) -> Result<Arc<Vec<u8>>, ApiError> {
        lock(&self.styles)
            .iter()
            .find(|s| s.info.id == id)
            .map(|s| s.thumbnail.clone())
            .ok_or_else(|| ApiError::not_found(format!("no style `{id}`")))
    }

    /// The size of an uploaded image from its header, refused (413) beyond
    /// [`ViewerConfig::max_upload_pixels`] before anything is decoded, and the memory its
    /// decoding takes by estimate.
    pub(crate) fn upload_cost(&self, name: &str, bytes: &[u8]) -> Result<u64, ApiError> {
        if bytes.is_empty() {
            return Err(ApiError::bad(
                "the upload is empty: send an image file as the body",
            ));
        }
        let shown = PathBuf::from(format!("upload `{}`", clean_name(name)));
        let (w, h) = gaussian::dataset::images::encoded_size(bytes, &shown)
            .map_err(|e| ApiError::bad(chain(&e)))?;
        let pixels = w as u64 * h as u64;
        let max = self.config.max_upload_pixels;
        if pixels > max {
            return Err(ApiError(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!(
                    "{}: the image is {w}x{h} = {pixels} pixels; an upload may have at most \
                     {max} pixels",
                    shown.display()
                ),
            ));
        }
        Ok(pixels * UPLOAD_BYTES_PER_PIXEL)
    }

    /// `POST /api/styles`: decodes an uploaded image under the size limits and keeps it (the
    /// oldest upload is dropped beyond [`ViewerConfig::max_uploads`]). The caller has checked
    /// its size ([`State::upload_cost`]).
    pub(crate) fn upload(&self, name: &str, bytes: &[u8]) -> Result<StyleInfo, ApiError> {
        if bytes.is_empty() {
            return Err(ApiError::bad(
                "the upload is empty: send an image file as the body",
            ));
        }
        let name = clean_name(name);
        let shown = PathBuf::from(format!("upload `{name}`"));
        let img = gaussian::dataset::images::decode_rgb(bytes, &shown, [0.0; 3]).map_err(|e| {
            let status = match e {
                gaussian::dataset::DatasetError::ImageTooLarge { .. } => {
                    StatusCode::PAYLOAD_TOO_LARGE
                }
                _ => StatusCode::BAD_REQUEST,
            };
            ApiError(status, chain(&e))
        })?;
        let side = self.config.style_side;
        let img = if img.width.max(img.height) > side {
            let s = side as f64 / img.width.max(img.height) as f64;
            let w = ((img.width as f64 * s).round() as u32).max(1);
            let h = ((img.height as f64 * s).round() as u32).max(1);
            gaussian::dataset::images::resize(&img, w, h)
        } else {
            img
        };
        let id = format!("u{}", self.next_id.fetch_add(1, Ordering::Relaxed));
        let info = StyleInfo {
            id: id.clone(),
            name: name.clone(),
        };
        let stored = StoredStyle {
            info: info.clone(),
            thumbnail: Arc::new(thumbnail(&img).map_err(ApiError::internal)?),
            image: Arc::new(StyleImage {
                name,
                path: shown,
                image: img,
            }),
            uploaded: true,
            encoded: None,
        };
        let mut styles = lock(&self.styles);
        styles.push(stored);
        let uploads = styles.iter().filter(|s| s.uploaded).count();
        if uploads > self.config.max_uploads {
            if let Some(i) = styles.iter().position(|s| s.uploaded) {
                styles.remove(i);
            }
        }
        Ok(info)
    }

    /// The distinct styles of a request (entries naming the same style merged, their weights
    /// added) with their images, at most [`MAX_REQUEST_STYLES`] entries.
    fn styles_of(
        &self,
        chosen: &[WeightedStyle],
    ) -> Result<Vec<(WeightedStyle, Arc<StyleImage>)>, ApiError> {
        if chosen.is_empty() {
            return Err(ApiError::bad("choose at least one style"));
        }
        if chosen.len() > MAX_REQUEST_STYLES {
            return Err(ApiError::bad(format!(
                "{} styles in one request; a mixture has at most {MAX_REQUEST_STYLES}",
                chosen.len()
            )));
        }
        let styles = lock(&self.styles);
        let mut out: Vec<(WeightedStyle, Arc<StyleImage>)> = Vec::new();
        for c in chosen {
            if let Some((seen, _)) = out.iter_mut().find(|(s, _)| s.id == c.id) {
                seen.weight += c.weight;
                continue;
            }
            let s = styles
                .iter()
                .find(|s| s.info.id == c.id)
                .ok_or_else(|| ApiError::not_found(format!("no style `{}`", c.id)))?;
            out.push((c.clone(), s.image.clone()));
        }
        Ok(out)
    }

    /// The one target of a request: its styles' statistics (cached per style), mixed by the
    /// weights; with colour preservation the styles are encoded afresh against `colour`.
    fn target(
        &self,
        chosen: &[WeightedStyle],
        colour: Option<&ndarray::Array4<f32>>,
    ) -> Result<stylize::StyleTarget, ApiError> {
        let bundle = self.bundle()?;
        let chosen = self.styles_of(chosen)?;
        let weights = if chosen.len() > 1 {
            let w: Vec<f64> = chosen.iter().map(|(c, _)| c.weight).collect();
            Some(stylize::normalised_weights(&w, w.len()).map_err(|e| ApiError::bad(chain(&e)))?)
        } else {
            None
        };
        let encoded = if colour.is_some() {
            // At most MAX_REQUEST_STYLES images, each at most the style side.
            let images: Vec<StyleImage> = chosen.iter().map(|(_, i)| (**i).clone()).collect();
            stylize::encode_styles(&bundle.encoder, &images, colour).map_err(ApiError::internal)?
        } else {
            let mut out = Vec::with_capacity(chosen.len());
            for (c, img) in &chosen {
                let cached = lock(&self.styles)
                    .iter()
                    .find(|s| s.info.id == c.id)
                    .and_then(|s| s.encoded.clone());
                let t = match cached {
                    Some(t) => t,
                    None => {
                        let t = stylize::encode_styles(
                            &bundle.encoder,
                            std::slice::from_ref(&**img),
                            None,
                        )
                        .map_err(ApiError::internal)?
                        .remove(0);
                        if let Some(s) = lock(&self.styles).iter_mut().find(|s| s.info.id == c.id) {
                            s.encoded = Some(t.clone());
                        }
                        t
                    }
                };
                out.push(t);
            }
            out
        };
        let mut targets = stylize::mix_targets(encoded, weights.as_deref())
            .map_err(|e| ApiError::bad(chain(&e)))?;
        Ok(targets.remove(0))
    }

    /// The camera of a stylize request, checked (400): valid, at most the view-size limit, and
    /// after `max_side` still large enough for the networks ([`SceneBundle::check_view_size`]).
    /// Also the request's estimated working memory.
    pub(crate) fn stylize_camera(&self, req: &StylizeRequest) -> Result<(Camera, u64), ApiError> {
        let bundle = self.bundle()?;
        stylize::check_alpha(req.alpha).map_err(|e| ApiError::bad(chain(&e)))?;
        let mut camera = req
            .camera
            .camera(self.config.max_view_side)
            .map_err(ApiError::bad)?;
        if let Some(max) = req.max_side {
            if max == 0 {
                return Err(ApiError::bad("max_side must be at least 1"));
            }
            let k = camera.intrinsics;
            let side = k.width.max(k.height);
            if side > max {
                camera = camera.scaled(max as f64 / side as f64);
            }
        }
        let k = camera.intrinsics;
        bundle
            .check_view_size(k.width, k.height)
            .map_err(ApiError::bad)?;
        if req.styles.len() > MAX_REQUEST_STYLES {
            return Err(ApiError::bad(format!(
                "{} styles in one request; a mixture has at most {MAX_REQUEST_STYLES}",
                req.styles.len()
            )));
        }
        Ok((camera, self.stylize_cost(bundle, &camera)))
    }

    /// The working memory of stylizing `camera`'s view, by estimate: the tile budget of the
    /// networks, the feature map and its lifted copy at the feature resolution (each kept
    /// twice while it is transformed), and the image with its colour render and PNG.
    fn stylize_cost(&self, bundle: &SceneBundle, camera: &Camera) -> u64 {
        let k = camera.intrinsics;
        let (fw, fh) = bundle.feature_size(k.width, k.height);
        let channels = (bundle.info.feature_dim + bundle.lifter.out_channels()) as u64;
        let features = fw as u64 * fh as u64 * channels * 4 * 2;
        let image = k.width as u64 * k.height as u64 * 12 * 3;
        self.config.tile_budget + features + image
    }

    /// `POST /api/stylize`: the stylized view as a PNG, for a camera checked by
    /// [`State::stylize_camera`].
    pub(crate) fn stylize(
        &self,
        req: &StylizeRequest,
        camera: &Camera,
    ) -> Result<Vec<u8>, ApiError> {
        let started = std::time::Instant::now();
        let result = self.stylize_png(req, camera);
        self.report(match &result {
            Ok(_) => Activity::Stylized {
                width: camera.intrinsics.width,
                height: camera.intrinsics.height,
                styles: self.style_names(&req.styles),
                seconds: started.elapsed().as_secs_f64(),
            },
            Err(e) => Activity::StylizeFailed {
                message: e.1.clone(),
            },
        });
        result
    }

    /// The names of the chosen styles (their ids where unknown).
    fn style_names(&self, chosen: &[WeightedStyle]) -> Vec<String> {
        let styles = lock(&self.styles);
        chosen
            .iter()
            .map(|c| {
                styles
                    .iter()
                    .find(|s| s.info.id == c.id)
                    .map_or_else(|| c.id.clone(), |s| s.info.name.clone())
            })
            .collect()
    }

    /// Tells the program what happened ([`ViewerConfig::activity`]); a program that stopped
    /// listening is not an error.
    fn report(&self, activity: Activity) {
        if let Some(tx) = &self.config.activity {
            let _ = tx.send(activity);
        }
    }

    fn stylize_png(&self, req: &StylizeRequest, camera: &Camera) -> Result<Vec<u8>, ApiError> {
        let bundle = self.bundle()?;
        let camera = *camera;
        let content = if req.preserve_colour {
            let r = render_colour(&bundle.scene, &camera, bundle.info.background)
                .map_err(ApiError::internal)?;
            Some(stylize::colour_content(&[&r.image]).map_err(ApiError::internal)?)
        } else {
            None
        };
        let target = self.target(&req.styles, content.as_ref())?;
        let frame = bundle
            .frame(
                &camera,
                target.stats.deepest(),
                req.alpha,
                self.config.tile_budget,
            )
            .map_err(ApiError::internal)?;
        image_io::encode_png(&frame.image).map_err(ApiError::internal)
    }

    /// `POST /api/bake`: checks the request and starts the bake on a thread of its own.
    pub(crate) fn start_bake(self: &Arc<Self>, req: &BakeRequest) -> Result<String, ApiError> {
        self.bundle()?;
        stylize::check_alpha(req.alpha).map_err(|e| ApiError::bad(chain(&e)))?;
        if req.iterations > MAX_BAKE_ITERATIONS {
            return Err(ApiError::bad(format!(
                "iterations {}: a bake runs 0 (the colour solve alone) to {MAX_BAKE_ITERATIONS} \
                 iterations",
                req.iterations
            )));
        }
        let target = self.target(&req.styles, None)?;
        let job = Arc::new(Mutex::new(Job {
            state: "running",
            stage: "starting".into(),
            ..Job::default()
        }));
        let id = {
            let mut jobs = lock(&self.jobs);
            if jobs.values().any(|j| lock(j).state == "running") {
                return Err(ApiError::conflict(
                    "a bake is running already; wait for it to finish",
                ));
            }
            let id = format!("bake{}", self.next_id.fetch_add(1, Ordering::Relaxed));
            jobs.insert(id.clone(), job.clone());
            id
        };
        let state = self.clone();
        let (alpha, iterations) = (req.alpha, req.iterations);
        self.report(Activity::BakeStarted {
            job: id.clone(),
            iterations,
        });
        let job_id = id.clone();
        std::thread::spawn(move || {
            let started = std::time::Instant::now();
            let result = state.bake(&target, alpha, iterations, &job);
            state.report(Activity::BakeEnded {
                job: job_id,
                error: result.as_ref().err().cloned(),
                seconds: started.elapsed().as_secs_f64(),
            });
            let mut j = lock(&job);
            match result {
                Ok(g) => {
                    j.state = "done";
                    j.gaussians = Some(Arc::new(g));
                }
                Err(e) => {
                    j.state = "failed";
                    j.error = e;
                }
            }
        });
        Ok(id)
    }

    fn bake(
        &self,
        target: &stylize::StyleTarget,
        alpha: f64,
        iterations: u64,
        job: &Mutex<Job>,
    ) -> Result<Vec<u8>, String> {
        let bundle = self.bundle().map_err(|e| e.1)?;
        let stats = bundle
            .target_stats(target.stats.deepest(), alpha)
            .map_err(|e| chain(&e))?;
        let config = BakeConfig {
            iterations,
            tile_budget_mib: (self.config.tile_budget >> 20).max(1),
            ..BakeConfig::default()
        };
        let sink = |e: Event| {
            let mut j = lock(job);
            match e {
                Event::StageStarted { stage, total, done } => {
                    j.stage = stage_name(stage);
                    j.total = total;
                    j.done = done;
                }
                Event::Progress { done, .. } => j.done = done,
                _ => {}
            }
        };
        let run = train::Run {
            out_dir: None,
            stop: Some(&self.stop),
            sink: &sink,
        };
        let report = train::bake(bundle, &stats, &config, None, &run).map_err(|e| chain(&e))?;
        if report.run.interrupted {
            return Err("the server stopped during the bake".into());
        }
        Ok(pack_gaussians(&report.scene))
    }

    /// `GET /api/jobs/{id}`.
    pub(crate) fn job(&self, id: &str) -> Result<JobInfo, ApiError> {
        let job = lock(&self.jobs)
            .get(id)
            .cloned()
            .ok_or_else(|| ApiError::not_found(format!("no job `{id}`")))?;
        let j = lock(&job);
        Ok(JobInfo {
            kind: "bake".into(),
            state: j.state.into(),
            done: j.done,
            total: j.total,
            message: if j.state == "failed" {
                j.error.clone()
            } else {
                j.stage.clone()
            },
        })
    }

    /// `GET /api/jobs/{id}/gaussians`: the baked scene of a finished job.
    pub(crate) fn job_gaussians(&self, id: &str) -> Result<Arc<Vec<u8>>, ApiError> {
        let job = lock(&self.jobs)
            .get(id)
            .cloned()
            .ok_or_else(|| ApiError::not_found(format!("no job `{id}`")))?;
        let j = lock(&job);
        j.gaussians
            .clone()
            .ok_or_else(|| ApiError::conflict(format!("job `{id}` is {}", j.state)))
    }
}

fn stage_name(stage: Stage) -> String {
    match stage {
        Stage::BakeTargets => "rendering the stylized targets".into(),
        other => format!("{other:?}").to_lowercase(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_is_named_by_its_folder_not_by_the_pipeline_layout() {
        for (path, name) in [
            ("/runs/dsgs-demo/features/bundle", "dsgs-demo"),
            ("/runs/beer/geometry/point_cloud.ply", "beer"),
            (
                "/o/garden/point_cloud/iteration_30000/point_cloud.ply",
                "garden",
            ),
            ("/scenes/lego_bundle", "lego_bundle"),
            ("/x/trained_9080.ply", "trained_9080.ply"),
            ("/bundle", "bundle"),
        ] {
            assert_eq!(scene_name(Path::new(path)), name, "{path}");
        }
    }
}
