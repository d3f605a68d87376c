//! COLMAP sparse models (`cameras`, `images`, `points3D`), binary and text.
//!
//! Conventions are COLMAP's: an image's pose `(qw, qx, qy, qz, tx, ty, tz)` is the rigid
//! transform `camera_from_world` in OpenCV camera axes (x right, y down, z forward), the
//! quaternion is Hamilton `(w, x, y, z)`, and pixel `(i, j)` has its centre at
//! `(i + 0.5, j + 0.5)`, the same as [`crate::Camera`]. 2D observations are in the pixels of
//! the original (distorted) images.
//!
//! Binary layouts (little-endian; counts `u64`):
//! * `cameras.bin`: count, then per camera `camera_id: u32, model_id: i32, width: u64,
//!   height: u64, params: f64 x (number of the model's parameters)`.
//! * `images.bin`: count, then per image `image_id: u32, qvec: 4 f64, tvec: 3 f64,
//!   camera_id: u32, name: NUL-terminated bytes, num_points2D: u64, then (x: f64, y: f64,
//!   point3D_id: u64) each`, where `u64::MAX` (written as -1 in text) means "no 3D point".
//! * `points3D.bin`: count, then per point `point3D_id: u64, xyz: 3 f64, rgb: 3 u8,
//!   error: f64, track_length: u64, then (image_id: u32, point2D_idx: u32) each`.
//!
//! Text files hold the same fields, one record per line (`images.txt`: two lines per image, the
//! second listing the 2D points and possibly empty), with `#` comment lines.
//!
//! Every count is checked against the bytes present before anything is allocated from it.

use std::fs;
use std::path::{Path, PathBuf};

use super::DatasetError;

/// COLMAP camera models, with their numeric ids and parameter counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraModel {
    /// `SIMPLE_PINHOLE` (id 0): `f, cx, cy`.
    SimplePinhole,
    /// `PINHOLE` (id 1): `fx, fy, cx, cy`.
    Pinhole,
    /// `SIMPLE_RADIAL` (id 2): `f, cx, cy, k`.
    SimpleRadial,
    /// `RADIAL` (id 3): `f, cx, cy, k1, k2`.
    Radial,
    /// `OPENCV` (id 4): `fx, fy, cx, cy, k1, k2, p1, p2`.
    OpenCv,
    /// `OPENCV_FISHEYE` (id 5): `fx, fy, cx, cy, k1, k2, k3, k4`.
    OpenCvFisheye,
    /// `FULL_OPENCV` (id 6): `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`.
    FullOpenCv,
    /// `FOV` (id 7): `fx, fy, cx, cy, omega`.
    Fov,
    /// `SIMPLE_RADIAL_FISHEYE` (id 8): `f, cx, cy, k`.
    SimpleRadialFisheye,
    /// `RADIAL_FISHEYE` (id 9): `f, cx, cy, k1, k2`.
    RadialFisheye,
    /// `THIN_PRISM_FISHEYE` (id 10): 12 parameters, `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1,
    /// sy1`.
    ThinPrismFisheye,
    /// `RAD_TAN_THIN_PRISM_FISHEYE` (id 11): 16 parameters.
    RadTanThinPrismFisheye,
}

const MODELS: [(CameraModel, i32, &str, usize); 12] = [
    (CameraModel::SimplePinhole, 0, "SIMPLE_PINHOLE", 3),
    (CameraModel::Pinhole, 1, "PINHOLE", 4),
    (CameraModel::SimpleRadial, 2, "SIMPLE_RADIAL", 4),
    (CameraModel::Radial, 3, "RADIAL", 5),
    (CameraModel::OpenCv, 4, "OPENCV", 8),
    (CameraModel::OpenCvFisheye, 5, "OPENCV_FISHEYE", 8),
    (CameraModel::FullOpenCv, 6, "FULL_OPENCV", 12),
    (CameraModel::Fov, 7, "FOV", 5),
    (
        CameraModel::SimpleRadialFisheye,
        8,
        "SIMPLE_RADIAL_FISHEYE",
        4,
    ),
    (CameraModel::RadialFisheye, 9, "RADIAL_FISHEYE", 5),
    (CameraModel::ThinPrismFisheye, 10, "THIN_PRISM_FISHEYE", 12),
    (
        CameraModel::RadTanThinPrismFisheye,
        11,
        "RAD_TAN_THIN_PRISM_FISHEYE",
        16,
    ),
];

