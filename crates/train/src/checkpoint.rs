//! Geometry-stage checkpoints: everything needed to resume training exactly.
//!
//! One safetensors file holds, as tensors:
//! * the scene: `scene.means [N,3]`, `scene.log_scales [N,3]`, `scene.quats [N,4]`,
//!   `scene.opacity_logits [N]`, `scene.sh [N,K,3]` (f32);
//! * the Adam state of every group `G`: `adam.G.exp_avg`, `adam.G.exp_avg_sq` (`[N, width]`, f32);
//! * the densification statistics: `stats.grad_norm_sum [N]` (f64), `stats.visible_count [N]`,
//!   `stats.max_screen_radius [N]` (u32);
//! * the views left in the current pass over the training set: `view_stack [M]` (u64);
//!
//! and, as string metadata, the format tag, the completed step, the seed, the scene extent, the
//! active SH degree, each group's learning rate and step count, the running averages shown in
//! the progress bar and the configuration (JSON). Floating-point metadata is written in Rust's
//! shortest round-trip form, so it reads back bit-identically. The file is written to a temporary
//! name in the same directory and renamed into place.

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

use gaussian::FeatureGaussians;
use safetensors::{Dtype, SafeTensors};

use crate::adam::{Adam, AdamConfig, ParamState};
use crate::error::TrainError;
use crate::model::GaussianModel;
use raster::DensificationStats;

/// The completed step recorded in the `step` metadata of any checkpoint of dsgs (geometry,
/// decoder, features, bake), read from the file's header alone.
pub fn checkpoint_step(path: &Path) -> Result<u64, TrainError> {
    use std::io::Read;
    let bad = |message: String| TrainError::Checkpoint {
        path: path.to_path_buf(),
        message,
    };
    let mut f = std::fs::File::open(path).map_err(|e| TrainError::io(path, e))?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|e| bad(format!("no safetensors header ({e})")))?;
    let len = u64::from_le_bytes(len);
    if len > 100_000_000 {
        return Err(bad(format!("a header of {len} bytes is not plausible")));
    }
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header)
        .map_err(|e| bad(format!("truncated header ({e})")))?;
    let json: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| bad(format!("header is not JSON ({e})")))?;
    json["__metadata__"]["step"]
        .as_str()
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| bad("no step in the metadata".into()))
}

/// The value of the `format` metadata entry.
pub const FORMAT: &str = "dsgs-geometry-checkpoint-v1";

/// The resumable state of a geometry training run.
#[derive(Clone, Debug, PartialEq)]
pub struct GeometryCheckpoint {
    /// Completed iterations.
    pub step: u64,
    /// The scene with its Adam state and densification statistics.
    pub model: GaussianModel,
    /// Training-view indices not yet visited in the current pass.
    pub view_stack: Vec<usize>,
    /// Exponential moving average of the training loss (progress display only).
    pub ema_loss: f64,
    /// Exponential moving average of the training PSNR in dB (progress display only).
    pub ema_psnr: f64,
    /// The run seed ([`GeometryConfig::seed`](crate::GeometryConfig::seed)); the random choices
    /// of every iteration follow from it and the iteration number.
    pub seed: u64,
    /// The scene extent (3DGS `cameras_extent`).
    pub extent: f64,
    /// The configuration of the run, as JSON (informative).
    pub config_json: String,
}

struct Tensor<'a> {
    name: String,
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: Cow<'a, [u8]>,
}

/// An `f32` tensor over `v`'s own bytes on little-endian machines (no copy of the values), over a
/// little-endian copy elsewhere.
fn f32_tensor<'a>(name: &str, shape: Vec<usize>, v: &'a [f32]) -> Tensor<'a> {
    Tensor {
        name: name.to_string(),
        dtype: Dtype::F32,
        shape,
        bytes: if cfg!(target_endian = "little") {
            Cow::Borrowed(bytemuck::cast_slice(v))
        } else {
            Cow::Owned(v.iter().flat_map(|x| x.to_le_bytes()).collect())
        },
    }
}

