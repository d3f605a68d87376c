//! The scene bundle: what feature training produces and zero-shot stylization consumes.
//!
//! A bundle is frozen geometry whose Gaussians carry learned features, together with the lifter
//! trained on them and the encoder and decoder they were trained against. On disk it is a
//! directory:
//!
//! ```text
//! scene.ply          the official 3DGS layout, then f_feat_0 .. f_feat_{F-1}
//! nets.safetensors   encoder, decoder and lifter under their canonical names (nets::NetWeights)
//! bundle.json        BundleInfo: variant, widths, background, scene statistics, cameras
//! ```
//!
//! [`BundleInfo::load`] checks every camera of `bundle.json` ([`CameraRecord::check`]) before
//! anything is allocated or rendered from it: width and height between 1 and
//! [`MAX_IMAGE_SIDE`], focal lengths finite and positive, principal point finite, every entry of
//! `camera_from_world` finite, its last row `0 0 0 1` and its rotation part orthonormal with
//! determinant +1 (a rigid transform, as the dataset loaders of `gaussian::dataset` require).
//! A bad camera is reported as a [`RuntimeError::Bundle`] naming `bundle.json`, the camera's
//! index and name, and the problem. [`SceneBundle::load`] also refuses cameras smaller than the
//! networks can decode ([`SceneBundle::min_view_side`]) and `bundle.json` values that do not fit
//! the scene or the networks, naming the key.
//!
//! How a bundle renders a stylized view is in [`crate::frame`].

use std::path::{Path, PathBuf};

use gaussian::camera::check_rigid;
use gaussian::ply::{load_ply, save_ply};
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DMat4;
use nets::{Decoder, Encoder, Lifter, NetWeights, PoolRounding, Resolution};
use serde::{Deserialize, Serialize};
use style::FeatureNorm;

use crate::error::RuntimeError;
use base::Fnv1a;

/// The scene inside a bundle directory: the official 3DGS PLY layout plus the `f_feat_*`
/// feature properties.
pub const SCENE_FILE: &str = "scene.ply";
/// The networks inside a bundle directory: encoder, decoder and lifter weights (safetensors).
pub const NETS_FILE: &str = "nets.safetensors";
/// The description ([`BundleInfo`]) inside a bundle directory, as JSON.
pub const INFO_FILE: &str = "bundle.json";

/// The value of [`BundleInfo::format`].
pub const BUNDLE_FORMAT: &str = "dsgs-bundle-1";

/// The largest image width or height a bundle camera may have (the project's one image-size
/// limit, defined with the cameras).
pub use gaussian::camera::MAX_IMAGE_SIDE;

/// Which network variant the features were trained for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    /// Encoder pooling and decoder upsampling as in AdaIN; features rasterized at the encoder's
    /// output resolution.
    #[default]
    Standard,
    /// No pooling and no upsampling; features rasterized at image resolution.
    Fullres,
}

impl Variant {
    /// The networks' resolution setting.
    pub fn resolution(self) -> Resolution {
        match self {
            Variant::Standard => Resolution::Standard,
            Variant::Fullres => Resolution::Fullres,
        }
    }

    /// `"standard"` or `"fullres"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Variant::Standard => "standard",
            Variant::Fullres => "fullres",
        }
    }
}

impl std::str::FromStr for Variant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "standard" => Ok(Variant::Standard),
            "fullres" => Ok(Variant::Fullres),
            other => Err(format!(
                "unknown variant `{other}` (expected `standard` or `fullres`)"
            )),
        }
    }
}

/// Which decoder the features were trained against in stage 3 (the paper's decoder ablation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DecoderMode {
    /// The decoder pre-trained in 2D (for fullres, fine-tuned), frozen in stage 3: the paper's
    /// design.
    #[default]
    Pretrained,
    /// The same CNN initialised at random and trained inside stage 3 only, together with the
    /// features and the lifter.
    Scratch,
    /// A per-pixel MLP from features to colour
    /// (`train::decoder_training::init_mlp_decoder`) trained inside stage 3
    /// only. It decodes each feature pixel to one image pixel, so it needs the fullres variant.
    Mlp,
}