impl CameraModel {
    /// The model with COLMAP's numeric id.
    pub fn from_id(id: i32) -> Option<CameraModel> {
        MODELS.iter().find(|m| m.1 == id).map(|m| m.0)
    }

    /// The model with COLMAP's name (e.g. `SIMPLE_RADIAL`).
    pub fn from_name(name: &str) -> Option<CameraModel> {
        MODELS.iter().find(|m| m.2 == name).map(|m| m.0)
    }

    fn entry(self) -> &'static (CameraModel, i32, &'static str, usize) {
        // Every variant is listed in MODELS.
        MODELS.iter().find(|m| m.0 == self).unwrap_or(&MODELS[0])
    }

    /// COLMAP's name of the model.
    pub fn name(self) -> &'static str {
        self.entry().2
    }

    /// Number of parameters COLMAP stores for the model.
    pub fn num_params(self) -> usize {
        self.entry().3
    }
}

/// A camera of a COLMAP model.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// COLMAP camera id, referenced by [`ColmapImage::camera_id`].
    pub id: u32,
    /// The camera model, which fixes the meaning of `params`.
    pub model: CameraModel,
    /// Image width in pixels.
    pub width: u64,
    /// Image height in pixels.
    pub height: u64,
    /// The model's parameters in COLMAP's order (e.g. SIMPLE_RADIAL: `f, cx, cy, k`).
    pub params: Vec<f64>,
}

/// A registered image of a COLMAP model.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// COLMAP image id, referenced by [`ColmapPoint::track`].
    pub id: u32,
    /// Rotation `camera_from_world` as a quaternion `(w, x, y, z)`.
    pub qvec: [f64; 4],
    /// Translation of `camera_from_world`.
    pub tvec: [f64; 3],
    /// Id of the [`ColmapCamera`] that took the image.
    pub camera_id: u32,
    /// Image file name, relative to the `images` folder.
    pub name: String,
    /// 2D observations in original image pixels and the 3D point each belongs to, if any.
    pub points2d: Vec<([f64; 2], Option<u64>)>,
}

/// A 3D point of a COLMAP model.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    /// COLMAP 3D point id, referenced by [`ColmapImage::points2d`].
    pub id: u64,
    /// World-space position.
    pub xyz: [f64; 3],
    /// 8-bit RGB colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels.
    pub error: f64,
    /// `(image_id, point2D_idx)` observations.
    pub track: Vec<(u32, u32)>,
}

/// A COLMAP sparse model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    /// The cameras, in file order.
    pub cameras: Vec<ColmapCamera>,
    /// The registered images, in file order.
    pub images: Vec<ColmapImage>,
    /// The 3D points, in file order.
    pub points: Vec<ColmapPoint>,
}

