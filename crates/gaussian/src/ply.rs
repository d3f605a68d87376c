//! Reading and writing Gaussian scenes in the PLY layout of the official 3DGS trainer.
//!
//! # Layout
//! One `vertex` element with one float32 property per value, in this order:
//! `x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity scale_0 scale_1
//! scale_2 rot_0 rot_1 rot_2 rot_3`, with `K = (degree + 1)^2` SH coefficients per channel.
//! All values are stored before activation (log-scales, opacity logits, unnormalised
//! quaternions `(w, x, y, z)`). The DC coefficients are Gaussian-major RGB, but `f_rest` is
//! CHANNEL-major: `f_rest_{c (K-1) + (k-1)}` is coefficient `k >= 1` of channel `c`, whereas
//! [`FeatureGaussians::sh`] keeps `sh[n K + k][c]`. Normals are unused and written as 0.
//! When the scene carries features, `f_feat_0 .. f_feat_{F-1}` follow `rot_3`.
//!
//! # Reading
//! The reader accepts ASCII, binary little-endian and binary big-endian files, any scalar type
//! for the known properties (converted to `f32`), and the properties in any order: they are
//! looked up by name. The SH degree is inferred from the number of `f_rest_*` properties
//! (0, 9, 24, 45 for degrees 0..3; anything else is an error). Unknown scalar vertex properties
//! are kept as [`ExtraProperty`] columns and can be written back; unknown list properties and
//! other elements (faces, edges, ...) are parsed past and dropped. Every malformed or truncated
//! input yields a [`PlyError`] that names the file, the element and property (and instance)
//! and the problem; element counts are checked against the bytes that are actually present
//! before anything is allocated from them. Values are checked as they are read: a value that is
//! not finite as an `f32` (NaN, infinite, or a `double` beyond the `f32` range), or a position,
//! log-scale, opacity logit or rotation norm outside the bounds documented in [`crate::scene`]
//! ("Bounds on values read from files"), is refused naming the vertex (instance), the property
//! and the value.
//!
//! # Writing
//! [`save_ply`] writes the canonical binary little-endian layout above (with `float`
//! properties and no comments), so a file in that layout is re-saved byte for byte. Writes are
//! atomic: the bytes go to a temporary file in the target directory, which is then renamed.
//!
//! # Why not `ply-rs`
//! The PLY format needed here is a fixed-stride table of scalars, and this module needs three
//! things a general PLY object model does not give: errors that name the file, element,
//! instance and property; columnar decoding straight into the struct-of-arrays scene (a generic
//! reader materialises a key-value map or a setter call per property per vertex, about 62 per
//! Gaussian); and exact control of the header and property order on write, which byte-identical
//! re-saving and preserving unknown columns rely on. So this module parses PLY itself, with
//! checked arithmetic throughout. The `ply-rs-bw` crate is used by the tests as an independent
//! reader to cross-check the values this parser returns.

use std::fmt;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use crate::camera::{plain_number, plain_numbers};
use crate::scene::{
    SceneError, MAX_ABS_OPACITY_LOGIT, MAX_ABS_POSITION, MAX_LOG_SCALE, MAX_QUAT_NORM,
    MIN_LOG_SCALE, MIN_QUAT_NORM,
};
use crate::{FeatureGaussians, Real};

/// A PLY file that could not be read or written.
#[derive(Debug, thiserror::Error)]
#[error("{}: {kind}", path.display())]
pub struct PlyError {
    /// The file concerned (or the name given to in-memory bytes).
    pub path: PathBuf,
    /// What went wrong.
    pub kind: PlyErrorKind,
}

/// What went wrong with a PLY file.
#[derive(Debug, thiserror::Error)]
pub enum PlyErrorKind {
    /// Reading, writing or renaming the file failed. The message includes the I/O error's
    /// text, which is not also returned as [`std::error::Error::source`] (so it shows once).
    #[error("I/O error: {}", base::error::chain(.0))]
    Io(io::Error),
    /// A header line is malformed or unsupported.
    #[error("header line {line}: {problem}")]
    Header {
        /// 1-based header line number.
        line: usize,
        /// What is wrong with the line.
        problem: String,
    },
    /// An element's declared count does not fit in the bytes that remain.
    #[error("element `{element}`: {problem}")]
    Element {
        /// The element's name, e.g. `vertex`.
        element: String,
        /// What is wrong with it.
        problem: String,
    },
    /// A property value could not be parsed or converted.
    #[error("element `{element}` instance {instance}, property `{property}`: {problem}")]
    Value {
        /// The element's name.
        element: String,
        /// 0-based index of the instance within the element.
        instance: u64,
        /// The property's name.
        property: String,
        /// What is wrong with the value.
        problem: String,
    },
    /// The `vertex` element is missing or its properties do not form the 3DGS layout (e.g. an
    /// unsupported number of `f_rest_*` properties).
    #[error("vertex layout: {0}")]
    Layout(String),
    /// The scene to write (or the one read) fails [`FeatureGaussians::validate`]. The message
    /// includes the scene error's text, which is not also returned as
    /// [`std::error::Error::source`].
    #[error("invalid scene: {0}")]
    Scene(SceneError),
}