/// The contents of a geometry checkpoint, borrowed: those of a [`GeometryCheckpoint`], or of a
/// trainer writing one without copying its model first.
pub(crate) struct CheckpointParts<'a> {
    pub step: u64,
    pub model: &'a GaussianModel,
    pub view_stack: &'a [usize],
    pub ema_loss: f64,
    pub ema_psnr: f64,
    pub seed: u64,
    pub extent: f64,
    pub config_json: &'a str,
}

impl GeometryCheckpoint {
    /// Serialises the checkpoint to safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, TrainError> {
        Ok(self.parts().encode()?.into_vec())
    }

    fn parts(&self) -> CheckpointParts<'_> {
        CheckpointParts {
            step: self.step,
            model: &self.model,
            view_stack: &self.view_stack,
            ema_loss: self.ema_loss,
            ema_psnr: self.ema_psnr,
            seed: self.seed,
            extent: self.extent,
            config_json: &self.config_json,
        }
    }

    /// Writes the checkpoint atomically.
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        self.parts().save(path)
    }
}

impl CheckpointParts<'_> {
    /// The checkpoint, owning copies of the parts.
    pub(crate) fn to_owned(&self) -> GeometryCheckpoint {
        GeometryCheckpoint {
            step: self.step,
            model: self.model.clone(),
            view_stack: self.view_stack.to_vec(),
            ema_loss: self.ema_loss,
            ema_psnr: self.ema_psnr,
            seed: self.seed,
            extent: self.extent,
            config_json: self.config_json.to_string(),
        }
    }

    /// The checkpoint's file, in the two pieces of [`nets::weights_file::Canonical`].
    fn encode(&self) -> Result<nets::weights_file::Canonical, TrainError> {
        let m = self.model;
        let s = &m.scene;
        let n = s.len();
        let k = s.sh_coeffs_per_gaussian();
        let mut tensors = vec![
            f32_tensor("scene.means", vec![n, 3], s.means.as_flattened()),
            f32_tensor("scene.log_scales", vec![n, 3], s.log_scales.as_flattened()),
            f32_tensor("scene.quats", vec![n, 4], s.quats.as_flattened()),
            f32_tensor("scene.opacity_logits", vec![n], &s.opacity_logits),
            f32_tensor("scene.sh", vec![n, k, 3], s.sh.as_flattened()),
        ];
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), FORMAT.to_string());
        meta.insert("step".to_string(), self.step.to_string());
        meta.insert("seed".to_string(), self.seed.to_string());
        meta.insert("extent".to_string(), self.extent.to_string());
        meta.insert("ema_loss".to_string(), self.ema_loss.to_string());
        meta.insert("ema_psnr".to_string(), self.ema_psnr.to_string());
        meta.insert("sh_degree".to_string(), s.sh_degree.to_string());
        meta.insert(
            "active_sh_degree".to_string(),
            m.active_sh_degree.to_string(),
        );
        meta.insert("adam.beta1".to_string(), m.adam.config.beta1.to_string());
        meta.insert("adam.beta2".to_string(), m.adam.config.beta2.to_string());
        meta.insert("adam.eps".to_string(), m.adam.config.eps.to_string());
        let names: Vec<&str> = m.adam.params().iter().map(|p| p.name.as_str()).collect();
        meta.insert("adam.groups".to_string(), names.join(","));
        for p in m.adam.params() {
            let w = p.width();
            meta.insert(format!("adam.{}.lr", p.name), p.lr.to_string());
            meta.insert(format!("adam.{}.step", p.name), p.step_count().to_string());
            meta.insert(format!("adam.{}.width", p.name), w.to_string());
            tensors.push(f32_tensor(
                &format!("adam.{}.exp_avg", p.name),
                vec![p.rows(), w],
                p.exp_avg(),
            ));
            tensors.push(f32_tensor(
                &format!("adam.{}.exp_avg_sq", p.name),
                vec![p.rows(), w],
                p.exp_avg_sq(),
            ));
        }
        meta.insert("config".to_string(), self.config_json.to_string());
        tensors.push(Tensor {
            name: "stats.grad_norm_sum".into(),
            dtype: Dtype::F64,
            shape: vec![n],
            bytes: m
                .stats
                .grad_norm_sum
                .iter()
                .flat_map(|x| x.to_le_bytes())
                .collect(),
        });
        for (name, v) in [
            ("stats.visible_count", &m.stats.visible_count),
            ("stats.max_screen_radius", &m.stats.max_screen_radius),
        ] {
            tensors.push(Tensor {
                name: name.into(),
                dtype: Dtype::U32,
                shape: vec![n],
                bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            });
        }
        tensors.push(Tensor {
            name: "view_stack".into(),
            dtype: Dtype::U64,
            shape: vec![self.view_stack.len()],
            bytes: self
                .view_stack
                .iter()
                .flat_map(|&x| (x as u64).to_le_bytes())
                .collect(),
        });
        let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = tensors
            .iter()
            .map(|t| {
                safetensors::tensor::TensorView::new(t.dtype, t.shape.clone(), &t.bytes)
                    .map(|v| (t.name.clone(), v))
                    .map_err(|error| TrainError::Tensor {
                        what: format!("checkpoint tensor {}", t.name),
                        error,
                    })
            })
            .collect::<Result<_, _>>()?;
        nets::weights_file::canonical(views, meta).map_err(|problem| TrainError::Serialize {
            what: "the checkpoint",
            problem,
        })
    }

    /// Writes the checkpoint atomically, header and tensor data in turn.
    pub(crate) fn save(&self, path: &Path) -> Result<(), TrainError> {
        let file = self.encode()?;
        base::write_atomic_with(path, |f| file.write_to(f)).map_err(|e| TrainError::io(path, e))
    }
}

