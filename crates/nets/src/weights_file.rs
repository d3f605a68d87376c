//! The canonical weights file: safetensors, `f32`, with documented tensor names and metadata.
//!
//! Tensor names (weights OIHW, biases `[O]`):
//! * `encoder.conv0.{weight,bias}`: the 1x1 input conv;
//! * `encoder.conv{K}_{J}.{weight,bias}`: the J-th 3x3 conv of relu level K (`conv1_1`, `conv1_2`,
//!   `conv2_1`, ..., up to `conv{depth}_1`);
//! * `decoder.conv{K}_{J}.{weight,bias}`: the decoder conv mirroring encoder `conv{K}_{J}`
//!   (run from the deepest level down: `conv4_1`, `conv3_4`, ..., `conv1_1`);
//! * `lifter.{weight,bias}`: the lifter's 1x1 conv `[C, F, 1, 1]`.
//!
//! Metadata (`__metadata__`, all strings): `format` = `dsgs-nets`, `format_version` = `1`, and for
//! each network present:
//! * `encoder.depth`, `encoder.in_channels`, `encoder.widths` (comma-separated channels of
//!   `relu{k}_1`), `encoder.convs_per_level` (comma-separated), `encoder.pool` (`ceil`/`floor`);
//! * `decoder.depth`, `decoder.in_channels`, `decoder.out_channels`, `decoder.convs_per_level`
//!   (deepest level first), `decoder.final_relu` (`true`/`false`), `decoder.kernel` (`1`, written
//!   only for a pointwise decoder, [`Decoder::pointwise`]; without it the convs are 3x3);
//! * `lifter.in_channels`, `lifter.out_channels`.
//!
//! Loading checks the metadata against the tensors and names the offending entry on mismatch.
//! Equal contents give equal bytes: [`serialize_canonical`] writes the header's keys in sorted
//! order (the `safetensors` crate writes its metadata map in hash order, which differs between
//! processes). Every safetensors file of dsgs (weights, checkpoints) is written through it.
//! Saving writes a temporary file in the target directory and renames it, so a reader never sees a
//! partial file. The resolution variant (standard/fullres) is a way of running the weights, not a
//! property of them, and is not stored.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

use crate::decoder::Decoder;
use crate::encoder::Encoder;
use crate::error::NetError;
use crate::layer::ConvLayer;
use crate::layout::{decoder_spec, encoder_spec};
use crate::lifter::Lifter;
use crate::pool::PoolRounding;
use crate::state_dict::{sub_dict, StateDict, TensorF32};

/// `safetensors::serialize` with the header's keys and the metadata's keys in sorted order, so
/// that the same tensors and metadata always give the same bytes. The tensor data and their
/// offsets are those of `safetensors::serialize`; the header is padded with spaces to a multiple
/// of 8 bytes, as the format asks. Two tensors of one name are an error.
pub fn serialize_canonical(
    views: Vec<(String, TensorView<'_>)>,
    metadata: HashMap<String, String>,
) -> Result<Vec<u8>, String> {
    Ok(canonical(views, metadata)?.into_vec())
}

/// The bytes of [`serialize_canonical`] in two pieces, the header and the tensor data, so that
/// a file can take them in turn ([`Canonical::write_to`]) without a copy of the data that
/// joins them.
#[derive(Debug)]
pub struct Canonical {
    /// The header's length (8 bytes, little-endian) and its text.
    head: Vec<u8>,
    /// `safetensors::serialize`'s bytes, whose tensor data starts at `data_start`.
    serialized: Vec<u8>,
    data_start: usize,
}

impl Canonical {
    /// The tensor data: every tensor's bytes at the offsets the header gives.
    fn data(&self) -> &[u8] {
        &self.serialized[self.data_start..]
    }

    /// Writes the file's bytes to `out`.
    pub fn write_to(&self, out: &mut impl std::io::Write) -> std::io::Result<()> {
        out.write_all(&self.head)?;
        out.write_all(self.data())
    }

    /// The file's bytes in one buffer.
    pub fn into_vec(self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.head.len() + self.data().len());
        out.extend_from_slice(&self.head);
        out.extend_from_slice(self.data());
        out
    }
}