impl From<io::Error> for PlyErrorKind {
    fn from(e: io::Error) -> PlyErrorKind {
        PlyErrorKind::Io(e)
    }
}

impl From<SceneError> for PlyErrorKind {
    fn from(e: SceneError) -> PlyErrorKind {
        PlyErrorKind::Scene(e)
    }
}

impl PlyError {
    fn new(path: &Path, kind: PlyErrorKind) -> PlyError {
        PlyError {
            path: path.to_path_buf(),
            kind,
        }
    }
}

/// A PLY scalar type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScalarType {
    /// `char` (`int8`): signed 8-bit integer.
    I8,
    /// `uchar` (`uint8`): unsigned 8-bit integer.
    U8,
    /// `short` (`int16`): signed 16-bit integer.
    I16,
    /// `ushort` (`uint16`): unsigned 16-bit integer.
    U16,
    /// `int` (`int32`): signed 32-bit integer.
    I32,
    /// `uint` (`uint32`): unsigned 32-bit integer.
    U32,
    /// `float` (`float32`): IEEE 754 single precision.
    F32,
    /// `double` (`float64`): IEEE 754 double precision.
    F64,
}

impl ScalarType {
    /// Size in bytes of one binary value.
    pub fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }

    /// The type's name as written in headers (the original PLY spelling).
    pub fn ply_name(self) -> &'static str {
        match self {
            ScalarType::I8 => "char",
            ScalarType::U8 => "uchar",
            ScalarType::I16 => "short",
            ScalarType::U16 => "ushort",
            ScalarType::I32 => "int",
            ScalarType::U32 => "uint",
            ScalarType::F32 => "float",
            ScalarType::F64 => "double",
        }
    }

    /// Parses a header type name, in either the original or the sized spelling.
    pub fn from_ply_name(name: &str) -> Option<ScalarType> {
        Some(match name {
            "char" | "int8" => ScalarType::I8,
            "uchar" | "uint8" => ScalarType::U8,
            "short" | "int16" => ScalarType::I16,
            "ushort" | "uint16" => ScalarType::U16,
            "int" | "int32" => ScalarType::I32,
            "uint" | "uint32" => ScalarType::U32,
            "float" | "float32" => ScalarType::F32,
            "double" | "float64" => ScalarType::F64,
            _ => return None,
        })
    }

    fn is_float(self) -> bool {
        matches!(self, ScalarType::F32 | ScalarType::F64)
    }

    /// Decodes one binary value (`bytes.len() == self.size()`) exactly into an `f64`.
    fn decode(self, bytes: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&bytes[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a) as f64
                } else {
                    <$t>::from_le_bytes(a) as f64
                }
            }};
        }
        match self {
            ScalarType::I8 => get!(i8, 1),
            ScalarType::U8 => get!(u8, 1),
            ScalarType::I16 => get!(i16, 2),
            ScalarType::U16 => get!(u16, 2),
            ScalarType::I32 => get!(i32, 4),
            ScalarType::U32 => get!(u32, 4),
            ScalarType::F32 => get!(f32, 4),
            ScalarType::F64 => get!(f64, 8),
        }
    }

    /// Parses one ASCII token as this type, returning it exactly as an `f64`.
    fn parse_ascii(self, token: &str) -> Result<f64, String> {
        let bad = || format!("`{token}` is not a valid {}", self.ply_name());
        if self.is_float() {
            return match self {
                ScalarType::F32 => token.parse::<f32>().map(f64::from).map_err(|_| bad()),
                _ => token.parse::<f64>().map_err(|_| bad()),
            };
        }
        let v: i64 = token.parse().map_err(|_| bad())?;
        let (lo, hi) = match self {
            ScalarType::I8 => (i8::MIN as i64, i8::MAX as i64),
            ScalarType::U8 => (0, u8::MAX as i64),
            ScalarType::I16 => (i16::MIN as i64, i16::MAX as i64),
            ScalarType::U16 => (0, u16::MAX as i64),
            ScalarType::I32 => (i32::MIN as i64, i32::MAX as i64),
            _ => (0, u32::MAX as i64),
        };
        if v < lo || v > hi {
            return Err(format!("{v} is out of range for {}", self.ply_name()));
        }
        Ok(v as f64)
    }

    /// Appends `v` (which must be representable) in binary little-endian.
    fn encode_le(self, v: f64, out: &mut Vec<u8>) {
        match self {
            ScalarType::I8 => out.extend_from_slice(&(v as i8).to_le_bytes()),
            ScalarType::U8 => out.extend_from_slice(&(v as u8).to_le_bytes()),
            ScalarType::I16 => out.extend_from_slice(&(v as i16).to_le_bytes()),
            ScalarType::U16 => out.extend_from_slice(&(v as u16).to_le_bytes()),
            ScalarType::I32 => out.extend_from_slice(&(v as i32).to_le_bytes()),
            ScalarType::U32 => out.extend_from_slice(&(v as u32).to_le_bytes()),
            ScalarType::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
            ScalarType::F64 => out.extend_from_slice(&v.to_le_bytes()),
        }
    }

    /// Whether `v` is stored exactly by this type.
    fn represents(self, v: f64) -> bool {
        match self {
            ScalarType::F64 => true,
            ScalarType::F32 => v.is_nan() || (v as f32) as f64 == v,
            _ => v.fract() == 0.0 && self.parse_ascii(&format!("{v:.0}")).is_ok(),
        }
    }
}

