//! Where rendering commands put their cameras: the cameras of a dataset or a bundle, the
//! held-out split, a smooth tour of where they stand, or an orbit.
//!
//! Cameras follow `gaussian::camera` (`camera_from_world` in OpenCV axes, pixel centres at
//! `i + 0.5`).
//!
//! * `dataset`: every known camera (at most `frames` of them, evenly spaced, when given).
//! * `test`: the held-out ones (a bundle's `held_out` flags; for a dataset every 8th image,
//!   index `% 8 == 0`, as `gaussian::dataset::eval_split`).
//! * `path`: `frames` cameras on a smooth tour of the region the known cameras see the scene
//!   from ([`gaussian::camera_path::tour`]): all the way round when they surround it, else along
//!   the arc they cover, at their (smoothed) heights and distances, always looking at the point
//!   nearest to all their optical axes, about their mean image-up direction (or `up`). Never
//!   a jump between cameras that are far apart in the capture's order.
//! * `orbit`: `frames` cameras on a circle. With known cameras it starts at the first one and
//!   circles the point nearest to all their optical axes (least squares) about their mean
//!   image-up direction ([`gaussian::camera_path::orbit_from`]). Without cameras it circles the
//!   per-axis median of the Gaussian means at `ORBIT_RADIUS_FACTOR` times their median distance
//!   from it, 20 degrees above the plane orthogonal to `up` (default world `-y`, the usual up
//!   axis of COLMAP reconstructions), with a 60 degree horizontal field of view.
//!
//! Image sizes: `width` and `height` resize every camera (one of them alone keeps each camera's
//! aspect ratio); `scale` scales them ([`gaussian::Camera::scaled`]); without any, the cameras
//! keep their size, and cameras made from nothing are 256 x 256.
//!
//! Size limits: every image size, given or computed (the flags, a scale factor, an aspect ratio
//! kept, the cameras of a dataset or bundle), must be 1 to [`MAX_IMAGE_SIDE`] pixels per side
//! and at most [`MAX_IMAGE_PIXELS`] pixels in all ([`check_image_size`]). [`select`] checks the
//! request ([`CameraRequest::check`]) before making any camera and every camera it returns, so
//! an oversized request fails with a message naming the flag and the limit instead of
//! allocating.

use crate::cli::{at_least_one, direction, one_of, positive, whole_in};
use crate::error::{bail, Context, Error, Result};
use gaussian::camera::MAX_IMAGE_SIDE;
use gaussian::camera_path::{arc_from, look_at_point, mean_up, orbit, orbit_from, tour};
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DVec3;

/// The most pixels (width times height) of an image the pipeline renders, decodes or reads as a
/// style, beside the per-side limit [`MAX_IMAGE_SIDE`]: 8192 x 8192.
///
/// The side limit alone lets through 16384 x 16384 = 2^28 pixels, 3 GiB for one RGB `f32`
/// image; a render holds several such planes (colour, alpha, depth, the rasterizer's own) and a
/// stylized view tens to hundreds of feature channels per pixel, so sizes near that product
/// abort on allocation on most machines. A quarter of it still takes every real camera (a 4K
/// frame is an eighth of it) and panoramas up to 16384 x 4096.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;

/// Checks an image size against [`MAX_IMAGE_SIDE`] and [`MAX_IMAGE_PIXELS`]; the error starts
/// with `what` (the flag, file or camera the size comes from) and states the limit.
pub fn check_image_size(what: &str, width: u64, height: u64) -> Result<()> {
    let max = MAX_IMAGE_SIDE as u64;
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
        bail!(
            "{what}: {width} x {height} pixels; an image side must be 1 to {MAX_IMAGE_SIDE} \
             pixels"
        );
    }
    let pixels = width * height;
    if pixels > MAX_IMAGE_PIXELS {
        bail!(
            "{what}: {width} x {height} = {pixels} pixels; an image may have at most \
             {MAX_IMAGE_PIXELS} pixels"
        );
    }
    Ok(())
}

