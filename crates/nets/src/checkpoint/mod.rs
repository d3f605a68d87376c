//! Import of PyTorch checkpoints (`torch.save` state dicts) into a [`StateDict`], in pure safe
//! Rust, without Python.
//!
//! Both on-disk formats are read, told apart by their first bytes:
//! * the zip format of PyTorch >= 1.6 (`PK\x03\x04`), read by the `zip` module;
//! * the legacy format (a pickle, `0x80`), read by the `legacy` module.
//!
//! The pickles are run by a restricted virtual machine (the `pickle` module) that knows only the
//! opcodes and globals that state dicts use; nothing is imported or executed. Tensors are rebuilt
//! from `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ..)` with offset and
//! strides honoured, and materialised contiguous and row-major (the `tensor` module).
//!
//! Which tensors come out, and under which names:
//! * The unpickled object must be a dict: a state dict (`OrderedDict`) or a plain dict.
//! * Wrapper: if that dict holds no tensor directly and has one of the [`WRAPPER_KEYS`] (tried
//!   in order) with a dict value, that inner dict is the state dict and everything else (epoch
//!   counters, optimiser state) is ignored. `{'model': state_dict, 'epoch': 20}` loads as
//!   `state_dict`.
//! * Nested dicts are flattened with dotted names: `{'enc': {'0.weight': t}}` gives
//!   `enc.0.weight`. Integer keys are written in decimal.
//! * Tensors of float32, float64, float16 and bfloat16 storages become `f32` (float64 rounded to
//!   nearest, the others exact). Integer and bool tensors (such as BatchNorm's
//!   `num_batches_tracked`) and non-tensor values (numbers, strings, lists) are skipped.
//!
//! Errors name the byte offset (counted from the start of the file, also inside zip entries),
//! the storage key or the tensor. Memory stays proportional to the file size: the file is read
//! once, storages are borrowed from its bytes after their sizes are checked against it, the
//! pickle machine has fixed limits, and all tensors together may materialise at most
//! [`EXPANSION_LIMIT`] elements per stored element (overlapping views of one storage, such as
//! tied weights, count once per view).

mod error;
mod legacy;
pub(crate) mod pickle;
mod tensor;
mod zip;

use std::collections::HashMap;
use std::path::Path;
use std::rc::Rc;

pub use error::{CheckpointError, FormatError};

use crate::state_dict::StateDict;
use pickle::{Arena, Pickle, TensorRef, Value};
use tensor::StorageBytes;

/// Keys under which a checkpoint may wrap its state dict, in the order they are tried.
pub const WRAPPER_KEYS: [&str; 4] = ["state_dict", "model_state_dict", "model", "net"];

/// Most elements all tensors together may materialise, per element stored in the file.
pub const EXPANSION_LIMIT: u64 = 4;

/// Deepest dict nesting that is flattened.
const MAX_NESTING: usize = 32;

/// Longest flattened tensor name, in bytes.
const MAX_NAME_LEN: usize = 4096;

/// Reads the PyTorch checkpoint at `path` (zip or legacy format).
pub fn load_checkpoint(path: &Path) -> Result<StateDict, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|error| CheckpointError::Io {
        path: path.to_owned(),
        error,
    })?;
    load_checkpoint_bytes(&bytes).map_err(|problem| CheckpointError::Invalid {
        path: path.to_owned(),
        problem,
    })
}

/// Reads a PyTorch checkpoint (zip or legacy format) held in memory.
pub fn load_checkpoint_bytes(bytes: &[u8]) -> Result<StateDict, FormatError> {
    let (pickle, storages) = if bytes.starts_with(b"PK\x03\x04") {
        zip::load(bytes)?
    } else if bytes.first() == Some(&0x80) {
        legacy::load(bytes)?
    } else {
        return Err(FormatError::UnknownFormat {
            found: bytes[..bytes.len().min(4)].to_vec(),
        });
    };
    build_state_dict(&pickle, &storages)
}

/// Names every float tensor of the unpickled object and materialises it.
fn build_state_dict(
    pickle: &Pickle,
    storages: &HashMap<String, StorageBytes>,
) -> Result<StateDict, FormatError> {
    let arena = &pickle.arena;
    let Value::Dict(root) = pickle.root else {
        return Err(FormatError::Layout {
            reason: format!(
                "the checkpoint holds {}, not a dict",
                pickle.root.describe()
            ),
        });
    };
    let root = unwrap(arena, root);
    let mut named = Vec::new();
    let mut visited = vec![false; arena.dicts.len()];
    flatten(arena, root, "", 0, &mut visited, &mut named)?;

    // Every declared storage must be present, even those of skipped tensors.
    for key in pickle.storages.keys() {
        if !storages.contains_key(key) {
            return Err(FormatError::MissingStorage { key: key.clone() });
        }
    }
    let stored: u64 = storages
        .values()
        .map(|s| s.bytes.len() as u64 / s.dtype.size())
        .sum();
    let mut budget = stored.saturating_mul(EXPANSION_LIMIT);

    let mut out = StateDict::new();
    for (name, t) in named {
        if !t.storage.dtype.is_float() {
            continue;
        }
        let storage = storages
            .get(&t.storage.key)
            .ok_or_else(|| FormatError::MissingStorage {
                key: t.storage.key.clone(),
            })?;
        let tensor = tensor::materialise(&name, &t, storage, &mut budget)?;
        if out.insert(name.clone(), tensor).is_some() {
            return Err(FormatError::Layout {
                reason: format!("two tensors are both named {name}"),
            });
        }
    }
    Ok(out)
}

/// The state dict inside a wrapper dict, or the dict itself.
fn unwrap(arena: &Arena, dict: usize) -> usize {
    let d = &arena.dicts[dict];
    if d.entries.iter().any(|(_, v)| matches!(v, Value::Tensor(_))) {
        return dict;
    }
    WRAPPER_KEYS
        .iter()
        .find_map(|k| match d.get_str(k) {
            Some(Value::Dict(inner)) => Some(*inner),
            _ => None,
        })
        .unwrap_or(dict)
}

/// Collects the tensors of `dict` and its nested dicts, named with dotted paths.
///
/// Each dict is flattened once: one reached a second time (a dict shared by two keys, or
/// containing itself) is an error, so the work and the names stay proportional to the pickle.
fn flatten(
    arena: &Arena,
    dict: usize,
    prefix: &str,
    depth: usize,
    visited: &mut [bool],
    out: &mut Vec<(String, Rc<TensorRef>)>,
) -> Result<(), FormatError> {
    let layout = |reason: String| FormatError::Layout { reason };
    let here = if prefix.is_empty() {
        "the top level"
    } else {
        prefix
    };
    if depth > MAX_NESTING {
        return Err(layout(format!(
            "dicts nested deeper than {MAX_NESTING} levels at {here}"
        )));
    }
    if std::mem::replace(&mut visited[dict], true) {
        return Err(layout(format!(
            "the dict at {here} also appears elsewhere in the checkpoint"
        )));
    }
    for (key, value) in &arena.dicts[dict].entries {
        let name = if prefix.is_empty() {
            key.to_string()
        } else {
            format!("{prefix}.{key}")
        };
        if name.len() > MAX_NAME_LEN {
            return Err(layout(format!(
                "a tensor name is longer than {MAX_NAME_LEN} bytes"
            )));
        }
        match value {
            Value::Tensor(t) => out.push((name, t.clone())),
            Value::Dict(inner) => flatten(arena, *inner, &name, depth + 1, visited, out)?,
            _ => {}
        }
    }
    Ok(())
}