impl fmt::Display for ScalarType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.ply_name())
    }
}

/// An unknown scalar vertex property, kept so that it can be written back.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtraProperty {
    /// The property's name in the header.
    pub name: String,
    /// The type it had in the file (and is written back as).
    pub ty: ScalarType,
    /// One value per Gaussian, exactly as stored.
    pub values: Vec<f64>,
}

/// A scene read from PLY together with the vertex properties the scene does not model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyScene {
    /// The Gaussians.
    pub gaussians: FeatureGaussians<f32>,
    /// Unknown scalar vertex properties, in file order.
    pub extras: Vec<ExtraProperty>,
}

// ---------------------------------------------------------------------------------------------
// header

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Clone, Debug)]
enum PropKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Clone, Debug)]
struct PropertyDef {
    name: String,
    kind: PropKind,
}

#[derive(Clone, Debug)]
struct ElementDef {
    name: String,
    count: u64,
    props: Vec<PropertyDef>,
}

struct Header {
    format: Format,
    elements: Vec<ElementDef>,
    /// Offset of the first byte after `end_header\n`.
    body_start: usize,
}

fn header_err(path: &Path, line: usize, problem: impl Into<String>) -> PlyError {
    PlyError::new(
        path,
        PlyErrorKind::Header {
            line,
            problem: problem.into(),
        },
    )
}

/// Whether `s` is a non-empty run of printable, non-space ASCII characters.
fn is_plain_word(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|b| b.is_ascii_graphic())
}