/// Checks the size of every camera against the limits ([`check_image_size`]), naming the
/// first camera outside them by its index in `cameras`.
pub fn check_camera_sizes(cameras: &[Camera]) -> Result<()> {
    for (i, c) in cameras.iter().enumerate() {
        let k = &c.intrinsics;
        check_image_size(&format!("camera {i}"), k.width as u64, k.height as u64)?;
    }
    Ok(())
}

/// The help of `--cameras`, without its default: each command adds its own
/// ([`DEFAULT_SOURCES`]).
pub const CAMERAS_HELP: &str = "Camera source: the dataset's or bundle's cameras, the held-out \
     ones, a smooth tour round what they look at through where they stand, an orbit, or a dense \
     arc (frames 1 degree apart around what the cameras look at)";

/// The camera source of each command that renders when `--cameras` is not given.
pub const DEFAULT_SOURCES: [(&str, CameraSource); 3] = [
    ("render", CameraSource::Orbit),
    ("stylize", CameraSource::Orbit),
    ("eval", CameraSource::Dense),
];

/// `cmd` with each command's default camera source ([`DEFAULT_SOURCES`]) in the help of its
/// `--cameras`.
pub fn with_default_sources(mut cmd: clap::Command) -> clap::Command {
    for (name, source) in DEFAULT_SOURCES {
        let help = crate::cli::with_default(CAMERAS_HELP, source.as_str());
        cmd = cmd.mut_subcommand(name, |sub| sub.mut_arg("cameras", |a| a.help(help)));
    }
    cmd
}

/// The camera source of `command` when `--cameras` is not given ([`DEFAULT_SOURCES`]; orbit for
/// a command not listed).
pub fn default_source(command: &str) -> CameraSource {
    DEFAULT_SOURCES
        .iter()
        .find(|(c, _)| *c == command)
        .map_or(CameraSource::Orbit, |(_, s)| *s)
}

/// The orbit radius, in median distances of the Gaussians from their median centre.
pub const ORBIT_RADIUS_FACTOR: f64 = 2.5;
/// Default number of frames of generated paths and orbits.
pub const DEFAULT_FRAMES: usize = 30;
/// Default image side of cameras made from nothing.
pub const DEFAULT_SIDE: u32 = 256;

/// Which cameras to render from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraSource {
    /// Every camera of the dataset or bundle.
    Dataset,
    /// The held-out cameras.
    Test,
    /// A smooth tour round what the cameras look at, through where they stand.
    Path,
    /// An orbit around the scene.
    Orbit,
    /// An arc of the orbit through the first camera around what the cameras look at, frames
    /// [`DENSE_STEP_DEGREES`] apart: consecutive frames a small fixed rotation and translation
    /// apart, as in a video (the default of `dsgs eval`).
    Dense,
}

/// How far apart consecutive cameras of a sequence are, on average.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PathStep {
    /// Mean angle of the rotation between consecutive cameras, in degrees.
    pub degrees: f64,
    /// Mean distance between consecutive camera centres, in scene units.
    pub distance: f64,
}

/// The mean step between consecutive `cameras` (`None` for fewer than two).
pub fn path_step(cameras: &[Camera]) -> Option<PathStep> {
    if cameras.len() < 2 {
        return None;
    }
    let n = (cameras.len() - 1) as f64;
    let (mut degrees, mut distance) = (0.0, 0.0);
    for w in cameras.windows(2) {
        let r = w[0].rotation().transpose() * w[1].rotation();
        let cos = ((r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0);
        degrees += cos.acos().to_degrees();
        distance += (w[1].center() - w[0].center()).length();
    }
    Some(PathStep {
        degrees: degrees / n,
        distance: distance / n,
    })
}

/// Degrees between consecutive frames of the [`CameraSource::Dense`] path.
pub const DENSE_STEP_DEGREES: f64 = 1.0;

impl CameraSource {
    /// Every value, by its command-line name.
    pub const NAMES: &'static [&'static str] = &["dataset", "test", "path", "orbit", "dense"];

    /// The command-line name.
    pub fn as_str(self) -> &'static str {
        match self {
            CameraSource::Dataset => "dataset",
            CameraSource::Test => "test",
            CameraSource::Path => "path",
            CameraSource::Orbit => "orbit",
            CameraSource::Dense => "dense",
        }
    }
}