impl DecoderMode {
    /// `"pretrained"`, `"scratch"` or `"mlp"`.
    pub fn as_str(self) -> &'static str {
        match self {
            DecoderMode::Pretrained => "pretrained",
            DecoderMode::Scratch => "scratch",
            DecoderMode::Mlp => "mlp",
        }
    }

    /// Whether stage 3 trains the decoder.
    pub fn trains_decoder(self) -> bool {
        self != DecoderMode::Pretrained
    }
}

impl std::str::FromStr for DecoderMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "pretrained" => Ok(DecoderMode::Pretrained),
            "scratch" => Ok(DecoderMode::Scratch),
            "mlp" => Ok(DecoderMode::Mlp),
            other => Err(format!(
                "unknown decoder mode `{other}` (expected `pretrained`, `scratch` or `mlp`)"
            )),
        }
    }
}

/// A camera as stored in `bundle.json`: pinhole intrinsics and the row-major 4x4
/// `camera_from_world` (OpenCV axes, see `gaussian::camera`).
///
/// JSON has no NaN or infinity (`serde_json` writes them as `null`); a `null` focal length,
/// principal point or matrix entry is read back as NaN, so that [`CameraRecord::check`] names
/// the field instead of the load failing on a bare type error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraRecord {
    /// The view's name (the dataset image name).
    pub name: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, in pixels.
    #[serde(deserialize_with = "null_as_nan::number")]
    pub fx: f64,
    /// Focal length along y, in pixels.
    #[serde(deserialize_with = "null_as_nan::number")]
    pub fy: f64,
    /// Principal point x, in pixels from the left image edge.
    #[serde(deserialize_with = "null_as_nan::number")]
    pub cx: f64,
    /// Principal point y, in pixels from the top image edge.
    #[serde(deserialize_with = "null_as_nan::number")]
    pub cy: f64,
    /// The world-to-camera rigid transform, row-major (`camera_from_world[row][col]`), to
    /// OpenCV camera axes (x right, y down, z forward).
    #[serde(deserialize_with = "null_as_nan::matrix")]
    pub camera_from_world: [[f64; 4]; 4],
    /// Whether the view was held out of training.
    pub held_out: bool,
}

impl CameraRecord {
    /// Records `camera` under `name`.
    pub fn new(name: impl Into<String>, camera: &Camera, held_out: bool) -> CameraRecord {
        let k = &camera.intrinsics;
        let m = camera.camera_from_world.transpose().to_cols_array_2d();
        CameraRecord {
            name: name.into(),
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            camera_from_world: m,
            held_out,
        }
    }

    /// Checks that the record describes a camera that can be rendered from: its intrinsics pass
    /// [`Intrinsics::check`] (sizes up to [`MAX_IMAGE_SIDE`], finite positive focal lengths,
    /// finite principal point) and `camera_from_world` passes
    /// [`gaussian::camera::check_rigid`] (finite, last row `0 0 0 1`, orthonormal rotation with
    /// determinant +1), the same checks as the dataset loaders'. The error says which field is
    /// wrong and why.
    pub fn check(&self) -> Result<(), String> {
        self.intrinsics().check()?;
        check_rigid(&self.matrix()).map_err(|p| format!("camera_from_world: {p}"))
    }

    /// The camera (not checked: see [`CameraRecord::check`], which [`BundleInfo::load`] runs).
    pub fn camera(&self) -> Camera {
        Camera::new(self.intrinsics(), self.matrix())
    }

    fn intrinsics(&self) -> Intrinsics {
        Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width: self.width,
            height: self.height,
        }
    }

    /// `camera_from_world` as a matrix (the record stores its rows).
    fn matrix(&self) -> DMat4 {
        DMat4::from_cols_array_2d(&self.camera_from_world).transpose()
    }
}