fn parse_header(bytes: &[u8], path: &Path) -> Result<Header, PlyError> {
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<ElementDef> = Vec::new();
    loop {
        line_no += 1;
        let Some(nl) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(header_err(
                path,
                line_no,
                "file ends before `end_header` (truncated or not a PLY file)",
            ));
        };
        let raw = &bytes[pos..pos + nl];
        pos += nl + 1;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        // The magic line first, on the raw bytes: an image or any other file is named as not a
        // PLY file rather than by what its first bytes happen to be.
        if line_no == 1 {
            if raw.trim_ascii_end() != b"ply" {
                return Err(header_err(
                    path,
                    1,
                    "not a PLY file: it does not start with the `ply` magic line",
                ));
            }
            continue;
        }
        let Ok(line) = std::str::from_utf8(raw) else {
            return Err(header_err(path, line_no, "header line is not valid text"));
        };
        let mut words = line.split_ascii_whitespace();
        let Some(keyword) = words.next() else {
            continue; // tolerate blank lines
        };
        let rest: Vec<&str> = words.collect();
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                if format.is_some() {
                    return Err(header_err(path, line_no, "second `format` line"));
                }
                let f = match rest.first().copied() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::BinaryLittleEndian,
                    Some("binary_big_endian") => Format::BinaryBigEndian,
                    other => {
                        return Err(header_err(
                            path,
                            line_no,
                            format!("unknown format {:?}", other.unwrap_or("")),
                        ))
                    }
                };
                if rest.get(1).copied() != Some("1.0") || rest.len() != 2 {
                    return Err(header_err(
                        path,
                        line_no,
                        format!("expected `format {} 1.0`", rest[0]),
                    ));
                }
                format = Some(f);
            }
            "element" => {
                let [name, count] = rest[..] else {
                    return Err(header_err(
                        path,
                        line_no,
                        "expected `element <name> <count>`",
                    ));
                };
                let count: u64 = count.parse().map_err(|_| {
                    header_err(
                        path,
                        line_no,
                        format!("element `{name}` has an invalid count `{count}`"),
                    )
                })?;
                if !is_plain_word(name) {
                    return Err(header_err(
                        path,
                        line_no,
                        format!("element name {name:?} is not printable ASCII"),
                    ));
                }
                if elements.iter().any(|e| e.name == name) {
                    return Err(header_err(
                        path,
                        line_no,
                        format!("element `{name}` declared twice"),
                    ));
                }
                elements.push(ElementDef {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(header_err(path, line_no, "`property` before any `element`"));
                };
                let ty = |name: &str| {
                    ScalarType::from_ply_name(name).ok_or_else(|| {
                        header_err(path, line_no, format!("unknown property type `{name}`"))
                    })
                };
                let (name, kind) = match rest[..] {
                    ["list", count, item, name] => {
                        let count = ty(count)?;
                        if count.is_float() {
                            return Err(header_err(
                                path,
                                line_no,
                                format!("list `{name}` has a floating-point count type"),
                            ));
                        }
                        (
                            name,
                            PropKind::List {
                                count,
                                item: ty(item)?,
                            },
                        )
                    }
                    [t, name] if t != "list" => (name, PropKind::Scalar(ty(t)?)),
                    _ => {
                        return Err(header_err(
                            path,
                            line_no,
                            "expected `property <type> <name>` or `property list <count type> <item type> <name>`",
                        ))
                    }
                };
                if !is_plain_word(name) {
                    return Err(header_err(
                        path,
                        line_no,
                        format!("property name {name:?} is not printable ASCII"),
                    ));
                }
                if element.props.iter().any(|p| p.name == name) {
                    return Err(header_err(
                        path,
                        line_no,
                        format!(
                            "property `{name}` declared twice in element `{}`",
                            element.name
                        ),
                    ));
                }
                element.props.push(PropertyDef {
                    name: name.to_string(),
                    kind,
                });
            }
            "end_header" => {
                let Some(format) = format else {
                    return Err(header_err(
                        path,
                        line_no,
                        "no `format` line before `end_header`",
                    ));
                };
                return Ok(Header {
                    format,
                    elements,
                    body_start: pos,
                });
            }
            other => {
                return Err(header_err(
                    path,
                    line_no,
                    format!("unknown header keyword `{other}`"),
                ))
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// body

/// Where a vertex property goes in the scene.
#[derive(Clone, Copy, Debug)]
enum Target {
    Mean(usize),
    Normal,
    Dc(usize),
    Rest(usize),
    Opacity,
    Scale(usize),
    Rot(usize),
    Feat(usize),
    Extra(usize),
    /// An unknown list property: parsed past and dropped.
    Skip,
}

/// Parses `prefix<i>` with a plain decimal index.
fn indexed(name: &str, prefix: &str) -> Option<usize> {
    let digits = name.strip_prefix(prefix)?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    if digits.len() > 1 && digits.starts_with('0') {
        return None;
    }
    digits.parse().ok()
}

/// The layout of the vertex element: a target per property, the SH degree and feature width.
struct VertexLayout {
    targets: Vec<Target>,
    sh_degree: usize,
    feature_dim: usize,
    extras: Vec<(String, ScalarType)>,
}

fn vertex_layout(vertex: &ElementDef, path: &Path) -> Result<VertexLayout, PlyError> {
    let layout_err = |p: String| PlyError::new(path, PlyErrorKind::Layout(p));
    let mut targets = Vec::with_capacity(vertex.props.len());
    let mut extras = Vec::new();
    let (mut n_rest, mut n_feat) = (0usize, 0usize);
    for p in &vertex.props {
        let name = p.name.as_str();
        let t = match name {
            "x" => Target::Mean(0),
            "y" => Target::Mean(1),
            "z" => Target::Mean(2),
            "nx" | "ny" | "nz" => Target::Normal,
            "opacity" => Target::Opacity,
            _ => {
                if let Some(i) = indexed(name, "f_dc_").filter(|&i| i < 3) {
                    Target::Dc(i)
                } else if let Some(i) = indexed(name, "scale_").filter(|&i| i < 3) {
                    Target::Scale(i)
                } else if let Some(i) = indexed(name, "rot_").filter(|&i| i < 4) {
                    Target::Rot(i)
                } else if let Some(i) = indexed(name, "f_rest_") {
                    n_rest += 1;
                    Target::Rest(i)
                } else if let Some(i) = indexed(name, "f_feat_") {
                    n_feat += 1;
                    Target::Feat(i)
                } else {
                    match p.kind {
                        PropKind::Scalar(ty) => {
                            extras.push((p.name.clone(), ty));
                            Target::Extra(extras.len() - 1)
                        }
                        PropKind::List { .. } => Target::Skip,
                    }
                }
            }
        };
        if !matches!(t, Target::Extra(_) | Target::Skip) {
            if let PropKind::List { .. } = p.kind {
                return Err(layout_err(format!(
                    "property `{name}` is a list; the Gaussian layout needs a scalar"
                )));
            }
        }
        targets.push(t);
    }
    const REQUIRED: [&str; 14] = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    for name in REQUIRED {
        if !vertex.props.iter().any(|p| p.name == name) {
            return Err(layout_err(format!(
                "required property `{name}` is missing from element `vertex`"
            )));
        }
    }
    let sh_degree = match n_rest {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        n => {
            return Err(layout_err(format!(
                "{n} `f_rest_*` properties; expected 0, 9, 24 or 45 (SH degree 0..3)"
            )))
        }
    };
    // Names are unique, so indices are distinct; they must also be exactly 0..n.
    if let Some(i) = targets.iter().find_map(|t| match *t {
        Target::Rest(i) if i >= n_rest => Some(i),
        _ => None,
    }) {
        return Err(layout_err(format!(
            "`f_rest_{i}` present but there are only {n_rest} `f_rest_*` properties (indices must run 0..{n_rest})"
        )));
    }
    if let Some(i) = targets.iter().find_map(|t| match *t {
        Target::Feat(i) if i >= n_feat => Some(i),
        _ => None,
    }) {
        return Err(layout_err(format!(
            "`f_feat_{i}` present but there are only {n_feat} `f_feat_*` properties (indices must run 0..{n_feat})"
        )));
    }
    Ok(VertexLayout {
        targets,
        sh_degree,
        feature_dim: n_feat,
        extras,
    })
}

/// Scene arrays being filled, one Gaussian at a time.
struct SceneBuilder {
    scene: FeatureGaussians<f32>,
    extras: Vec<ExtraProperty>,
    k: usize,
}

impl SceneBuilder {
    fn new(layout: &VertexLayout, capacity: usize) -> SceneBuilder {
        let k = (layout.sh_degree + 1) * (layout.sh_degree + 1);
        SceneBuilder {
            scene: FeatureGaussians {
                means: Vec::with_capacity(capacity),
                log_scales: Vec::with_capacity(capacity),
                quats: Vec::with_capacity(capacity),
                opacity_logits: Vec::with_capacity(capacity),
                sh_degree: layout.sh_degree,
                sh: Vec::with_capacity(capacity.saturating_mul(k)),
                feature_dim: layout.feature_dim,
                features: Vec::with_capacity(capacity.saturating_mul(layout.feature_dim)),
            },
            extras: layout
                .extras
                .iter()
                .map(|(name, ty)| ExtraProperty {
                    name: name.clone(),
                    ty: *ty,
                    values: Vec::with_capacity(capacity),
                })
                .collect(),
            k,
        }
    }

    /// Opens a new Gaussian, zero-initialised.
    fn push_zero(&mut self) {
        let s = &mut self.scene;
        s.means.push([0.0; 3]);
        s.log_scales.push([0.0; 3]);
        s.quats.push([0.0; 4]);
        s.opacity_logits.push(0.0);
        s.sh.extend(std::iter::repeat_n([0.0f32; 3], self.k));
        s.features
            .extend(std::iter::repeat_n(0.0f32, s.feature_dim));
        for e in &mut self.extras {
            e.values.push(0.0);
        }
    }

    /// Stores value `v` of the current (last) Gaussian.
    fn set(&mut self, target: Target, v: f64) {
        let s = &mut self.scene;
        let n = s.means.len() - 1;
        let f = v as f32;
        match target {
            Target::Mean(a) => s.means[n][a] = f,
            Target::Dc(c) => s.sh[n * self.k][c] = f,
            Target::Rest(j) => {
                let km1 = self.k - 1;
                s.sh[n * self.k + 1 + j % km1][j / km1] = f;
            }
            Target::Opacity => s.opacity_logits[n] = f,
            Target::Scale(a) => s.log_scales[n][a] = f,
            Target::Rot(a) => s.quats[n][a] = f,
            Target::Feat(j) => s.features[n * s.feature_dim + j] = f,
            Target::Extra(e) => {
                if let Some(last) = self.extras[e].values.last_mut() {
                    *last = v;
                }
            }
            Target::Normal | Target::Skip => {}
        }
    }
}

/// Why a value read for `target` is refused, if it is: it is not finite as an `f32`, or it is
/// outside the bounds of [`crate::scene`] (see its "Bounds on values read from files").
/// Rotations are also checked as a whole by [`quat_problem`].
fn value_problem(target: Target, v: f64) -> Option<String> {
    let what = match target {
        Target::Mean(_) => "positions (means)",
        Target::Dc(_) | Target::Rest(_) => "SH coefficients",
        Target::Opacity => "opacity logits",
        Target::Scale(_) => "log-scales",
        Target::Rot(_) => "rotation quaternions",
        Target::Feat(_) => "features",
        Target::Normal | Target::Extra(_) | Target::Skip => return None,
    };
    let f = v as f32;
    if !f.is_finite() {
        let why = if v.is_finite() {
            " (beyond the 32-bit float range)"
        } else {
            ""
        };
        return Some(format!(
            "non-finite value {}{why}; {what} must be finite",
            plain_number(v)
        ));
    }
    match target {
        Target::Mean(_) if f.abs() > MAX_ABS_POSITION => Some(format!(
            "position coordinate {} is outside ±{MAX_ABS_POSITION:e}, the accepted range of {what}",
            plain_number(f)
        )),
        Target::Scale(_) if !(MIN_LOG_SCALE..=MAX_LOG_SCALE).contains(&f) => Some(format!(
            "log-scale {} is outside [{MIN_LOG_SCALE}, {MAX_LOG_SCALE}], the accepted range of \
             {what} (the activated scale, its exponential, would be {})",
            plain_number(f),
            plain_number(f.exp())
        )),
        Target::Opacity if f.abs() > MAX_ABS_OPACITY_LOGIT => Some(format!(
            "opacity logit {} is outside ±{MAX_ABS_OPACITY_LOGIT:e}, the accepted range of {what}",
            plain_number(f)
        )),
        _ => None,
    }
}

/// Why a rotation quaternion (as stored, `f32`) is refused, if it is: its norm is outside
/// [[`MIN_QUAT_NORM`], [`MAX_QUAT_NORM`]], so it cannot be normalised into a rotation.
fn quat_problem(q: [f32; 4]) -> Option<String> {
    let norm = q.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
    (!(MIN_QUAT_NORM..=MAX_QUAT_NORM).contains(&norm)).then(|| {
        format!(
            "the rotation quaternion {} has norm {}, outside [{MIN_QUAT_NORM:e}, \
             {MAX_QUAT_NORM:e}]; it cannot be normalised into a rotation",
            plain_numbers(&q),
            plain_number(norm)
        )
    })
}

/// Fewest bytes one instance of an element can take in the body (binary: scalars and list
/// counts; ASCII: one character per value, plus a separator).
fn min_instance_bytes(e: &ElementDef, format: Format) -> usize {
    e.props
        .iter()
        .map(|p| match (format, &p.kind) {
            (Format::Ascii, _) => 2,
            (_, PropKind::Scalar(t)) => t.size(),
            (_, PropKind::List { count, .. }) => count.size(),
        })
        .sum()
}

fn value_err(path: &Path, e: &ElementDef, instance: u64, prop: &str, problem: String) -> PlyError {
    PlyError::new(
        path,
        PlyErrorKind::Value {
            element: e.name.clone(),
            instance,
            property: prop.to_string(),
            problem,
        },
    )
}

/// A cursor over the body that hands out values as exact `f64`s, binary or ASCII.
struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    format: Format,
}

impl Body<'_> {
    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// The next value of type `ty`, or a description of why there is none.
    fn next(&mut self, ty: ScalarType) -> Result<f64, String> {
        match self.format {
            Format::Ascii => {
                let rest = &self.bytes[self.pos..];
                let start = rest
                    .iter()
                    .position(|b| !b.is_ascii_whitespace())
                    .ok_or_else(|| "file ends early (truncated)".to_string())?;
                let len = rest[start..]
                    .iter()
                    .position(|b| b.is_ascii_whitespace())
                    .unwrap_or(rest.len() - start);
                let token = &rest[start..start + len];
                self.pos += start + len;
                let token = std::str::from_utf8(token)
                    .map_err(|_| "value is not valid text".to_string())?;
                ty.parse_ascii(token)
            }
            Format::BinaryLittleEndian | Format::BinaryBigEndian => {
                let size = ty.size();
                if self.remaining() < size {
                    return Err(format!(
                        "file ends early (truncated): {size} bytes needed at offset {}, {} left",
                        self.pos,
                        self.remaining()
                    ));
                }
                let v = ty.decode(
                    &self.bytes[self.pos..self.pos + size],
                    self.format == Format::BinaryBigEndian,
                );
                self.pos += size;
                Ok(v)
            }
        }
    }

    /// Reads (and discards) one list value, returning nothing.
    fn skip_list(&mut self, count: ScalarType, item: ScalarType) -> Result<(), String> {
        let n = self.next(count)?;
        if n < 0.0 {
            return Err(format!("negative list length {n}"));
        }
        let n = n as u64;
        if self.format != Format::Ascii {
            let bytes = n.saturating_mul(item.size() as u64);
            if bytes > self.remaining() as u64 {
                return Err(format!(
                    "list of {n} items needs {bytes} bytes at offset {}, {} left (truncated)",
                    self.pos,
                    self.remaining()
                ));
            }
            self.pos += bytes as usize;
            return Ok(());
        }
        for _ in 0..n {
            self.next(item)?;
        }
        Ok(())
    }
}