impl std::str::FromStr for CameraSource {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "dataset" => Ok(CameraSource::Dataset),
            "test" => Ok(CameraSource::Test),
            "path" => Ok(CameraSource::Path),
            "orbit" => Ok(CameraSource::Orbit),
            "dense" => Ok(CameraSource::Dense),
            _ => Err(format!(
                "unknown camera source `{s}` (expected one of: dataset, test, path, orbit, dense)"
            )),
        }
    }
}

/// Cameras known for a scene (from a dataset or a bundle), with held-out flags and names.
#[derive(Clone, Debug, Default)]
pub struct KnownCameras {
    /// The cameras, in the order of the dataset or bundle.
    pub cameras: Vec<Camera>,
    /// Whether each camera is held out from training (the `test` source).
    pub held_out: Vec<bool>,
    /// The image name of each camera.
    pub names: Vec<String>,
    /// Where they came from, for error messages (a dataset or bundle path).
    pub origin: String,
}

impl KnownCameras {
    /// The cameras of a dataset directory, held-out flags from the every-8th split.
    pub fn from_dataset(dir: &std::path::Path) -> Result<KnownCameras> {
        let d = gaussian::Dataset::load(dir, &gaussian::LoadOptions::default())
            .with_context(|| format!("loading the dataset {}", dir.display()))?;
        let split = d.split();
        let mut held_out = vec![false; d.len()];
        for i in split.test {
            held_out[i] = true;
        }
        Ok(KnownCameras {
            cameras: d.cameras,
            held_out,
            names: d.names,
            origin: dir.display().to_string(),
        })
    }

    /// The cameras stored in a bundle.
    pub fn from_bundle(bundle: &runtime::SceneBundle, origin: &str) -> KnownCameras {
        KnownCameras::from_bundle_info(&bundle.info, origin)
    }

    /// The cameras recorded in a bundle's description.
    pub fn from_bundle_info(info: &runtime::BundleInfo, origin: &str) -> KnownCameras {
        KnownCameras {
            cameras: info.cameras(),
            held_out: info.cameras.iter().map(|c| c.held_out).collect(),
            names: info.cameras.iter().map(|c| c.name.clone()).collect(),
            origin: origin.to_string(),
        }
    }

    /// The cameras of a directory: a scene bundle's (when it holds `bundle.json`, at the
    /// bundle's training resolution), else a dataset's.
    pub fn from_dir(dir: &std::path::Path) -> Result<KnownCameras> {
        if dir.join(runtime::bundle::INFO_FILE).is_file() {
            let info = runtime::BundleInfo::load(dir)
                .with_context(|| format!("reading the cameras of the bundle {}", dir.display()))?;
            return Ok(KnownCameras::from_bundle_info(
                &info,
                &dir.display().to_string(),
            ));
        }
        KnownCameras::from_dataset(dir)
    }
}