/// [`serialize_canonical`] in two pieces ([`Canonical`]).
pub fn canonical(
    views: Vec<(String, TensorView<'_>)>,
    metadata: HashMap<String, String>,
) -> Result<Canonical, String> {
    use std::collections::{BTreeMap, BTreeSet};
    let mut names = BTreeSet::new();
    if let Some((name, _)) = views.iter().find(|(name, _)| !names.insert(name.as_str())) {
        return Err(format!("two tensors are both named `{name}`"));
    }
    let serialized = safetensors::serialize(views, Some(metadata)).map_err(|e| e.to_string())?;
    let n = u64::from_le_bytes(serialized[..8].try_into().expect("8 bytes")) as usize;
    let header = &serialized[8..8 + n];
    let mut header: BTreeMap<String, serde_json::Value> =
        serde_json::from_slice(header).map_err(|e| e.to_string())?;
    if let Some(meta) = header.get_mut("__metadata__") {
        let sorted: BTreeMap<String, String> =
            serde_json::from_value(meta.take()).map_err(|e| e.to_string())?;
        *meta = serde_json::to_value(sorted).map_err(|e| e.to_string())?;
    }
    let mut text = serde_json::to_vec(&header).map_err(|e| e.to_string())?;
    text.resize(text.len().next_multiple_of(8), b' ');
    let mut head = Vec::with_capacity(8 + text.len());
    head.extend_from_slice(&(text.len() as u64).to_le_bytes());
    head.extend_from_slice(&text);
    Ok(Canonical {
        head,
        serialized,
        data_start: 8 + n,
    })
}

/// The `format` metadata value.
pub const FORMAT: &str = "dsgs-nets";
/// The `format_version` metadata value.
pub const FORMAT_VERSION: &str = "1";

/// A set of networks stored together (any of them may be absent).
#[derive(Clone, Debug, Default)]
pub struct NetWeights {
    /// The normalised VGG-19 encoder up to `relu{depth}_1` (tensors `encoder.*`), if stored.
    pub encoder: Option<Encoder>,
    /// The decoder from `relu{depth}_1` features back to an image (tensors `decoder.*`), if
    /// stored.
    pub decoder: Option<Decoder>,
    /// The lifter `relu(conv1x1(x))` from rasterized `F`-dimensional features to the encoder width
    /// (tensors `lifter.*`), if stored.
    pub lifter: Option<Lifter>,
}

fn join(v: &[usize]) -> String {
    v.iter().map(usize::to_string).collect::<Vec<_>>().join(",")
}

fn put_layer(sd: &mut StateDict, prefix: &str, l: &ConvLayer) {
    sd.insert(format!("{prefix}.weight"), TensorF32::from_array(&l.weight));
    sd.insert(format!("{prefix}.bias"), TensorF32::from_array(&l.bias));
}

impl NetWeights {
    /// The tensors under their canonical names.
    pub fn to_state_dict(&self) -> StateDict {
        let mut sd = StateDict::new();
        if let Some(e) = &self.encoder {
            for l in e.layers() {
                put_layer(&mut sd, &format!("encoder.{}", l.name), l);
            }
        }
        if let Some(d) = &self.decoder {
            for l in d.layers() {
                put_layer(&mut sd, &format!("decoder.{}", l.name), l);
            }
        }
        if let Some(l) = &self.lifter {
            put_layer(&mut sd, "lifter", l.layer());
        }
        sd
    }

    /// The metadata describing the networks present.
    pub fn metadata(&self) -> HashMap<String, String> {
        let mut m = HashMap::new();
        m.insert("format".into(), FORMAT.into());
        m.insert("format_version".into(), FORMAT_VERSION.into());
        if let Some(e) = &self.encoder {
            m.insert("encoder.depth".into(), e.depth().to_string());
            m.insert("encoder.in_channels".into(), e.in_channels().to_string());
            m.insert("encoder.widths".into(), join(&e.widths()));
            m.insert("encoder.convs_per_level".into(), join(&e.convs_per_level()));
            m.insert("encoder.pool".into(), e.pool_rounding().as_str().into());
        }
        if let Some(d) = &self.decoder {
            m.insert("decoder.depth".into(), d.depth().to_string());
            m.insert("decoder.in_channels".into(), d.in_channels().to_string());
            m.insert("decoder.out_channels".into(), d.out_channels().to_string());
            m.insert("decoder.convs_per_level".into(), join(&d.convs_per_level()));
            m.insert("decoder.final_relu".into(), d.final_relu().to_string());
            if d.is_pointwise() {
                m.insert("decoder.kernel".into(), d.kernel().to_string());
            }
        }
        if let Some(l) = &self.lifter {
            m.insert("lifter.in_channels".into(), l.in_channels().to_string());
            m.insert("lifter.out_channels".into(), l.out_channels().to_string());
        }
        m
    }

    /// Serialises to safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, NetError> {
        let sd = self.to_state_dict();
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = sd
            .iter()
            .map(|(k, t)| {
                let b = t.data.iter().flat_map(|v| v.to_le_bytes()).collect();
                (k.clone(), t.shape.clone(), b)
            })
            .collect();
        let views = bytes
            .iter()
            .map(|(k, shape, b)| {
                TensorView::new(Dtype::F32, shape.clone(), b)
                    .map(|v| (k.clone(), v))
                    .map_err(|e| NetError::Input(format!("tensor {k}: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        serialize_canonical(views, self.metadata())
            .map_err(|e| NetError::Input(format!("cannot serialise weights: {e}")))
    }

    /// Writes the file atomically ([`base::write_atomic`]).
    pub fn save(&self, path: &Path) -> Result<(), NetError> {
        let bytes = self.to_bytes()?;
        base::write_atomic(path, &bytes).map_err(|error| NetError::Io {
            path: path.to_path_buf(),
            error,
        })
    }

    /// Reads a file written by [`NetWeights::save`].
    pub fn load(path: &Path) -> Result<NetWeights, NetError> {
        let bytes = std::fs::read(path).map_err(|error| NetError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        NetWeights::from_bytes(&bytes).map_err(|e| match e {
            NetError::Io { .. } | NetError::File { .. } => e,
            other => NetError::File {
                path: path.to_path_buf(),
                detail: other.to_string(),
            },
        })
    }

    /// Parses safetensors bytes in the canonical format.
    pub fn from_bytes(bytes: &[u8]) -> Result<NetWeights, NetError> {
        let bad = |d: String| NetError::Input(d);
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let md = meta.metadata().clone().unwrap_or_default();
        let get = |k: &str| {
            md.get(k)
                .cloned()
                .ok_or_else(|| bad(format!("metadata entry `{k}` is missing")))
        };
        if get("format")? != FORMAT {
            return Err(bad(format!("metadata `format` is not `{FORMAT}`")));
        }
        let v = get("format_version")?;
        if v != FORMAT_VERSION {
            return Err(bad(format!("unsupported format_version {v}")));
        }
        let mut sd = StateDict::new();
        for (name, view) in st.tensors() {
            if view.dtype() != Dtype::F32 {
                return Err(bad(format!(
                    "tensor `{name}` has dtype {:?}, expected F32",
                    view.dtype()
                )));
            }
            let data = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect();
            sd.insert(
                name.clone(),
                TensorF32 {
                    shape: view.shape().to_vec(),
                    data,
                },
            );
        }
        let check = |key: &str, found: String| -> Result<(), NetError> {
            let want = get(key)?;
            if want != found {
                return Err(bad(format!(
                    "metadata `{key}` = {want} but the tensors give {found}"
                )));
            }
            Ok(())
        };
        let mut out = NetWeights::default();
        if md.contains_key("encoder.depth") {
            let pool = match get("encoder.pool")?.as_str() {
                "ceil" => PoolRounding::Ceil,
                "floor" => PoolRounding::Floor,
                other => return Err(bad(format!("metadata `encoder.pool` = {other}"))),
            };
            let esd = sub_dict(&sd, "encoder.");
            let e = Encoder::from_spec(&esd, encoder_spec(&esd, Some(pool))?)
                .map_err(|e| prefix_tensor(e, "encoder."))?;
            check("encoder.depth", e.depth().to_string())?;
            check("encoder.in_channels", e.in_channels().to_string())?;
            check("encoder.widths", join(&e.widths()))?;
            check("encoder.convs_per_level", join(&e.convs_per_level()))?;
            out.encoder = Some(e);
        }
        if md.contains_key("decoder.depth") {
            let final_relu = match get("decoder.final_relu")?.as_str() {
                "true" => true,
                "false" => false,
                other => return Err(bad(format!("metadata `decoder.final_relu` = {other}"))),
            };
            let kernel = match md.get("decoder.kernel").map(String::as_str) {
                None | Some("3") => 3,
                Some("1") => 1,
                Some(other) => {
                    return Err(bad(format!(
                        "metadata `decoder.kernel` = {other} (expected 3 or 1)"
                    )))
                }
            };
            let dsd = sub_dict(&sd, "decoder.");
            let d = Decoder::from_spec(&dsd, decoder_spec(&dsd, Some(final_relu))?, kernel)
                .map_err(|e| prefix_tensor(e, "decoder."))?;
            check("decoder.depth", d.depth().to_string())?;
            check("decoder.in_channels", d.in_channels().to_string())?;
            check("decoder.out_channels", d.out_channels().to_string())?;
            check("decoder.convs_per_level", join(&d.convs_per_level()))?;
            out.decoder = Some(d);
        }
        if md.contains_key("lifter.in_channels") {
            let l = Lifter::from_state_dict(&sub_dict(&sd, "lifter."))
                .map_err(|e| prefix_tensor(e, "lifter."))?;
            check("lifter.in_channels", l.in_channels().to_string())?;
            check("lifter.out_channels", l.out_channels().to_string())?;
            out.lifter = Some(l);
        }
        let known = |k: &str| {
            (out.encoder.is_some() && k.starts_with("encoder."))
                || (out.decoder.is_some() && k.starts_with("decoder."))
                || (out.lifter.is_some() && k.starts_with("lifter."))
        };
        if let Some(k) = sd.keys().find(|k| !known(k)) {
            return Err(bad(format!(
                "tensor `{k}` belongs to no network described by the metadata"
            )));
        }
        Ok(out)
    }
}

/// Puts the file-level prefix back on tensor names in an error.
fn prefix_tensor(e: NetError, prefix: &str) -> NetError {
    match e {
        NetError::MissingTensor { name } => NetError::MissingTensor {
            name: format!("{prefix}{name}"),
        },
        NetError::TensorShape {
            name,
            found,
            expected,
        } => NetError::TensorShape {
            name: format!("{prefix}{name}"),
            found,
            expected,
        },
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two files of the same tensors and metadata, the metadata maps filled in opposite orders
    /// (and each with its own hash seed): the same bytes, which read back to the same content.
    #[test]
    fn canonical_serialisation_is_independent_of_the_map_order() {
        let data: Vec<u8> = (0..24u8).collect();
        let keys: Vec<String> = (0..32).map(|i| format!("key{i:02}")).collect();
        let write = |order: &mut dyn Iterator<Item = &String>| {
            let meta: HashMap<String, String> =
                order.map(|k| (k.clone(), format!("v{k}"))).collect();
            let views = vec![
                (
                    "b".to_string(),
                    TensorView::new(Dtype::F32, vec![2, 2], &data[..16]).unwrap(),
                ),
                (
                    "a".to_string(),
                    TensorView::new(Dtype::U8, vec![8], &data[16..]).unwrap(),
                ),
            ];
            serialize_canonical(views, meta).unwrap()
        };
        let one = write(&mut keys.iter());
        let two = write(&mut keys.iter().rev());
        assert_eq!(one, two);
        let n = u64::from_le_bytes(one[..8].try_into().unwrap()) as usize;
        assert_eq!(n % 8, 0, "header not padded to 8 bytes");
        let st = SafeTensors::deserialize(&one).unwrap();
        assert_eq!(st.tensor("b").unwrap().data(), &data[..16]);
        assert_eq!(st.tensor("a").unwrap().data(), &data[16..]);
        let (_, meta) = SafeTensors::read_metadata(&one).unwrap();
        let meta = meta.metadata().clone().unwrap();
        assert_eq!(meta.len(), keys.len());
        assert!(keys.iter().all(|k| meta[k] == format!("v{k}")));
    }
}
