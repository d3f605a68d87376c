//! Recognising the weight layouts of a state dict and reading its layers with shape checks.
//!
//! Three layouts are understood; the layer names they map to are the canonical ones
//! (`conv0` for the encoder's 1x1 input conv, `conv{K}_{J}` for the J-th 3x3 conv of relu level K;
//! a decoder conv carries the name of the encoder conv it mirrors, so decoder `conv{K}_{J}` maps the
//! output width of encoder `conv{K}_{J}` back to its input width):
//!
//! * **Sequential** (the public AdaIN and WCT files): keys `{i}.weight` / `{i}.bias` where `i` is
//!   the index in an `nn.Sequential`. Encoder: the 1x1 conv at 0, then blocks of (reflection pad,
//!   conv, ReLU), so consecutive convs are 3 indices apart, or 4 when a max-pool sits between them
//!   (which starts the next level); the first 3x3 conv is at index 2. Decoder: the first conv at 1,
//!   consecutive convs 3 apart, or 4 when an upsampling sits between them. Max-pools round up
//!   (`ceil_mode=True`); the last decoder conv has no ReLU.
//! * **Named** (the 16x-compressed `4SE`/`4SD` pair): keys `conv0`, `conv{K}{J}` (one digit each);
//!   `*_aux` tensors are ignored. Max-pools round down; the decoder has a ReLU after its last conv.
//! * **Canonical** (this crate's safetensors files): keys `conv0`, `conv{K}_{J}`; the pooling
//!   rounding and final ReLU come from the file's metadata.
//!
//! A `model.` prefix on every key (a `{'model': state_dict}` wrapper flattened by an importer) is
//! removed first.

use std::collections::BTreeSet;

use base::Real;
use ndarray::{Array1, Array4};

use crate::error::NetError;
use crate::layer::ConvLayer;
use crate::pool::PoolRounding;
use crate::state_dict::StateDict;

/// The key families a state dict may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// `nn.Sequential` indices (`0.weight`, `2.weight`, ...).
    Sequential,
    /// Named layers of the compressed pair (`conv0`, `conv11`, ..., `*_aux` ignored).
    Named,
    /// Canonical names (`conv0`, `conv1_1`, ...).
    Canonical,
}

/// A layer to read: its canonical name and its key prefix in the state dict.
#[derive(Clone, Debug)]
pub(crate) struct LayerRef {
    pub(crate) name: String,
    pub(crate) source: String,
}

/// The structure of an encoder found in a state dict.
pub(crate) struct EncoderSpec {
    pub(crate) input: LayerRef,
    /// `levels[k-1]` = the 3x3 convs of relu level `k`, in order.
    pub(crate) levels: Vec<Vec<LayerRef>>,
    pub(crate) pool: PoolRounding,
}

/// The structure of a decoder found in a state dict.
pub(crate) struct DecoderSpec {
    /// Deepest level first; an upsampling sits between consecutive levels.
    pub(crate) levels: Vec<Vec<LayerRef>>,
    pub(crate) final_relu: bool,
}

/// Layer key prefixes (`{prefix}.weight`), with a common `model.` prefix removed.
fn prefixes(sd: &StateDict) -> Result<(String, BTreeSet<String>), NetError> {
    if sd.is_empty() {
        return Err(NetError::Layout("the state dict is empty".into()));
    }
    let strip = if sd.keys().all(|k| k.starts_with("model.")) {
        "model."
    } else {
        ""
    };
    let mut set = BTreeSet::new();
    for key in sd.keys() {
        let k = &key[strip.len()..];
        let p = k
            .strip_suffix(".weight")
            .or_else(|| k.strip_suffix(".bias"))
            .ok_or_else(|| {
                NetError::Layout(format!("key `{key}` is neither a `.weight` nor a `.bias`"))
            })?;
        set.insert(p.to_string());
    }
    Ok((strip.to_string(), set))
}