/// Parses PLY bytes into a scene. `path` only names the source in errors.
pub fn parse_ply(bytes: &[u8], path: &Path) -> Result<PlyScene, PlyError> {
    let header = parse_header(bytes, path)?;
    let Some(vertex_index) = header.elements.iter().position(|e| e.name == "vertex") else {
        return Err(PlyError::new(
            path,
            PlyErrorKind::Layout("the file has no `vertex` element".into()),
        ));
    };
    let layout = vertex_layout(&header.elements[vertex_index], path)?;
    let mut body = Body {
        bytes,
        pos: header.body_start,
        format: header.format,
    };
    let mut builder = None;
    for (ei, e) in header.elements.iter().enumerate() {
        let min = min_instance_bytes(e, header.format) as u64;
        let needed = e.count.checked_mul(min);
        let left = body.remaining() as u64;
        if needed.is_none_or(|b| b > left.saturating_add(1)) {
            return Err(PlyError::new(
                path,
                PlyErrorKind::Element {
                    element: e.name.clone(),
                    problem: format!(
                        "declares {} instances, which need at least {} bytes, but only {left} bytes remain (truncated or corrupt count)",
                        e.count,
                        needed.map_or("more than 2^64".to_string(), |b| b.to_string()),
                    ),
                },
            ));
        }
        if e.props.is_empty() {
            continue; // nothing to read, whatever the count says
        }
        let is_vertex = ei == vertex_index;
        if is_vertex {
            // Bounded by the bytes present (checked above), so this cannot be absurd.
            builder = Some(SceneBuilder::new(&layout, e.count as usize));
        }
        for instance in 0..e.count {
            if let Some(b) = builder.as_mut().filter(|_| is_vertex) {
                b.push_zero();
            }
            for (pi, p) in e.props.iter().enumerate() {
                let result = match p.kind {
                    PropKind::Scalar(ty) => body.next(ty).map(Some),
                    PropKind::List { count, item } => body.skip_list(count, item).map(|_| None),
                };
                let v = result.map_err(|problem| value_err(path, e, instance, &p.name, problem))?;
                if let (Some(b), Some(v), true) = (builder.as_mut(), v, is_vertex) {
                    let target = layout.targets[pi];
                    if let Some(problem) = value_problem(target, v) {
                        return Err(value_err(path, e, instance, &p.name, problem));
                    }
                    b.set(target, v);
                }
            }
            if let Some(b) = builder.as_ref().filter(|_| is_vertex) {
                let q = b
                    .scene
                    .quats
                    .last()
                    .copied()
                    .unwrap_or([1.0, 0.0, 0.0, 0.0]);
                if let Some(problem) = quat_problem(q) {
                    return Err(value_err(path, e, instance, "rot_0 .. rot_3", problem));
                }
            }
        }
    }
    let Some(builder) = builder else {
        return Err(PlyError::new(
            path,
            PlyErrorKind::Layout("the file has no `vertex` element".into()),
        ));
    };
    builder
        .scene
        .validate()
        .map_err(|e| PlyError::new(path, e.into()))?;
    Ok(PlyScene {
        gaussians: builder.scene,
        extras: builder.extras,
    })
}