impl GeometryCheckpoint {
    /// Reads a checkpoint written by [`GeometryCheckpoint::save`].
    pub fn load(path: &Path) -> Result<Self, TrainError> {
        let bytes = std::fs::read(path).map_err(|e| TrainError::io(path, e))?;
        Self::from_bytes(&bytes, path)
    }

    /// Parses checkpoint bytes; `path` only names the file in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, TrainError> {
        let r = Reader::new(bytes, path)?;
        if r.meta_str("format")? != FORMAT {
            return Err(r.err(format!(
                "format `{}` is not `{FORMAT}`",
                r.meta_str("format")?
            )));
        }
        let sh_degree: usize = r.meta_parse("sh_degree")?;
        if sh_degree > 3 {
            return Err(r.err(format!("SH degree {sh_degree} is not supported")));
        }
        let k = (sh_degree + 1) * (sh_degree + 1);
        let means = r.f32s("scene.means", &[None, Some(3)])?;
        let n = means.len() / 3;
        let scene = FeatureGaussians {
            means: rows3(&means),
            log_scales: rows3(&r.f32s("scene.log_scales", &[Some(n), Some(3)])?),
            quats: r
                .f32s("scene.quats", &[Some(n), Some(4)])?
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            opacity_logits: r.f32s("scene.opacity_logits", &[Some(n)])?,
            sh_degree,
            sh: rows3(&r.f32s("scene.sh", &[Some(n), Some(k), Some(3)])?),
            feature_dim: 0,
            features: Vec::new(),
        };
        let config = AdamConfig {
            beta1: r.meta_parse("adam.beta1")?,
            beta2: r.meta_parse("adam.beta2")?,
            eps: r.meta_parse("adam.eps")?,
        };
        let mut adam = Adam::new(config);
        for name in r.meta_str("adam.groups")?.split(',') {
            let width: usize = r.meta_parse(&format!("adam.{name}.width"))?;
            let m = r.f32s(&format!("adam.{name}.exp_avg"), &[Some(n), Some(width)])?;
            let v = r.f32s(&format!("adam.{name}.exp_avg_sq"), &[Some(n), Some(width)])?;
            let state = ParamState::from_parts(
                name,
                r.meta_parse(&format!("adam.{name}.lr"))?,
                width,
                r.meta_parse(&format!("adam.{name}.step"))?,
                m,
                v,
            )
            .map_err(|e| r.err(e.to_string()))?;
            adam.push_state(state);
        }
        let stats = DensificationStats {
            grad_norm_sum: r.f64s("stats.grad_norm_sum", n)?,
            visible_count: r.u32s("stats.visible_count", n)?,
            max_screen_radius: r.u32s("stats.max_screen_radius", n)?,
        };
        let model = GaussianModel {
            scene,
            active_sh_degree: r.meta_parse("active_sh_degree")?,
            adam,
            stats,
        };
        model
            .check_consistency()
            .map_err(|e| r.err(e.to_string()))?;
        Ok(GeometryCheckpoint {
            step: r.meta_parse("step")?,
            model,
            view_stack: r.u64s("view_stack")?,
            ema_loss: r.meta_parse("ema_loss")?,
            ema_psnr: r.meta_parse("ema_psnr")?,
            seed: r.meta_parse("seed")?,
            extent: r.meta_parse("extent")?,
            config_json: r.meta_str("config")?.to_string(),
        })
    }
}

