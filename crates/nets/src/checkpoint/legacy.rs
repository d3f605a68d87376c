//! The legacy checkpoint format (`torch.save(..., _use_new_zipfile_serialization=False)`, and
//! every `torch.save` before PyTorch 1.6).
//!
//! The file is five pickles back to back, then the storage bytes:
//! 1. the magic number `0x1950a86a20f9469cfc6c`;
//! 2. the protocol version `1001`;
//! 3. system info, a dict whose `little_endian` flag gives the byte order of the storages;
//! 4. the object itself, whose storages are persistent ids
//!    `('storage', storage_type, key, location, numel, view_metadata)`;
//! 5. the list of storage keys, in the order their data follows;
//!
//! then, for each key of that list, the element count as 8 bytes little-endian followed by
//! `count * element_size` raw bytes. The count must equal the `numel` of the persistent id, as
//! `torch.load` requires. (The still older tar-based format of PyTorch < 0.4 is not supported.)

use std::collections::HashMap;

use super::error::FormatError;
use super::pickle::{unpickle, Pickle, Value};
use super::tensor::{ByteOrder, StorageBytes};

/// First pickle of every legacy checkpoint.
const MAGIC_NUMBER: i128 = 0x1950_a86a_20f9_469c_fc6c;
/// Second pickle.
const PROTOCOL_VERSION: i128 = 1001;

/// Reads a legacy checkpoint: its main pickle and the storages listed after it.
pub(crate) fn load(
    data: &[u8],
) -> Result<(Pickle, HashMap<String, StorageBytes<'_>>), FormatError> {
    let mut pos = 0usize;
    let next = |pos: &mut usize| -> Result<(Pickle, u64), FormatError> {
        let at = *pos as u64;
        let p = unpickle(&data[*pos..], at)?;
        *pos += p.len;
        Ok((p, at))
    };
    let header = |offset: u64, reason: String| FormatError::Header { offset, reason };

    let (magic, at) = next(&mut pos)?;
    if !matches!(magic.root, Value::Int(MAGIC_NUMBER)) {
        return Err(header(
            at,
            "wrong magic number: not a PyTorch checkpoint".into(),
        ));
    }
    let (version, at) = next(&mut pos)?;
    if !matches!(version.root, Value::Int(PROTOCOL_VERSION)) {
        return Err(header(
            at,
            format!("unsupported protocol version {}", version.root.describe()),
        ));
    }
    let (sys_info, at) = next(&mut pos)?;
    let order = match &sys_info.root {
        Value::Dict(id) => match sys_info.arena.dicts[*id].get_str("little_endian") {
            None | Some(Value::Bool(true)) => ByteOrder::Little,
            Some(Value::Bool(false)) => ByteOrder::Big,
            Some(other) => {
                return Err(header(at, format!("little_endian is {}", other.describe())))
            }
        },
        other => {
            return Err(header(
                at,
                format!("system info is {}, not a dict", other.describe()),
            ))
        }
    };

    let (main, _) = next(&mut pos)?;

    let (keys, at) = next(&mut pos)?;
    let Value::List(list) = keys.root else {
        return Err(header(at, "storage key list is not a list".into()));
    };
    let mut storages = HashMap::new();
    for key in &keys.arena.lists[list] {
        let key = match key {
            Value::Str(s) => s.to_string(),
            other => {
                return Err(header(
                    at,
                    format!("storage key {} is not a string", other.describe()),
                ))
            }
        };
        let decl = main
            .storages
            .get(&key)
            .ok_or_else(|| FormatError::Storage {
                key: key.clone(),
                reason: "listed in the file but never referenced by the pickle".into(),
            })?;
        let count_at = pos;
        let count = data
            .get(pos..pos + 8)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
            .ok_or_else(|| FormatError::Truncated {
                what: format!("element count of storage {key}"),
                offset: pos as u64,
                needed: (pos + 8 - data.len()) as u64,
            })?;
        pos += 8;
        if count != decl.numel {
            return Err(FormatError::Storage {
                key,
                reason: format!(
                    "the file holds {count} elements at byte {count_at}, the pickle declares {}",
                    decl.numel
                ),
            });
        }
        let left = (data.len() - pos) as u64;
        let nbytes = count
            .checked_mul(decl.dtype.size())
            .filter(|&n| n <= left)
            .ok_or_else(|| FormatError::Truncated {
                what: format!("data of storage {key} ({count} x {:?})", decl.dtype),
                offset: pos as u64,
                needed: count.saturating_mul(decl.dtype.size()).saturating_sub(left),
            })? as usize;
        let bytes = &data[pos..pos + nbytes];
        pos += nbytes;
        let dup = storages.insert(
            key.clone(),
            StorageBytes {
                dtype: decl.dtype,
                order,
                bytes,
            },
        );
        if dup.is_some() {
            return Err(FormatError::Storage {
                key,
                reason: "listed twice in the file".into(),
            });
        }
    }
    Ok((main, storages))
}