/// The camera flags of the commands that render a sequence (`--cameras`, `--frames`,
/// `--width`, `--height`, `--scale`, `--dataset`, `--up`), as [`clap::Args`]: a
/// [`CameraRequest`] whose source has a default per command, and where the known cameras come
/// from.
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct CameraArgs {
    /// The source; `None` takes the command's default ([`CameraArgs::request`]).
    #[arg(
        long,
        value_parser = one_of::<CameraSource>(CameraSource::NAMES.iter().copied()),
        help = CAMERAS_HELP
    )]
    pub cameras: Option<CameraSource>,
    /// [`CameraRequest::frames`].
    #[arg(long, value_parser = at_least_one::<usize>(), help = format!(
        "Number of frames (path and orbit), or at most this many cameras (dataset and test); at \
         least 1 [default: {DEFAULT_FRAMES} for path and orbit, every camera for dataset and \
         test]",
    ))]
    pub frames: Option<usize>,
    /// [`CameraRequest::width`].
    #[arg(long, value_parser = whole_in(1, MAX_IMAGE_SIDE), help = format!(
        "Image width, 1 to {MAX_IMAGE_SIDE} (alone: keeps the aspect ratio) [default: the \
         cameras' width; {DEFAULT_SIDE} for an orbit without cameras]",
    ))]
    pub width: Option<u32>,
    /// [`CameraRequest::height`].
    #[arg(long, value_parser = whole_in(1, MAX_IMAGE_SIDE), help = format!(
        "Image height, 1 to {MAX_IMAGE_SIDE} (alone: keeps the aspect ratio) [default: the \
         cameras' height; {DEFAULT_SIDE} for an orbit without cameras]",
    ))]
    pub height: Option<u32>,
    /// [`CameraRequest::scale`].
    #[arg(
        long,
        value_parser = positive,
        help = "Scale every camera's image by this factor (above 0) [default: 1]"
    )]
    pub scale: Option<f64>,
    /// The inverse of `scale`, in the words of the dataset commands (`fit-geometry`'s
    /// `dataset.downscale`): the cameras of a dataset at the size a scene was fitted at.
    #[arg(
        long,
        value_parser = positive,
        conflicts_with = "scale",
        help = "Divide every camera's image size by this factor, as fit-geometry's --downscale \
                does (above 0; the inverse of --scale) [default: 1]"
    )]
    pub downscale: Option<f64>,
    /// Take the known cameras from this dataset or bundle directory instead of the scene's
    /// ([`KnownCameras::from_dir`]).
    #[arg(
        long,
        help = "Take the cameras from this directory instead of the scene: a dataset, or a scene \
                bundle (its cameras at its training size, e.g. to render a baked `.ply` from \
                them) [default: the scene's own cameras]"
    )]
    pub dataset: Option<std::path::PathBuf>,
    /// [`CameraRequest::up`].
    #[arg(
        long,
        value_parser = direction,
        allow_hyphen_values = true,
        help = "World up axis of orbits, as x,y,z (finite, not zero) [default: the cameras' mean \
                image-up, else 0,-1,0]"
    )]
    pub up: Option<DVec3>,
}

impl CameraArgs {
    /// The request, with `default` as the source when none is given.
    pub fn request(&self, default: CameraSource) -> CameraRequest {
        CameraRequest {
            source: self.cameras.unwrap_or(default),
            frames: self.frames,
            width: self.width,
            height: self.height,
            scale: self.scale.or(self.downscale.map(|d| 1.0 / d)),
            up: self.up,
        }
    }

    /// The known cameras: those of [`CameraArgs::dataset`] when given, else `scene`'s.
    pub fn known(&self, scene: KnownCameras) -> Result<KnownCameras> {
        match &self.dataset {
            Some(d) => KnownCameras::from_dir(d),
            None => Ok(scene),
        }
    }

    /// The cameras the flags ask for ([`select`]), around a scene of `gaussians` whose own
    /// cameras are `scene`, with `default` as the source when none is given.
    pub fn select(
        &self,
        default: CameraSource,
        scene: KnownCameras,
        gaussians: &FeatureGaussians<f32>,
    ) -> Result<Vec<Camera>> {
        select(&self.request(default), &self.known(scene)?, gaussians)
    }
}

/// A camera request.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRequest {
    /// Which cameras (`--cameras`: `dataset`, `test`, `path`, `orbit` or `dense`).
    pub source: CameraSource,
    /// Number of frames of a path or orbit (default [`DEFAULT_FRAMES`]), or at most this many
    /// cameras of `dataset` and `test`, evenly spaced (`--frames`).
    pub frames: Option<usize>,
    /// Image width; alone it keeps each camera's aspect ratio (`--width`).
    pub width: Option<u32>,
    /// Image height; alone it keeps each camera's aspect ratio (`--height`).
    pub height: Option<u32>,
    /// Factor scaling every camera's image (`--scale`).
    pub scale: Option<f64>,
    /// World up axis of orbits (`--up`); without it, the mean image-up of the known cameras,
    /// else `-y`.
    pub up: Option<DVec3>,
}

impl CameraRequest {
    /// A request for `source` with no size or frame options.
    pub fn new(source: CameraSource) -> CameraRequest {
        CameraRequest {
            source,
            frames: None,
            width: None,
            height: None,
            scale: None,
            up: None,
        }
    }