/// The folder holding the sparse model of a scene: `sparse/0` if present, else `sparse`.
pub fn model_dir(scene_dir: &Path) -> Option<PathBuf> {
    [scene_dir.join("sparse").join("0"), scene_dir.join("sparse")]
        .into_iter()
        .find(|d| d.join("cameras.bin").is_file() || d.join("cameras.txt").is_file())
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, DatasetError> {
    fs::read(path).map_err(|error| DatasetError::Io {
        path: path.to_path_buf(),
        error,
    })
}

/// Reads `cameras`, `images` and `points3D` from `dir`, preferring `.bin` files over `.txt`.
/// `points3D` may be absent (an empty point list is returned).
pub fn read_model(dir: &Path) -> Result<ColmapModel, DatasetError> {
    let pick = |stem: &str| {
        let bin = dir.join(format!("{stem}.bin"));
        let txt = dir.join(format!("{stem}.txt"));
        if bin.is_file() {
            Some((bin, true))
        } else if txt.is_file() {
            Some((txt, false))
        } else {
            None
        }
    };
    let missing = |stem: &str| DatasetError::Malformed {
        path: dir.to_path_buf(),
        problem: format!("COLMAP model has neither {stem}.bin nor {stem}.txt"),
    };
    let (cam_path, bin) = pick("cameras").ok_or_else(|| missing("cameras"))?;
    let bytes = read_bytes(&cam_path)?;
    let cameras = if bin {
        parse_cameras_bin(&bytes, &cam_path)?
    } else {
        parse_cameras_txt(&bytes, &cam_path)?
    };
    let (img_path, bin) = pick("images").ok_or_else(|| missing("images"))?;
    let bytes = read_bytes(&img_path)?;
    let images = if bin {
        parse_images_bin(&bytes, &img_path)?
    } else {
        parse_images_txt(&bytes, &img_path)?
    };
    let points = match pick("points3D") {
        None => Vec::new(),
        Some((p, bin)) => {
            let bytes = read_bytes(&p)?;
            if bin {
                parse_points3d_bin(&bytes, &p)?
            } else {
                parse_points3d_txt(&bytes, &p)?
            }
        }
    };
    Ok(ColmapModel {
        cameras,
        images,
        points,
    })
}

/// A point's position, or why it is refused: a coordinate that is not finite.
fn finite_xyz(id: u64, xyz: [f64; 3]) -> Result<[f64; 3], String> {
    if xyz.iter().all(|v| v.is_finite()) {
        Ok(xyz)
    } else {
        Err(format!(
            "point {id}: position {xyz:?} is not finite (every coordinate must be a finite number)"
        ))
    }
}

/// Reads only the 3D points of the model in `dir` (binary or text), if there are any.
pub fn read_points(dir: &Path) -> Result<Option<Vec<ColmapPoint>>, DatasetError> {
    let bin = dir.join("points3D.bin");
    let txt = dir.join("points3D.txt");
    if bin.is_file() {
        Ok(Some(parse_points3d_bin(&read_bytes(&bin)?, &bin)?))
    } else if txt.is_file() {
        Ok(Some(parse_points3d_txt(&read_bytes(&txt)?, &txt)?))
    } else {
        Ok(None)
    }
}

// ---------------------------------------------------------------------------------------------
// binary

/// A little-endian cursor whose reads fail with a description instead of panicking.
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        if self.bytes.len() - self.pos < n {
            return Err(format!(
                "file ends early at byte {} ({n} bytes needed, {} left; truncated)",
                self.pos,
                self.bytes.len() - self.pos
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn arr<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }
    fn u64(&mut self) -> Result<u64, String> {
        self.arr().map(u64::from_le_bytes)
    }
    fn u32(&mut self) -> Result<u32, String> {
        self.arr().map(u32::from_le_bytes)
    }
    fn i32(&mut self) -> Result<i32, String> {
        self.arr().map(i32::from_le_bytes)
    }
    fn f64(&mut self) -> Result<f64, String> {
        self.arr().map(f64::from_le_bytes)
    }
    fn u8(&mut self) -> Result<u8, String> {
        self.arr::<1>().map(|a| a[0])
    }
    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    /// A record count, checked against the bytes left given the smallest record size.
    fn count(&mut self, what: &str, min_record: usize) -> Result<usize, String> {
        let n = self.u64()?;
        let fits = n
            .checked_mul(min_record as u64)
            .is_some_and(|b| b <= self.remaining() as u64);
        if !fits {
            return Err(format!(
                "{n} {what} declared at byte {}, but only {} bytes follow (truncated or corrupt count)",
                self.pos - 8,
                self.remaining()
            ));
        }
        Ok(n as usize)
    }
}

fn malformed(path: &Path, problem: String) -> DatasetError {
    DatasetError::Malformed {
        path: path.to_path_buf(),
        problem,
    }
}

/// Parses `cameras.bin` bytes. `path` only names the source in errors.
pub fn parse_cameras_bin(bytes: &[u8], path: &Path) -> Result<Vec<ColmapCamera>, DatasetError> {
    let mut c = Cursor { bytes, pos: 0 };
    let n = c
        .count("cameras", 24 + 3 * 8)
        .map_err(|p| malformed(path, p))?;
    let mut cameras = Vec::with_capacity(n);
    for i in 0..n {
        let cam = (|| {
            let id = c.u32()?;
            let model_id = c.i32()?;
            let model = CameraModel::from_id(model_id)
                .ok_or_else(|| format!("camera {id} has unknown model id {model_id}"))?;
            let width = c.u64()?;
            let height = c.u64()?;
            let params = (0..model.num_params())
                .map(|_| c.f64())
                .collect::<Result<Vec<_>, _>>()?;
            Ok::<_, String>(ColmapCamera {
                id,
                model,
                width,
                height,
                params,
            })
        })()
        .map_err(|p| malformed(path, format!("camera record {i}: {p}")))?;
        cameras.push(cam);
    }
    Ok(cameras)
}

/// Parses `images.bin` bytes. `path` only names the source in errors.
pub fn parse_images_bin(bytes: &[u8], path: &Path) -> Result<Vec<ColmapImage>, DatasetError> {
    let mut c = Cursor { bytes, pos: 0 };
    let n = c
        .count("images", 4 + 56 + 4 + 1 + 8)
        .map_err(|p| malformed(path, p))?;
    let mut images = Vec::with_capacity(n);
    for i in 0..n {
        let image = (|| {
            let id = c.u32()?;
            let mut qvec = [0.0; 4];
            for q in &mut qvec {
                *q = c.f64()?;
            }
            let mut tvec = [0.0; 3];
            for t in &mut tvec {
                *t = c.f64()?;
            }
            let camera_id = c.u32()?;
            let rest = &c.bytes[c.pos..];
            let len = rest
                .iter()
                .position(|&b| b == 0)
                .ok_or_else(|| format!("image {id}: name is not NUL-terminated (truncated)"))?;
            let name = String::from_utf8(rest[..len].to_vec())
                .map_err(|_| format!("image {id}: name is not valid UTF-8"))?;
            c.pos += len + 1;
            let np = c
                .count("2D points", 24)
                .map_err(|p| format!("image {id} `{name}`: {p}"))?;
            let mut points2d = Vec::with_capacity(np);
            for _ in 0..np {
                let x = c.f64()?;
                let y = c.f64()?;
                let pid = c.u64()?;
                points2d.push(([x, y], (pid != u64::MAX).then_some(pid)));
            }
            Ok::<_, String>(ColmapImage {
                id,
                qvec,
                tvec,
                camera_id,
                name,
                points2d,
            })
        })()
        .map_err(|p| malformed(path, format!("image record {i}: {p}")))?;
        images.push(image);
    }
    Ok(images)
}

/// Parses `points3D.bin` bytes. `path` only names the source in errors.
pub fn parse_points3d_bin(bytes: &[u8], path: &Path) -> Result<Vec<ColmapPoint>, DatasetError> {
    let mut c = Cursor { bytes, pos: 0 };
    let n = c
        .count("points", 8 + 24 + 3 + 8 + 8)
        .map_err(|p| malformed(path, p))?;
    let mut points = Vec::with_capacity(n);
    for i in 0..n {
        let point = (|| {
            let id = c.u64()?;
            let xyz = finite_xyz(id, [c.f64()?, c.f64()?, c.f64()?])?;
            let rgb = [c.u8()?, c.u8()?, c.u8()?];
            let error = c.f64()?;
            let nt = c
                .count("track entries", 8)
                .map_err(|p| format!("point {id}: {p}"))?;
            let mut track = Vec::with_capacity(nt);
            for _ in 0..nt {
                track.push((c.u32()?, c.u32()?));
            }
            Ok::<_, String>(ColmapPoint {
                id,
                xyz,
                rgb,
                error,
                track,
            })
        })()
        .map_err(|p| malformed(path, format!("point record {i}: {p}")))?;
        points.push(point);
    }
    Ok(points)
}

// ---------------------------------------------------------------------------------------------
// text

fn text_lines<'a>(bytes: &'a [u8], path: &Path) -> Result<Vec<(usize, &'a str)>, DatasetError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| malformed(path, format!("not valid UTF-8 text ({e})")))?;
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .collect())
}