fn parse_named(p: &str) -> Option<(usize, usize)> {
    let d = p.strip_prefix("conv")?;
    if d.len() == 2 && d.bytes().all(|b| b.is_ascii_digit()) {
        let b = d.as_bytes();
        Some(((b[0] - b'0') as usize, (b[1] - b'0') as usize))
    } else {
        None
    }
}

fn parse_canonical(p: &str) -> Option<(usize, usize)> {
    let (k, j) = p.strip_prefix("conv")?.split_once('_')?;
    Some((k.parse().ok()?, j.parse().ok()?))
}

/// Which layout a state dict uses.
pub fn detect_layout(sd: &StateDict) -> Result<Layout, NetError> {
    let (_, ps) = prefixes(sd)?;
    if ps.iter().all(|p| p.parse::<usize>().is_ok()) {
        return Ok(Layout::Sequential);
    }
    let relevant: Vec<&String> = ps.iter().filter(|p| !p.ends_with("_aux")).collect();
    if relevant
        .iter()
        .all(|p| p.as_str() == "conv0" || parse_named(p).is_some())
    {
        return Ok(Layout::Named);
    }
    if relevant
        .iter()
        .all(|p| p.as_str() == "conv0" || parse_canonical(p).is_some())
    {
        return Ok(Layout::Canonical);
    }
    let odd = relevant
        .iter()
        .find(|p| {
            p.parse::<usize>().is_err()
                && p.as_str() != "conv0"
                && parse_named(p).is_none()
                && parse_canonical(p).is_none()
        })
        .map_or("?", |p| p.as_str());
    Err(NetError::Layout(format!(
        "unknown layout: layer `{odd}` fits neither Sequential indices (`0`, `2`, ...), \
         compressed names (`conv11`) nor canonical names (`conv1_1`)"
    )))
}

fn layer(strip: &str, name: String, source: &str) -> LayerRef {
    LayerRef {
        name,
        source: format!("{strip}{source}"),
    }
}

/// Groups sorted Sequential indices into runs separated by gaps of 4 (a pool or an upsampling).
fn sequential_groups(idx: &[usize], what: &str) -> Result<Vec<Vec<usize>>, NetError> {
    let mut groups: Vec<Vec<usize>> = vec![vec![idx[0]]];
    for w in idx.windows(2) {
        match w[1] - w[0] {
            3 => groups.last_mut().expect("non-empty").push(w[1]),
            4 => groups.push(vec![w[1]]),
            gap => {
                return Err(NetError::Layout(format!(
                    "{what}: convs at Sequential indices {} and {} are {gap} apart (expected 3, \
                     or 4 across a pool/upsampling)",
                    w[0], w[1]
                )))
            }
        }
    }
    Ok(groups)
}

/// A conv of the named layouts: level `K`, index `J` within the level, key prefix.
type Numbered = (usize, usize, String);

/// Numbered levels from `(K, J)` pairs: requires K = 1..L and J = 1..n within each level.
fn named_levels(pairs: &[Numbered], what: &str) -> Result<Vec<Vec<Numbered>>, NetError> {
    let mut levels: Vec<Vec<Numbered>> = Vec::new();
    let mut sorted = pairs.to_vec();
    sorted.sort();
    for (k, j, p) in sorted {
        if k == levels.len() + 1 && j == 1 {
            levels.push(vec![(k, j, p)]);
        } else if k >= 1 && k == levels.len() && j == levels[k - 1].len() + 1 {
            levels[k - 1].push((k, j, p));
        } else {
            return Err(NetError::Layout(format!(
                "{what}: layer `{p}` breaks the level numbering (levels must run 1, 2, ... and \
                 convs within a level 1, 2, ...)"
            )));
        }
    }
    if levels.is_empty() {
        return Err(NetError::Layout(format!("{what}: no 3x3 conv layers")));
    }
    Ok(levels)
}