/// Reads a 3DGS PLY file, keeping unknown scalar vertex properties.
pub fn load_ply_with_extras(path: impl AsRef<Path>) -> Result<PlyScene, PlyError> {
    let path = path.as_ref();
    let bytes = fs::read(path).map_err(|e| PlyError::new(path, e.into()))?;
    parse_ply(&bytes, path)
}

/// Reads a 3DGS PLY file (see the module documentation for what is accepted).
pub fn load_ply(path: impl AsRef<Path>) -> Result<FeatureGaussians<f32>, PlyError> {
    load_ply_with_extras(path).map(|s| s.gaussians)
}

// ---------------------------------------------------------------------------------------------
// writing

/// The canonical property names of a scene with `sh_degree` and `feature_dim`, in file order.
pub fn property_names(sh_degree: usize, feature_dim: usize) -> Vec<String> {
    let k = (sh_degree + 1) * (sh_degree + 1);
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names.extend((0..feature_dim).map(|i| format!("f_feat_{i}")));
    names
}

/// Encodes a scene (and extra columns, written after the known properties) as binary
/// little-endian PLY bytes. `path` only names the destination in errors.
pub fn encode_ply<T: Real>(
    scene: &FeatureGaussians<T>,
    extras: &[ExtraProperty],
    path: &Path,
) -> Result<Vec<u8>, PlyError> {
    scene
        .validate()
        .map_err(|e| PlyError::new(path, e.into()))?;
    let n = scene.len();
    let names = property_names(scene.sh_degree, scene.feature_dim);
    for (i, e) in extras.iter().enumerate() {
        let problem = if names.contains(&e.name) || extras[..i].iter().any(|o| o.name == e.name) {
            Some(format!(
                "extra property `{}` clashes with another property",
                e.name
            ))
        } else if !is_plain_word(&e.name) {
            Some(format!(
                "extra property name {:?} is not a single printable word",
                e.name
            ))
        } else if e.values.len() != n {
            Some(format!(
                "extra property `{}` has {} values for {n} Gaussians",
                e.name,
                e.values.len()
            ))
        } else {
            e.values.iter().position(|&v| !e.ty.represents(v)).map(|i| {
                format!(
                    "extra property `{}` value {} at index {i} is not a {}",
                    e.name, e.values[i], e.ty
                )
            })
        };
        if let Some(p) = problem {
            return Err(PlyError::new(path, PlyErrorKind::Layout(p)));
        }
    }
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    for name in &names {
        header.push_str(&format!("property float {name}\n"));
    }
    for e in extras {
        header.push_str(&format!("property {} {}\n", e.ty, e.name));
    }
    header.push_str("end_header\n");
    let stride = 4 * names.len() + extras.iter().map(|e| e.ty.size()).sum::<usize>();
    let mut out = Vec::with_capacity(header.len() + n * stride);
    out.extend_from_slice(header.as_bytes());
    let k = scene.sh_coeffs_per_gaussian();
    let put =
        |out: &mut Vec<u8>, v: T| out.extend_from_slice(&(v.to_f64_exact() as f32).to_le_bytes());
    for i in 0..n {
        for &v in &scene.means[i] {
            put(&mut out, v);
        }
        out.extend_from_slice(&[0u8; 12]); // normals
        let sh = scene.sh_of(i);
        for &v in &sh[0] {
            put(&mut out, v);
        }
        for c in 0..3 {
            for coeff in &sh[1..k] {
                put(&mut out, coeff[c]);
            }
        }
        put(&mut out, scene.opacity_logits[i]);
        for &v in &scene.log_scales[i] {
            put(&mut out, v);
        }
        for &v in &scene.quats[i] {
            put(&mut out, v);
        }
        for &v in scene.feature_of(i) {
            put(&mut out, v);
        }
        for e in extras {
            e.ty.encode_le(e.values[i], &mut out);
        }
    }
    Ok(out)
}

/// Writes a scene as a 3DGS PLY file (binary little-endian), atomically.
pub fn save_ply<T: Real>(
    path: impl AsRef<Path>,
    scene: &FeatureGaussians<T>,
) -> Result<(), PlyError> {
    save_ply_with_extras(path, scene, &[])
}

/// Writes a scene and extra vertex columns as a 3DGS PLY file, atomically.
pub fn save_ply_with_extras<T: Real>(
    path: impl AsRef<Path>,
    scene: &FeatureGaussians<T>,
    extras: &[ExtraProperty],
) -> Result<(), PlyError> {
    let path = path.as_ref();
    let bytes = encode_ply(scene, extras, path)?;
    base::write_atomic(path, &bytes).map_err(|e| PlyError::new(path, e.into()))
}