/// The description of a bundle (`bundle.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BundleInfo {
    /// Always [`BUNDLE_FORMAT`].
    pub format: String,
    /// The network variant the features were trained for.
    pub variant: Variant,
    /// Per-Gaussian feature width `F` (the lifter's input width).
    pub feature_dim: usize,
    /// The encoder's output width at each level (the last is the lifter's output width).
    pub encoder_widths: Vec<usize>,
    /// [`weights_fingerprint`] of the encoder the features were aligned to.
    pub encoder_fingerprint: String,
    /// The feature-map background value (one per feature channel).
    pub feature_background: Vec<f32>,
    /// The RGB background the geometry was trained on.
    pub background: [f32; 3],
    /// Mean over the training views of the deepest encoder features' per-channel mean.
    pub scene_mean: Vec<f32>,
    /// Same for the per-channel standard deviation.
    pub scene_std: Vec<f32>,
    /// The cameras of the dataset the bundle was trained on, at the training resolution.
    pub cameras: Vec<CameraRecord>,
    /// Where the bundle came from (dataset, geometry, style folder); informational.
    #[serde(default)]
    pub provenance: Vec<(String, String)>,
    /// Which decoder stage 3 trained against (absent in older bundles: pre-trained).
    #[serde(default)]
    pub decoder_mode: DecoderMode,
    /// Where the features are normalised (absent in older bundles: before rasterization, the
    /// paper's design); see step 3 of [`crate::frame`].
    #[serde(default)]
    pub normalize: FeatureNorm,
    /// Side of the block of rendered pixels averaged into each feature pixel (absent in older
    /// bundles: 1, one sample per feature pixel); see [`raster::supersample`].
    #[serde(default = "one")]
    pub supersample: u32,
}

fn one() -> u32 {
    1
}

/// The largest supersampling factor of a bundle's feature render ([`BundleInfo::supersample`]).
pub const MAX_SUPERSAMPLE: u32 = 16;

impl BundleInfo {
    /// The description of a bundle of `feature_dim`-wide features aligned to `encoder` at
    /// `variant`: the format, the encoder's widths and fingerprint and a zero feature background
    /// follow from them; `scene_stats` are the scene's mean and std of the deepest features;
    /// no provenance.
    pub fn new(
        encoder: &Encoder<f32>,
        variant: Variant,
        feature_dim: usize,
        background: [f32; 3],
        scene_stats: (Vec<f32>, Vec<f32>),
        cameras: Vec<CameraRecord>,
    ) -> BundleInfo {
        BundleInfo {
            format: BUNDLE_FORMAT.to_string(),
            variant,
            feature_dim,
            encoder_widths: encoder.widths(),
            encoder_fingerprint: weights_fingerprint(encoder),
            feature_background: vec![0.0; feature_dim],
            background,
            scene_mean: scene_stats.0,
            scene_std: scene_stats.1,
            cameras,
            provenance: Vec::new(),
            decoder_mode: DecoderMode::Pretrained,
            normalize: FeatureNorm::BeforeRaster,
            supersample: 1,
        }
    }

    /// Reads and checks the description (`bundle.json`) of the bundle directory `dir`, without
    /// its scene or networks (enough for its cameras).
    ///
    /// Checked: the JSON, the format tag, and every camera ([`CameraRecord::check`]). A bad
    /// camera gives a [`RuntimeError::Bundle`] on `bundle.json` whose message names the
    /// camera by index and name and says what is wrong, e.g. `camera 3 (r_12): fx is 0; the
    /// focal length must be finite and positive`.
    ///
    /// A missing folder or description is said once, plainly: `X: bundle folder not found`,
    /// `X: no bundle.json (...)`.
    pub fn load(dir: &Path) -> Result<BundleInfo, RuntimeError> {
        let info_path = dir.join(INFO_FILE);
        let bytes = std::fs::read(&info_path).map_err(|e| {
            if e.kind() != std::io::ErrorKind::NotFound {
                io_err(&info_path, "cannot be read", &e)
            } else if dir.is_dir() {
                bundle_err(dir, format!("no {INFO_FILE} ({})", holds()))
            } else {
                not_a_folder(dir)
            }
        })?;
        let info: BundleInfo = serde_json::from_slice(&bytes)
            .map_err(|e| bundle_err(&info_path, format!("not a bundle description: {e}")))?;
        if info.format != BUNDLE_FORMAT {
            return Err(bundle_err(
                &info_path,
                format!("format `{}`, expected `{BUNDLE_FORMAT}`", info.format),
            ));
        }
        if !(1..=MAX_SUPERSAMPLE).contains(&info.supersample) {
            return Err(bundle_err(
                &info_path,
                format!(
                    "supersample is {}; it must be 1 to {MAX_SUPERSAMPLE}",
                    info.supersample
                ),
            ));
        }
        for (i, camera) in info.cameras.iter().enumerate() {
            camera.check().map_err(|problem| {
                bundle_err(
                    &info_path,
                    format!("camera {i} ({}): {problem}", camera.name),
                )
            })?;
        }
        Ok(info)
    }