    /// Checks the values of the request on their own: at least one frame, a finite positive
    /// scale, width and height 1 to [`MAX_IMAGE_SIDE`] and, when both are given, at most
    /// [`MAX_IMAGE_PIXELS`] pixels. The error names the flag and the limit.
    pub fn check(&self) -> Result<()> {
        if self.frames == Some(0) {
            bail!("--frames must be at least 1");
        }
        if let Some(s) = self.scale {
            if !(s > 0.0 && s.is_finite()) {
                bail!("--scale {s} is not a positive factor");
            }
        }
        for (flag, v) in [("--width", self.width), ("--height", self.height)] {
            if let Some(v) = v {
                if !(1..=MAX_IMAGE_SIDE).contains(&v) {
                    bail!("{flag} {v}: an image side must be 1 to {MAX_IMAGE_SIDE} pixels");
                }
            }
        }
        if let (Some(w), Some(h)) = (self.width, self.height) {
            check_image_size(&format!("--width {w} --height {h}"), w as u64, h as u64)?;
        }
        Ok(())
    }

    /// The flags that change the cameras' sizes, as given (e.g. `--width 64 --scale 2`).
    fn size_flags(&self) -> String {
        let mut flags = Vec::new();
        if let Some(w) = self.width {
            flags.push(format!("--width {w}"));
        }
        if let Some(h) = self.height {
            flags.push(format!("--height {h}"));
        }
        if let Some(s) = self.scale {
            flags.push(format!("--scale {s}"));
        }
        flags.join(" ")
    }
}

/// `n` indices spread evenly over `0..len` (all of them when `n >= len`).
pub fn evenly_spaced(len: usize, n: usize) -> Vec<usize> {
    if n >= len {
        return (0..len).collect();
    }
    if n == 1 {
        return vec![0];
    }
    (0..n)
        .map(|k| ((k * (len - 1)) as f64 / (n - 1) as f64).round() as usize)
        .collect()
}

/// The per-axis median of the Gaussian means.
pub fn median_centre(scene: &FeatureGaussians<f32>) -> DVec3 {
    let median = |axis: usize| {
        let mut v: Vec<f64> = scene.means.iter().map(|m| m[axis] as f64).collect();
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            0.0
        } else {
            v[v.len() / 2]
        }
    };
    DVec3::new(median(0), median(1), median(2))
}

/// The cameras resized as the request says, each size checked ([`check_image_size`]) before the
/// camera is made; the error names the flags (or the cameras' origin) and the camera.
fn resize_all(cameras: Vec<Camera>, req: &CameraRequest, origin: &str) -> Result<Vec<Camera>> {
    let flags = req.size_flags();
    cameras
        .into_iter()
        .enumerate()
        .map(|(i, c)| {
            let k = c.intrinsics;
            // The size in floating point first, so that an absurd factor cannot wrap or
            // saturate before it is checked; rounded as `Intrinsics::scaled` rounds.
            let (mut w, mut h) = (k.width as f64, k.height as f64);
            if let Some(s) = req.scale {
                (w, h) = ((w * s).round().max(1.0), (h * s).round().max(1.0));
            }
            let aspect = h / w;
            let (w, h) = match (req.width, req.height) {
                (Some(a), Some(b)) => (a as f64, b as f64),
                (Some(a), None) => (a as f64, (a as f64 * aspect).round().max(1.0)),
                (None, Some(b)) => ((b as f64 / aspect).round().max(1.0), b as f64),
                (None, None) => (w, h),
            };
            let what = if flags.is_empty() {
                format!("camera {i} of {origin}")
            } else {
                format!("camera {i} of {origin} with {flags}")
            };
            // `as u64` saturates, so a size beyond u64 is still reported as too large.
            check_image_size(&what, w as u64, h as u64)?;
            let c = match req.scale {
                Some(s) => c.scaled(s),
                None => c,
            };
            Ok(match (req.width, req.height) {
                (None, None) => c,
                _ => c.resized(w as u32, h as u32),
            })
        })
        .collect()
}

/// A readable name of where known cameras come from.
fn origin_of(known: &KnownCameras) -> String {
    if known.origin.is_empty() {
        "the scene".to_string()
    } else {
        known.origin.clone()
    }
}