fn field<T: std::str::FromStr>(tokens: &[&str], i: usize, what: &str) -> Result<T, String> {
    let t = tokens
        .get(i)
        .ok_or_else(|| format!("missing field {} ({what})", i + 1))?;
    t.parse()
        .map_err(|_| format!("field {} ({what}) `{t}` is not valid", i + 1))
}

/// Parses `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]` per line.
pub fn parse_cameras_txt(bytes: &[u8], path: &Path) -> Result<Vec<ColmapCamera>, DatasetError> {
    let mut cameras = Vec::new();
    for (line_no, line) in text_lines(bytes, path)? {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        let cam = (|| {
            let id: u32 = field(&tokens, 0, "CAMERA_ID")?;
            let name = tokens.get(1).copied().unwrap_or("");
            let model = CameraModel::from_name(name)
                .ok_or_else(|| format!("camera {id} has unknown model `{name}`"))?;
            let width = field(&tokens, 2, "WIDTH")?;
            let height = field(&tokens, 3, "HEIGHT")?;
            if tokens.len() != 4 + model.num_params() {
                return Err(format!(
                    "camera {id}: model {} takes {} parameters, the line has {}",
                    model.name(),
                    model.num_params(),
                    tokens.len().saturating_sub(4)
                ));
            }
            let params = (0..model.num_params())
                .map(|k| field(&tokens, 4 + k, "PARAMS"))
                .collect::<Result<Vec<f64>, _>>()?;
            Ok(ColmapCamera {
                id,
                model,
                width,
                height,
                params,
            })
        })()
        .map_err(|p| malformed(path, format!("line {line_no}: {p}")))?;
        cameras.push(cam);
    }
    Ok(cameras)
}