/// Finds the encoder structure. `canonical_pool` is the pooling rounding for the canonical layout
/// (which stores it in file metadata); other layouts imply it.
pub(crate) fn encoder_spec(
    sd: &StateDict,
    canonical_pool: Option<PoolRounding>,
) -> Result<EncoderSpec, NetError> {
    let what = "encoder";
    let layout = detect_layout(sd)?;
    let (strip, ps) = prefixes(sd)?;
    match layout {
        Layout::Sequential => {
            let mut idx: Vec<usize> = ps.iter().map(|p| p.parse().expect("checked")).collect();
            idx.sort_unstable();
            if idx[0] != 0 {
                return Err(NetError::MissingTensor {
                    name: format!("{strip}0.weight"),
                });
            }
            if idx.len() < 2 || idx[1] != 2 {
                return Err(NetError::Layout(format!(
                    "{what}: expected the first 3x3 conv at Sequential index 2"
                )));
            }
            let groups = sequential_groups(&idx[1..], what)?;
            let levels = groups
                .iter()
                .enumerate()
                .map(|(k, g)| {
                    g.iter()
                        .enumerate()
                        .map(|(j, i)| {
                            layer(&strip, format!("conv{}_{}", k + 1, j + 1), &i.to_string())
                        })
                        .collect()
                })
                .collect();
            Ok(EncoderSpec {
                input: layer(&strip, "conv0".into(), "0"),
                levels,
                pool: PoolRounding::Ceil,
            })
        }
        Layout::Named | Layout::Canonical => {
            let parse = if layout == Layout::Named {
                parse_named
            } else {
                parse_canonical
            };
            if !ps.contains("conv0") {
                return Err(NetError::MissingTensor {
                    name: format!("{strip}conv0.weight"),
                });
            }
            let pairs: Vec<Numbered> = ps
                .iter()
                .filter(|p| !p.ends_with("_aux") && p.as_str() != "conv0")
                .map(|p| {
                    let (k, j) = parse(p).expect("checked by detect_layout");
                    (k, j, p.clone())
                })
                .collect();
            let levels = named_levels(&pairs, what)?
                .into_iter()
                .map(|lv| {
                    lv.into_iter()
                        .map(|(k, j, p)| layer(&strip, format!("conv{k}_{j}"), &p))
                        .collect()
                })
                .collect();
            let pool = if layout == Layout::Named {
                PoolRounding::Floor
            } else {
                canonical_pool.ok_or_else(|| {
                    NetError::Layout(
                        "canonical layer names carry no pooling rounding; load canonical weights \
                         with `NetWeights::load`, which reads it from the file metadata"
                            .into(),
                    )
                })?
            };
            Ok(EncoderSpec {
                input: layer(&strip, "conv0".into(), "conv0"),
                levels,
                pool,
            })
        }
    }
}