fn no_cameras(known: &KnownCameras, what: &str) -> Error {
    let origin = origin_of(known);
    Error::Message(format!(
        "{origin} has no cameras for `--cameras {what}`; give --dataset DIR with the scene's \
         cameras, or use `--cameras orbit`"
    ))
}

/// The cameras of a request. `scene` places orbits when no cameras are known.
///
/// The request is checked first ([`CameraRequest::check`]), and every camera's size before the
/// camera is returned ([`check_image_size`]), so nothing is made at a size beyond the limits.
pub fn select(
    req: &CameraRequest,
    known: &KnownCameras,
    scene: &FeatureGaussians<f32>,
) -> Result<Vec<Camera>> {
    req.check()?;
    let cams = match req.source {
        CameraSource::Dataset => {
            if known.cameras.is_empty() {
                return Err(no_cameras(known, "dataset"));
            }
            let idx = evenly_spaced(known.cameras.len(), req.frames.unwrap_or(usize::MAX));
            idx.iter().map(|&i| known.cameras[i]).collect()
        }
        CameraSource::Test => {
            let held: Vec<Camera> = known
                .cameras
                .iter()
                .zip(&known.held_out)
                .filter(|(_, &h)| h)
                .map(|(c, _)| *c)
                .collect();
            if held.is_empty() {
                return Err(no_cameras(known, "test"));
            }
            let idx = evenly_spaced(held.len(), req.frames.unwrap_or(usize::MAX));
            idx.iter().map(|&i| held[i]).collect()
        }
        CameraSource::Path => {
            if known.cameras.is_empty() {
                return Err(no_cameras(known, "path"));
            }
            let centre = look_at_point(&known.cameras).unwrap_or_else(|| median_centre(scene));
            let up = req
                .up
                .or_else(|| mean_up(&known.cameras))
                .unwrap_or(DVec3::NEG_Y);
            tour(
                &known.cameras,
                centre,
                up,
                req.frames.unwrap_or(DEFAULT_FRAMES),
            )?
        }
        CameraSource::Orbit => orbit_cameras(req, known, scene)?,
        CameraSource::Dense => {
            // From the first camera, or without cameras from the first of an orbit around the
            // scene.
            let (start, centre) = match known.cameras.first() {
                Some(c) => (
                    *c,
                    look_at_point(&known.cameras).unwrap_or_else(|| median_centre(scene)),
                ),
                None => {
                    let one = CameraRequest {
                        frames: Some(1),
                        ..req.clone()
                    };
                    (orbit_cameras(&one, known, scene)?[0], median_centre(scene))
                }
            };
            let up = req
                .up
                .or_else(|| mean_up(&known.cameras))
                .unwrap_or(DVec3::NEG_Y);
            arc_from(
                &start,
                centre,
                DENSE_STEP_DEGREES.to_radians(),
                req.frames.unwrap_or(DEFAULT_FRAMES),
                up,
            )?
        }
    };
    resize_all(cams, req, &origin_of(known))
}