/// Parses `images.txt`: per image a line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and a
/// line of `X Y POINT3D_ID` triples (which may be empty).
pub fn parse_images_txt(bytes: &[u8], path: &Path) -> Result<Vec<ColmapImage>, DatasetError> {
    let lines = text_lines(bytes, path)?;
    let mut images = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let (line_no, line) = lines[i];
        i += 1;
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let points_line = lines.get(i).map_or("", |l| l.1);
        i += 1;
        let image = (|| {
            let t: Vec<&str> = line.split_whitespace().collect();
            if t.len() < 10 {
                return Err(format!(
                    "expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, found {} fields",
                    t.len()
                ));
            }
            let id: u32 = field(&t, 0, "IMAGE_ID")?;
            let mut qvec = [0.0; 4];
            for (k, q) in qvec.iter_mut().enumerate() {
                *q = field(&t, 1 + k, "QVEC")?;
            }
            let mut tvec = [0.0; 3];
            for (k, v) in tvec.iter_mut().enumerate() {
                *v = field(&t, 5 + k, "TVEC")?;
            }
            let camera_id = field(&t, 8, "CAMERA_ID")?;
            let name = t[9..].join(" ");
            let p: Vec<&str> = points_line.split_whitespace().collect();
            if !p.len().is_multiple_of(3) {
                return Err(format!(
                    "image {id}: the 2D point line has {} fields, not a multiple of 3",
                    p.len()
                ));
            }
            let mut points2d = Vec::with_capacity(p.len() / 3);
            for k in 0..p.len() / 3 {
                let x = field(&p, 3 * k, "X")?;
                let y = field(&p, 3 * k + 1, "Y")?;
                let pid: i64 = field(&p, 3 * k + 2, "POINT3D_ID")?;
                points2d.push(([x, y], u64::try_from(pid).ok()));
            }
            Ok(ColmapImage {
                id,
                qvec,
                tvec,
                camera_id,
                name,
                points2d,
            })
        })()
        .map_err(|p| malformed(path, format!("line {line_no}: {p}")))?;
        images.push(image);
    }
    Ok(images)
}

/// Parses `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR TRACK[]` per line, the track being
/// `IMAGE_ID POINT2D_IDX` pairs.
pub fn parse_points3d_txt(bytes: &[u8], path: &Path) -> Result<Vec<ColmapPoint>, DatasetError> {
    let mut points = Vec::new();
    for (line_no, line) in text_lines(bytes, path)? {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let t: Vec<&str> = line.split_whitespace().collect();
        let point = (|| {
            if t.len() < 8 || !(t.len() - 8).is_multiple_of(2) {
                return Err(format!(
                    "expected `POINT3D_ID X Y Z R G B ERROR` and (IMAGE_ID, POINT2D_IDX) pairs, found {} fields",
                    t.len()
                ));
            }
            let id = field(&t, 0, "POINT3D_ID")?;
            let xyz = [field(&t, 1, "X")?, field(&t, 2, "Y")?, field(&t, 3, "Z")?];
            let xyz = finite_xyz(id, xyz)?;
            let rgb = [field(&t, 4, "R")?, field(&t, 5, "G")?, field(&t, 6, "B")?];
            let error = field(&t, 7, "ERROR")?;
            let track = (0..(t.len() - 8) / 2)
                .map(|k| {
                    Ok((
                        field(&t, 8 + 2 * k, "IMAGE_ID")?,
                        field(&t, 9 + 2 * k, "POINT2D_IDX")?,
                    ))
                })
                .collect::<Result<Vec<_>, String>>()?;
            Ok(ColmapPoint {
                id,
                xyz,
                rgb,
                error,
                track,
            })
        })()
        .map_err(|p| malformed(path, format!("line {line_no}: {p}")))?;
        points.push(point);
    }
    Ok(points)
}