    /// The cameras recorded in the description (checked by [`BundleInfo::load`] when read from
    /// disk).
    pub fn cameras(&self) -> Vec<Camera> {
        self.cameras.iter().map(CameraRecord::camera).collect()
    }
}

/// A loaded bundle.
#[derive(Clone, Debug)]
pub struct SceneBundle {
    /// Geometry plus features (`feature_dim = info.feature_dim`).
    pub scene: FeatureGaussians<f32>,
    /// The frozen encoder the features were aligned to (fingerprint
    /// [`BundleInfo::encoder_fingerprint`]).
    pub encoder: Encoder<f32>,
    /// The decoder that turns style-transformed lifted features into images.
    pub decoder: Decoder<f32>,
    /// The lifter `l = relu(W r + b)` from `F` feature channels to the encoder's deepest width.
    pub lifter: Lifter<f32>,
    /// The bundle's description (`bundle.json`).
    pub info: BundleInfo,
}

/// FNV-1a (64-bit) over the encoder's layer names, shapes and weight bits: a cheap identity for
/// "the same encoder weights", recorded in bundles and compared on load.
pub fn weights_fingerprint(encoder: &Encoder<f32>) -> String {
    let mut h = Fnv1a::new();
    for l in encoder.layers() {
        h.eat(l.name.as_bytes());
        for &d in l.weight.shape() {
            h.eat(&(d as u64).to_le_bytes());
        }
        for &v in l.weight.iter().chain(l.bias.iter()) {
            h.eat_f32(v);
        }
    }
    h.hex()
}

/// Reading `null` as NaN: `serde_json` writes NaN and the infinities as `null`, and a camera
/// whose numbers are not finite should be refused by [`CameraRecord::check`], with the field
/// named, rather than by the JSON parser.
mod null_as_nan {
    use serde::{Deserialize, Deserializer};

    /// A number, or NaN for `null`.
    pub(super) fn number<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }

    /// A 4x4 matrix of numbers, each `null` read as NaN.
    pub(super) fn matrix<'de, D: Deserializer<'de>>(d: D) -> Result<[[f64; 4]; 4], D::Error> {
        let m = <[[Option<f64>; 4]; 4]>::deserialize(d)?;
        Ok(m.map(|row| row.map(|v| v.unwrap_or(f64::NAN))))
    }
}