fn orbit_cameras(
    req: &CameraRequest,
    known: &KnownCameras,
    scene: &FeatureGaussians<f32>,
) -> Result<Vec<Camera>> {
    let frames = req.frames.unwrap_or(DEFAULT_FRAMES);
    if let Some(start) = known.cameras.first() {
        let centre = look_at_point(&known.cameras).unwrap_or_else(|| median_centre(scene));
        let up = req
            .up
            .or_else(|| mean_up(&known.cameras))
            .unwrap_or(DVec3::NEG_Y);
        return Ok(orbit_from(start, centre, frames, up)?);
    }
    if scene.is_empty() {
        bail!(
            "{}: the scene has no Gaussians, so an orbit around it is undefined",
            origin_of(known)
        );
    }
    let centre = median_centre(scene);
    let mut dist: Vec<f64> = scene
        .means
        .iter()
        .map(|m| (DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64) - centre).length())
        .collect();
    dist.sort_by(f64::total_cmp);
    let radius = ORBIT_RADIUS_FACTOR * dist[dist.len() / 2].max(1e-6);
    let side = DEFAULT_SIDE;
    // Square unless both sides are given: one alone keeps the default's aspect ratio.
    let (w, h) = (
        req.width.or(req.height).unwrap_or(side),
        req.height.or(req.width).unwrap_or(side),
    );
    let focal = 0.5 * w as f64 / 30f64.to_radians().tan();
    let k = Intrinsics {
        fx: focal,
        fy: focal,
        cx: 0.5 * w as f64,
        cy: 0.5 * h as f64,
        width: w,
        height: h,
    };
    let up = req.up.unwrap_or(DVec3::NEG_Y);
    Ok(orbit(k, centre, radius, 20f64.to_radians(), frames, up)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gaussian::camera_path::look_at;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 16.0,
            cy: 12.0,
            width: 32,
            height: 24,
        }
    }

    fn ring(n: usize) -> Vec<Camera> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.4;
                let eye = DVec3::new(3.0 * a.cos(), 1.0, 3.0 * a.sin()) + DVec3::new(1.0, 2.0, 3.0);
                look_at(k(), eye, DVec3::new(1.0, 2.0, 3.0), DVec3::Y).unwrap()
            })
            .collect()
    }

    #[test]
    fn evenly_spaced_keeps_ends() {
        assert_eq!(evenly_spaced(10, 3), vec![0, 5, 9]);
        assert_eq!(evenly_spaced(3, 10), vec![0, 1, 2]);
        assert_eq!(evenly_spaced(7, 1), vec![0]);
    }

    #[test]
    fn sources_and_sizes() {
        let known = KnownCameras {
            cameras: ring(17),
            held_out: (0..17).map(|i| i % 8 == 0).collect(),
            names: Vec::new(),
            origin: "ring".into(),
        };
        let scene = FeatureGaussians::<f32>::default();
        let mut req = CameraRequest::new(CameraSource::Test);
        assert_eq!(select(&req, &known, &scene).unwrap().len(), 3);
        req.source = CameraSource::Path;
        req.frames = Some(9);
        req.width = Some(64);
        let path = select(&req, &known, &scene).unwrap();
        assert_eq!(path.len(), 9);
        assert_eq!(
            (path[0].intrinsics.width, path[0].intrinsics.height),
            (64, 48)
        );
        req.source = CameraSource::Orbit;
        let orbit = select(&req, &known, &scene).unwrap();
        assert_eq!(orbit.len(), 9);
        assert!((orbit[0].center() - known.cameras[0].center()).length() < 1e-9);
        let empty = KnownCameras {
            origin: "scene.ply".into(),
            ..KnownCameras::default()
        };
        req.source = CameraSource::Dataset;
        let e = select(&req, &empty, &scene).unwrap_err().to_string();
        assert!(e.contains("scene.ply") && e.contains("no cameras"), "{e}");
    }

    #[test]
    fn the_path_is_smooth_whatever_the_cameras_order() {
        // The ring's cameras in a scrambled order (as NeRF-synthetic captures list theirs): the
        // path still turns evenly round what they look at, never jumping across the ring.
        let ring = ring(16);
        let cameras: Vec<Camera> = (0..16).map(|i| ring[(i * 7) % 16]).collect();
        let known = KnownCameras {
            held_out: vec![false; 16],
            cameras,
            names: Vec::new(),
            origin: "ring".into(),
        };
        let mut req = CameraRequest::new(CameraSource::Path);
        req.frames = Some(24);
        let path = select(&req, &known, &FeatureGaussians::<f32>::default()).unwrap();
        let target = DVec3::new(1.0, 2.0, 3.0);
        let radius = (known.cameras[0].center() - target).length();
        let arc = std::f64::consts::TAU / 24.0 * radius;
        for w in path.windows(2) {
            let moved = (w[1].center() - w[0].center()).length();
            assert!(moved < 1.01 * arc, "{moved} against {arc}");
        }
        for c in &path {
            let p = c.camera_from_world.transform_point3(target);
            assert!(p.z > 0.0 && p.x.abs() < 1e-6 * p.z && p.y.abs() < 1e-6 * p.z);
        }
    }
}