fn rows3(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Validating access to a checkpoint's tensors and metadata.
struct Reader<'a> {
    st: SafeTensors<'a>,
    meta: HashMap<String, String>,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], path: &'a Path) -> Result<Self, TrainError> {
        let st = SafeTensors::deserialize(bytes).map_err(|e| TrainError::Checkpoint {
            path: path.to_path_buf(),
            message: format!("not a safetensors file: {e}"),
        })?;
        let meta = SafeTensors::read_metadata(bytes)
            .ok()
            .and_then(|(_, m)| m.metadata().clone())
            .unwrap_or_default();
        Ok(Reader { st, meta, path })
    }

    fn err(&self, message: String) -> TrainError {
        TrainError::Checkpoint {
            path: self.path.to_path_buf(),
            message,
        }
    }

    fn meta_str(&self, key: &str) -> Result<&str, TrainError> {
        self.meta
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| self.err(format!("metadata entry `{key}` is missing")))
    }

    fn meta_parse<V: std::str::FromStr>(&self, key: &str) -> Result<V, TrainError> {
        let s = self.meta_str(key)?;
        s.parse()
            .map_err(|_| self.err(format!("metadata entry `{key}` = `{s}` is malformed")))
    }

    fn raw(
        &self,
        name: &str,
        dtype: Dtype,
        shape: &[Option<usize>],
    ) -> Result<&'a [u8], TrainError> {
        let t = self
            .st
            .tensor(name)
            .map_err(|_| self.err(format!("tensor `{name}` is missing")))?;
        let ok_shape = t.shape().len() == shape.len()
            && t.shape()
                .iter()
                .zip(shape)
                .all(|(&a, b)| b.is_none_or(|b| a == b));
        if t.dtype() != dtype || !ok_shape {
            return Err(self.err(format!(
                "tensor `{name}` is {:?} {:?}, expected {dtype:?} {shape:?}",
                t.dtype(),
                t.shape()
            )));
        }
        Ok(t.data())
    }

    fn f32s(&self, name: &str, shape: &[Option<usize>]) -> Result<Vec<f32>, TrainError> {
        Ok(self
            .raw(name, Dtype::F32, shape)?
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn f64s(&self, name: &str, n: usize) -> Result<Vec<f64>, TrainError> {
        Ok(self
            .raw(name, Dtype::F64, &[Some(n)])?
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect())
    }

    fn u32s(&self, name: &str, n: usize) -> Result<Vec<u32>, TrainError> {
        Ok(self
            .raw(name, Dtype::U32, &[Some(n)])?
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn u64s(&self, name: &str) -> Result<Vec<usize>, TrainError> {
        Ok(self
            .raw(name, Dtype::U64, &[None])?
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")) as usize)
            .collect())
    }
}

/// Safetensors state files of the style stages and the bake: tensors plus string metadata, written with
/// [`base::write_atomic`]. Floating-point metadata uses Rust's shortest round-trip form.
pub(crate) struct StateWriter {
    tensors: Vec<(String, Dtype, Vec<usize>, Vec<u8>)>,
    meta: HashMap<String, String>,
}

impl StateWriter {
    pub(crate) fn new(format: &str) -> Self {
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), format.to_string());
        StateWriter {
            tensors: Vec::new(),
            meta,
        }
    }

    pub(crate) fn meta(&mut self, key: &str, value: impl ToString) {
        self.meta.insert(key.to_string(), value.to_string());
    }

    pub(crate) fn f32s(&mut self, name: &str, shape: Vec<usize>, v: &[f32]) {
        let bytes = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        self.tensors
            .push((name.to_string(), Dtype::F32, shape, bytes));
    }

    pub(crate) fn bytes(&mut self, name: &str, v: Vec<u8>) {
        self.tensors
            .push((name.to_string(), Dtype::U8, vec![v.len()], v));
    }

    /// Running averages shown by the progress display, comma-separated.
    pub(crate) fn ema(&mut self, ema: Option<&[f64]>) {
        if let Some(e) = ema {
            let v: Vec<String> = e.iter().map(f64::to_string).collect();
            self.meta("ema", v.join(","));
        }
    }

    /// The optimiser: hyper-parameters, per-tensor names, learning rates, step counts and widths
    /// as metadata, moments as `adam.{name}.exp_avg` / `adam.{name}.exp_avg_sq`.
    pub(crate) fn adam(&mut self, adam: &Adam<f32>) {
        self.meta("adam.beta1", adam.config.beta1);
        self.meta("adam.beta2", adam.config.beta2);
        self.meta("adam.eps", adam.config.eps);
        let names: Vec<&str> = adam.params().iter().map(|p| p.name.as_str()).collect();
        self.meta("adam.groups", names.join(","));
        for p in adam.params() {
            self.meta(&format!("adam.{}.lr", p.name), p.lr);
            self.meta(&format!("adam.{}.step", p.name), p.step_count());
            self.meta(&format!("adam.{}.width", p.name), p.width());
            let shape = vec![p.rows(), p.width()];
            self.f32s(
                &format!("adam.{}.exp_avg", p.name),
                shape.clone(),
                p.exp_avg(),
            );
            self.f32s(
                &format!("adam.{}.exp_avg_sq", p.name),
                shape,
                p.exp_avg_sq(),
            );
        }
    }

    pub(crate) fn finish(self) -> Result<Vec<u8>, TrainError> {
        let views = self
            .tensors
            .iter()
            .map(|(name, dtype, shape, bytes)| {
                safetensors::tensor::TensorView::new(*dtype, shape.clone(), bytes)
                    .map(|v| (name.clone(), v))
                    .map_err(|error| TrainError::Tensor {
                        what: format!("state tensor {name}"),
                        error,
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        nets::weights_file::serialize_canonical(views, self.meta).map_err(|problem| {
            TrainError::Serialize {
                what: "the state",
                problem,
            }
        })
    }
}

/// Validating access to a file written by [`StateWriter`]; errors name the file.
pub(crate) struct StateReader<'a> {
    st: SafeTensors<'a>,
    meta: HashMap<String, String>,
    path: &'a Path,
}

impl<'a> StateReader<'a> {
    pub(crate) fn new(bytes: &'a [u8], path: &'a Path, format: &str) -> Result<Self, TrainError> {
        let err = |message: String| TrainError::Checkpoint {
            path: path.to_path_buf(),
            message,
        };
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| err(format!("not a safetensors file: {e}")))?;
        let meta = SafeTensors::read_metadata(bytes)
            .ok()
            .and_then(|(_, m)| m.metadata().clone())
            .unwrap_or_default();
        let r = StateReader { st, meta, path };
        let found = r.meta_str("format")?;
        if found != format {
            return Err(err(format!("format `{found}`, expected `{format}`")));
        }
        Ok(r)
    }

    pub(crate) fn err(&self, message: String) -> TrainError {
        TrainError::Checkpoint {
            path: self.path.to_path_buf(),
            message,
        }
    }

    pub(crate) fn meta_str(&self, key: &str) -> Result<&str, TrainError> {
        self.meta
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| self.err(format!("metadata entry `{key}` is missing")))
    }

    /// Whether the metadata has an entry `key`.
    pub(crate) fn has_meta(&self, key: &str) -> bool {
        self.meta.contains_key(key)
    }

    pub(crate) fn meta_parse<V: std::str::FromStr>(&self, key: &str) -> Result<V, TrainError> {
        let s = self.meta_str(key)?;
        s.parse()
            .map_err(|_| self.err(format!("metadata entry `{key}` = `{s}` is malformed")))
    }

    /// The running averages written by [`StateWriter::ema`], which must have `n` values.
    pub(crate) fn ema<const N: usize>(&self) -> Result<Option<[f64; N]>, TrainError> {
        let Some(s) = self.meta.get("ema") else {
            return Ok(None);
        };
        let bad = || self.err(format!("metadata entry `ema` = `{s}` is malformed"));
        let v: Vec<f64> = s
            .split(',')
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        let a: [f64; N] = v.try_into().map_err(|_| bad())?;
        Ok(Some(a))
    }

    fn raw(&self, name: &str, dtype: Dtype) -> Result<(Vec<usize>, &'a [u8]), TrainError> {
        let t = self
            .st
            .tensor(name)
            .map_err(|_| self.err(format!("tensor `{name}` is missing")))?;
        if t.dtype() != dtype {
            return Err(self.err(format!(
                "tensor `{name}` is {:?}, expected {dtype:?}",
                t.dtype()
            )));
        }
        Ok((t.shape().to_vec(), t.data()))
    }

    pub(crate) fn bytes(&self, name: &str) -> Result<&'a [u8], TrainError> {
        Ok(self.raw(name, Dtype::U8)?.1)
    }

    /// An `f32` tensor whose shape must be `shape`.
    pub(crate) fn f32s(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, TrainError> {
        let (found, data) = self.raw(name, Dtype::F32)?;
        if found != shape {
            return Err(self.err(format!(
                "tensor `{name}` has shape {found:?}, expected {shape:?}"
            )));
        }
        Ok(data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    /// The optimiser written by [`StateWriter::adam`]; `config` must match the stored
    /// hyper-parameters.
    pub(crate) fn adam(&self, config: AdamConfig) -> Result<Adam<f32>, TrainError> {
        let stored = AdamConfig {
            beta1: self.meta_parse("adam.beta1")?,
            beta2: self.meta_parse("adam.beta2")?,
            eps: self.meta_parse("adam.eps")?,
        };
        if stored != config {
            return Err(self.err(format!(
                "the optimiser ran with {stored:?}, the configuration asks for {config:?}"
            )));
        }
        let mut adam = Adam::new(stored);
        for name in self.meta_str("adam.groups")?.split(',') {
            let width: usize = self.meta_parse(&format!("adam.{name}.width"))?;
            let (shape, _) = self.raw(&format!("adam.{name}.exp_avg"), Dtype::F32)?;
            let rows = shape.first().copied().unwrap_or(0);
            let m = self.f32s(&format!("adam.{name}.exp_avg"), &[rows, width])?;
            let v = self.f32s(&format!("adam.{name}.exp_avg_sq"), &[rows, width])?;
            let state = ParamState::from_parts(
                name,
                self.meta_parse(&format!("adam.{name}.lr"))?,
                width,
                self.meta_parse(&format!("adam.{name}.step"))?,
                m,
                v,
            )
            .map_err(|e| self.err(e.to_string()))?;
            adam.push_state(state);
        }
        Ok(adam)
    }
}