fn bundle_err(path: &Path, message: impl Into<String>) -> RuntimeError {
    RuntimeError::Bundle {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// What a bundle folder holds, for messages.
fn holds() -> String {
    format!("a scene bundle is a folder holding {SCENE_FILE}, {NETS_FILE} and {INFO_FILE}")
}

/// The error of a file or folder that could not be read, created or written: `{path}: {what}:
/// {io}`. The I/O error's text is part of the message and not returned as its source, so that
/// a printed error chain shows it once.
fn io_err(path: &Path, what: &str, e: &std::io::Error) -> RuntimeError {
    bundle_err(path, format!("{what}: {e}"))
}

/// The error of a bundle path that is missing or not a folder.
fn not_a_folder(dir: &Path) -> RuntimeError {
    if dir.exists() {
        bundle_err(dir, format!("not a folder ({})", holds()))
    } else {
        bundle_err(dir, "bundle folder not found")
    }
}

impl SceneBundle {
    /// FNV-1a (64-bit) over everything a stylized frame depends on besides the camera and the
    /// style: the variant, the geometry, colours and features of every Gaussian, the lifter and
    /// decoder weights, the scene statistics and the backgrounds. Two bundles with the same
    /// fingerprint decode the same frames; shards of one run compare it
    /// (`dsgs assemble`).
    pub fn fingerprint(&self) -> String {
        let mut h = Fnv1a::new();
        h.eat_str(self.info.variant.as_str());
        let s = &self.scene;
        h.eat_u64(s.len() as u64);
        h.eat_u64(s.sh_degree as u64);
        h.eat_u64(s.feature_dim as u64);
        let geometry = s.means.iter().chain(&s.log_scales).flatten();
        let rest = s.quats.iter().flatten().chain(&s.opacity_logits);
        let colour = s.sh.iter().flatten().chain(&s.features);
        geometry
            .chain(rest)
            .chain(colour)
            .for_each(|&v| h.eat_f32(v));
        let layers = std::iter::once(self.lifter.layer()).chain(self.decoder.layers());
        for l in layers {
            h.eat_str(&l.name);
            for &d in l.weight.shape() {
                h.eat_u64(d as u64);
            }
            l.weight
                .iter()
                .chain(l.bias.iter())
                .for_each(|&v| h.eat_f32(v));
        }
        let info = &self.info;
        let stats = info.scene_mean.iter().chain(&info.scene_std);
        stats
            .chain(&info.feature_background)
            .chain(&info.background)
            .for_each(|&v| h.eat_f32(v));
        h.eat_str(&info.encoder_fingerprint);
        // Only the ablation is hashed, so bundles of the paper's design keep their fingerprints.
        if info.normalize != FeatureNorm::BeforeRaster {
            h.eat_str(info.normalize.as_str());
        }
        // Likewise only a supersampled render, so older bundles keep theirs.
        if info.supersample != 1 {
            h.eat_str("supersample");
            h.eat_u64(info.supersample as u64);
        }
        h.hex()
    }

    /// Checks that the parts fit together: feature width = lifter input, lifter output =
    /// decoder input = encoder's deepest width, statistics and background sizes.
    pub fn validate(&self) -> Result<(), RuntimeError> {
        let c = self.lifter.out_channels();
        let f = self.info.feature_dim;
        let deepest = *self.encoder.widths().last().unwrap_or(&0);
        let mut problems = Vec::new();
        if self.scene.feature_dim != f {
            problems.push(format!(
                "feature_dim is {f}, but the scene has {} feature channels",
                self.scene.feature_dim
            ));
        }
        if self.lifter.in_channels() != f {
            problems.push(format!(
                "feature_dim is {f}, but the lifter takes {} channels",
                self.lifter.in_channels()
            ));
        }
        if self.decoder.in_channels() != c {
            problems.push(format!(
                "the decoder takes {} channels, the lifter makes {c}",
                self.decoder.in_channels()
            ));
        }
        if deepest != c {
            problems.push(format!(
                "the encoder's deepest width is {deepest}, the lifter makes {c}"
            ));
        }
        if self.info.scene_mean.len() != c || self.info.scene_std.len() != c {
            problems.push(format!(
                "scene_mean and scene_std have {} and {} values, expected {c} (the lifter's \
                 width)",
                self.info.scene_mean.len(),
                self.info.scene_std.len()
            ));
        }
        if self.info.encoder_widths != self.encoder.widths() {
            problems.push(format!(
                "encoder_widths is {:?}, but the encoder's widths are {:?}",
                self.info.encoder_widths,
                self.encoder.widths()
            ));
        }
        if self.decoder.is_pointwise() && self.info.variant != Variant::Fullres {
            problems.push(format!(
                "variant is {}, but the decoder is a per-pixel MLP, which needs fullres",
                self.info.variant.as_str()
            ));
        }
        if self.info.feature_background.len() != f {
            problems.push(format!(
                "feature_background has {} values, expected {f} (feature_dim)",
                self.info.feature_background.len()
            ));
        }
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        for (key, values) in [
            ("scene_mean", &self.info.scene_mean),
            ("scene_std", &self.info.scene_std),
            ("feature_background", &self.info.feature_background),
        ] {
            if !finite(values) {
                problems.push(format!("{key} holds a value that is not finite"));
            }
        }
        if !self.info.background.iter().all(|x| x.is_finite()) {
            problems.push("background holds a value that is not finite".to_string());
        }
        let min = self.min_view_side();
        for (i, cam) in self.info.cameras.iter().enumerate() {
            if cam.width.min(cam.height) < min {
                problems.push(format!(
                    "camera {i} ({}) is {}x{}: the networks decode views of at least {min} \
                     pixels a side",
                    cam.name, cam.width, cam.height
                ));
                break;
            }
        }
        if problems.is_empty() {
            Ok(())
        } else {
            Err(RuntimeError::Config(problems.join("; ")))
        }
    }

    /// Writes the bundle into `dir` (created if needed); each file is written atomically.
    pub fn save(&self, dir: &Path) -> Result<(), RuntimeError> {
        self.validate()?;
        std::fs::create_dir_all(dir).map_err(|e| io_err(dir, "cannot be created", &e))?;
        save_ply(dir.join(SCENE_FILE), &self.scene)?;
        let nets = NetWeights {
            encoder: Some(self.encoder.clone().with_resolution(Resolution::Standard)),
            decoder: Some(self.decoder.clone().with_resolution(Resolution::Standard)),
            lifter: Some(self.lifter.clone()),
        };
        let nets_path = dir.join(NETS_FILE);
        nets.save(&nets_path)
            .map_err(|e| bundle_err(&nets_path, e.to_string()))?;
        let info_path = dir.join(INFO_FILE);
        let json = serde_json::to_vec_pretty(&self.info)
            .map_err(|e| bundle_err(&info_path, e.to_string()))?;
        base::write_atomic(&info_path, &json)
            .map_err(|e| io_err(&info_path, "cannot be written", &e))
    }

    /// Reads a bundle directory written by [`SceneBundle::save`], with the networks set to the
    /// bundle's variant. A missing folder or `bundle.json` is reported as by
    /// [`BundleInfo::load`].
    pub fn load(dir: &Path) -> Result<SceneBundle, RuntimeError> {
        if !dir.is_dir() {
            return Err(not_a_folder(dir));
        }
        let info = BundleInfo::load(dir)?;
        let scene = load_ply(dir.join(SCENE_FILE))?;
        let nets_path = dir.join(NETS_FILE);
        let nets =
            NetWeights::load(&nets_path).map_err(|e| bundle_err(&nets_path, e.to_string()))?;
        let missing = |what: &str| bundle_err(&nets_path, format!("the {what} is missing"));
        let resolution = info.variant.resolution();
        let encoder = nets
            .encoder
            .ok_or_else(|| missing("encoder"))?
            .with_resolution(resolution);
        let decoder = nets
            .decoder
            .ok_or_else(|| missing("decoder"))?
            .with_resolution(resolution);
        let lifter = nets.lifter.ok_or_else(|| missing("lifter"))?;
        let fingerprint = weights_fingerprint(&encoder);
        if fingerprint != info.encoder_fingerprint {
            return Err(bundle_err(
                &nets_path,
                format!(
                    "encoder fingerprint {fingerprint} does not match bundle.json's {}",
                    info.encoder_fingerprint
                ),
            ));
        }
        let bundle = SceneBundle {
            scene,
            encoder,
            decoder,
            lifter,
            info,
        };
        bundle.validate().map_err(|e| match e {
            RuntimeError::Config(m) => bundle_err(&dir.join(INFO_FILE), m),
            other => other,
        })?;
        Ok(bundle)
    }

    /// Replaces the decoder (for example with a fine-tuned fullres one) after checking that it
    /// takes the lifter's width; `variant` sets the resolution of both networks.
    pub fn with_decoder(
        mut self,
        decoder: Decoder<f32>,
        variant: Variant,
    ) -> Result<Self, RuntimeError> {
        if decoder.in_channels() != self.lifter.out_channels() {
            return Err(RuntimeError::Config(format!(
                "the decoder takes {} channels, but this bundle's features lift to {} \
                 (it was made with other weights)",
                decoder.in_channels(),
                self.lifter.out_channels()
            )));
        }
        if decoder.is_pointwise() && variant != Variant::Fullres {
            return Err(RuntimeError::Config(format!(
                "the decoder is a per-pixel MLP, which needs the fullres variant, not {}",
                variant.as_str()
            )));
        }
        self.decoder = decoder.with_resolution(variant.resolution());
        self.encoder = self.encoder.with_resolution(variant.resolution());
        self.info.variant = variant;
        Ok(self)
    }

    /// The cameras stored in the bundle.
    pub fn cameras(&self) -> Vec<Camera> {
        self.info.cameras()
    }

    /// The smallest side, in pixels, of a view these networks can stylize: its feature map
    /// must have at least 2x2 positions for the decoder's reflection-padded 3x3 convolutions
    /// (1x1 for a per-pixel decoder), after the standard variant's pooling.
    pub fn min_view_side(&self) -> u32 {
        let need = if self.decoder.is_pointwise() { 1 } else { 2 };
        (1..=MAX_IMAGE_SIDE)
            .find(|&s| {
                let (w, h) = self.feature_size(s, s);
                w.min(h) >= need
            })
            .unwrap_or(MAX_IMAGE_SIDE)
    }

    /// Checks that a `width x height` view can be stylized ([`SceneBundle::min_view_side`]);
    /// the error says the size and the minimum.
    pub fn check_view_size(&self, width: u32, height: u32) -> Result<(), String> {
        let min = self.min_view_side();
        if width.min(height) < min {
            return Err(format!(
                "a view of {width}x{height} pixels is too small: this bundle's networks decode \
                 views of at least {min} pixels a side"
            ));
        }
        Ok(())
    }

    /// The feature-map size `(width, height)` for an image of `width x height`.
    pub fn feature_size(&self, width: u32, height: u32) -> (u32, u32) {
        feature_size(&self.encoder, self.info.variant, width, height)
    }

    /// The camera of the feature map that a frame of `camera` is decoded from.
    ///
    /// Fullres, and the standard variant of an encoder that pools with ceil rounding: `camera`
    /// resized to [`SceneBundle::feature_size`], whose decoded image covers the frame (it may
    /// overshoot and is cropped). The standard variant of an encoder that pools with floor
    /// rounding (the 16x-compressed relu4_1 pair) would decode an image smaller than the frame
    /// for a side that is not a multiple of the pooling factor `f = 2^(depth - 1)`; its feature
    /// map is instead the frame's image plane scaled by exactly `1 / f` (feature pixel `i` covers
    /// image pixels `f i .. f (i + 1)`, as the encoder's pooling grid does), `ceil(side / f)`
    /// pixels a side, so the decoded image covers the frame and is cropped like the others.
    pub fn feature_camera(&self, camera: &Camera) -> Camera {
        let k = camera.intrinsics;
        let (w, h) = match pooling_grid(&self.encoder, self.info.variant) {
            Some(f) => (k.width.div_ceil(f), k.height.div_ceil(f)),
            None => self.feature_size(k.width, k.height),
        };
        feature_map_camera(&self.encoder, self.info.variant, camera, (w, h))
    }
}

/// The pooling factor `f = 2^(depth - 1)` when the feature map of `encoder` at `variant` lies
/// on the encoder's pooling grid (the standard variant of an encoder that pools with floor
/// rounding), else `None`.
fn pooling_grid<T: base::Real>(encoder: &Encoder<T>, variant: Variant) -> Option<u32> {
    (variant == Variant::Standard && encoder.pool_rounding() == PoolRounding::Floor)
        .then(|| 1u32 << (encoder.depth().max(1) - 1))
}

/// The camera of a `size` feature map of the frame of `camera`, for `encoder` at `variant`:
/// on the encoder's pooling grid (the image plane scaled by exactly `1 / f`, feature pixel `i`
/// covering image pixels `f i .. f (i + 1)`) for the standard variant of an encoder that pools
/// with floor rounding, whatever `size` (the encoder's own map, as training aligns to, or one
/// pixel more where a side is not a multiple of `f`, as stylization decodes); otherwise
/// `camera` resized to `size`. Training and stylization render features through it, so a
/// Gaussian lands on the same feature pixel in both.
pub fn feature_map_camera<T: base::Real>(
    encoder: &Encoder<T>,
    variant: Variant,
    camera: &Camera,
    size: (u32, u32),
) -> Camera {
    let Some(f) = pooling_grid(encoder, variant) else {
        return camera.resized(size.0, size.1);
    };
    let k = camera.intrinsics;
    let s = 1.0 / f as f64;
    let intrinsics = Intrinsics {
        fx: k.fx * s,
        fy: k.fy * s,
        cx: k.cx * s,
        cy: k.cy * s,
        width: size.0,
        height: size.1,
    };
    Camera::new(intrinsics, camera.camera_from_world)
}

/// The feature-map size for an image of `width x height` under `encoder` and `variant`: the
/// image size for fullres, else the size after each of the encoder's `depth - 1` poolings.
pub fn feature_size(
    encoder: &Encoder<f32>,
    variant: Variant,
    width: u32,
    height: u32,
) -> (u32, u32) {
    match variant {
        Variant::Fullres => (width, height),
        Variant::Standard => {
            let r = encoder.pool_rounding();
            let (mut w, mut h) = (width as usize, height as usize);
            for _ in 1..encoder.depth() {
                w = r.pooled(w);
                h = r.pooled(h);
            }
            (w as u32, h as u32)
        }
    }
}

/// Path of a file inside a bundle directory.
pub fn bundle_file(dir: &Path, name: &str) -> PathBuf {
    dir.join(name)
}

#[cfg(test)]
mod tests {
    use super::*;
    use base::error::chain;

    fn scratch(name: &str) -> PathBuf {
        dsgs_testkit::scratch_dir("bundle-unit", name)
    }

    #[test]
    fn a_missing_folder_or_description_is_said_once() {
        let dir = scratch("missing");
        let gone = dir.join("gone");
        for e in [
            BundleInfo::load(&gone).unwrap_err(),
            SceneBundle::load(&gone).unwrap_err(),
        ] {
            let text = chain(&e);
            assert!(text.contains("bundle folder not found"), "{text}");
            assert_eq!(text.matches("gone").count(), 1, "{text}");
            assert!(!text.contains("os error"), "{text}");
        }
        for e in [
            BundleInfo::load(&dir).unwrap_err(),
            SceneBundle::load(&dir).unwrap_err(),
        ] {
            let text = chain(&e);
            assert!(text.contains("no bundle.json"), "{text}");
            assert!(text.contains(&dir.display().to_string()), "{text}");
            assert!(!text.contains("os error"), "{text}");
        }
        let file = dir.join("bundle.ply");
        std::fs::write(&file, "ply").unwrap();
        let text = chain(&SceneBundle::load(&file).unwrap_err());
        assert!(text.contains("bundle.ply: not a folder"), "{text}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn an_io_error_is_part_of_the_message_and_not_its_source() {
        let dir = scratch("io");
        // A folder where bundle.json should be: reading it fails with an I/O error.
        std::fs::create_dir_all(dir.join(INFO_FILE)).unwrap();
        let e = BundleInfo::load(&dir).unwrap_err();
        let text = chain(&e);
        assert!(text.contains("bundle.json: cannot be read: "), "{text}");
        assert!(std::error::Error::source(&e).is_none(), "{text}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