/// Finds the decoder structure. `canonical_final_relu` is the final-ReLU flag for the canonical
/// layout (stored in file metadata); other layouts imply it.
pub(crate) fn decoder_spec(
    sd: &StateDict,
    canonical_final_relu: Option<bool>,
) -> Result<DecoderSpec, NetError> {
    let what = "decoder";
    let layout = detect_layout(sd)?;
    let (strip, ps) = prefixes(sd)?;
    match layout {
        Layout::Sequential => {
            let mut idx: Vec<usize> = ps.iter().map(|p| p.parse().expect("checked")).collect();
            idx.sort_unstable();
            if idx[0] != 1 {
                return Err(NetError::Layout(format!(
                    "{what}: expected the first conv at Sequential index 1 (after a reflection \
                     pad), found index {}",
                    idx[0]
                )));
            }
            let groups = sequential_groups(&idx, what)?;
            let depth = groups.len();
            let levels = groups
                .iter()
                .enumerate()
                .map(|(g, idxs)| {
                    let level = depth - g;
                    let n = idxs.len();
                    idxs.iter()
                        .enumerate()
                        .map(|(j, i)| {
                            layer(&strip, format!("conv{level}_{}", n - j), &i.to_string())
                        })
                        .collect()
                })
                .collect();
            Ok(DecoderSpec {
                levels,
                final_relu: false,
            })
        }
        Layout::Named | Layout::Canonical => {
            let parse = if layout == Layout::Named {
                parse_named
            } else {
                parse_canonical
            };
            if ps.contains("conv0") {
                return Err(NetError::Layout(format!(
                    "{what}: found `conv0`, the encoder's input conv (is this an encoder?)"
                )));
            }
            let pairs: Vec<Numbered> = ps
                .iter()
                .filter(|p| !p.ends_with("_aux"))
                .map(|p| {
                    let (k, j) = parse(p).expect("checked by detect_layout");
                    (k, j, p.clone())
                })
                .collect();
            let mut levels: Vec<Vec<LayerRef>> = named_levels(&pairs, what)?
                .into_iter()
                .map(|lv| {
                    lv.into_iter()
                        .rev()
                        .map(|(k, j, p)| layer(&strip, format!("conv{k}_{j}"), &p))
                        .collect()
                })
                .collect();
            levels.reverse();
            let final_relu = if layout == Layout::Named {
                true
            } else {
                canonical_final_relu.ok_or_else(|| {
                    NetError::Layout(
                        "canonical layer names carry no final-ReLU flag; load canonical weights \
                         with `NetWeights::load`, which reads it from the file metadata"
                            .into(),
                    )
                })?
            };
            Ok(DecoderSpec { levels, final_relu })
        }
    }
}

/// Reads one conv layer: `{source}.weight` of shape `[O, in_channels, kernel, kernel]` (any `O`
/// and, when `in_channels` is `None`, any input width) and `{source}.bias` of shape `[O]`.
pub(crate) fn read_conv<T: Real>(
    sd: &StateDict,
    r: &LayerRef,
    kernel: usize,
    in_channels: Option<usize>,
) -> Result<ConvLayer<T>, NetError> {
    let wname = format!("{}.weight", r.source);
    let bname = format!("{}.bias", r.source);
    let w = sd.get(&wname).ok_or_else(|| NetError::MissingTensor {
        name: wname.clone(),
    })?;
    let b = sd.get(&bname).ok_or_else(|| NetError::MissingTensor {
        name: bname.clone(),
    })?;
    let ok = w.shape.len() == 4
        && w.shape[0] > 0
        && w.shape[2] == kernel
        && w.shape[3] == kernel
        && in_channels.is_none_or(|c| w.shape[1] == c);
    if !ok {
        let cin = in_channels.map_or("C".to_string(), |c| c.to_string());
        return Err(NetError::TensorShape {
            name: wname,
            found: w.shape.clone(),
            expected: format!("[O, {cin}, {kernel}, {kernel}] for {}", r.name),
        });
    }
    if b.shape != [w.shape[0]] {
        return Err(NetError::TensorShape {
            name: bname,
            found: b.shape.clone(),
            expected: format!("[{}]", w.shape[0]),
        });
    }
    let dims = (w.shape[0], w.shape[1], kernel, kernel);
    let data = w.data.iter().map(|&v| T::lit(v as f64)).collect();
    let weight = Array4::from_shape_vec(dims, data).map_err(|_| NetError::TensorShape {
        name: wname.clone(),
        found: w.shape.clone(),
        expected: format!("{} elements", dims.0 * dims.1 * kernel * kernel),
    })?;
    if b.data.len() != w.shape[0] {
        return Err(NetError::TensorShape {
            name: bname,
            found: vec![b.data.len()],
            expected: format!("[{}] elements", w.shape[0]),
        });
    }
    let bias = Array1::from_iter(b.data.iter().map(|&v| T::lit(v as f64)));
    Ok(ConvLayer {
        name: r.name.clone(),
        source: r.source.clone(),
        weight,
        bias,
    })
}
