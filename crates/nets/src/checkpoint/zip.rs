//! The zip checkpoint format of PyTorch >= 1.6, and the small zip reader it needs.
//!
//! `torch.save` writes an uncompressed ("stored") zip archive with one top-level folder, named
//! after the file: `<top>/data.pkl` is the pickled object, `<top>/data/<key>` holds the raw bytes
//! of the storage with persistent-id key `<key>`, and `<top>/byteorder` (`little` or `big`) the
//! byte order of those bytes (little when absent). Other entries (`version`, `.format_version`,
//! `.storage_alignment`, `.data/serialization_id`) are not needed.
//!
//! The reader follows the zip specification (APPNOTE 6.3) only as far as such archives need:
//! the end-of-central-directory record, its zip64 variant (which PyTorch always writes), the
//! central directory with zip64 extra fields, and the local headers (only for the data offset:
//! PyTorch leaves the local sizes zero and uses data descriptors). Compressed, encrypted and
//! multi-disk archives are refused. Every entry read is checked against its CRC-32, except that a
//! recorded CRC of 0 is taken to mean "not computed" (`torch.serialization.set_crc32_options(False)`).

use std::collections::HashMap;

use super::error::FormatError;
use super::pickle::{unpickle, Pickle};
use super::tensor::{ByteOrder, StorageBytes};

const LOCAL_HEADER: u32 = 0x0403_4b50;
const CENTRAL_HEADER: u32 = 0x0201_4b50;
const END_OF_CENTRAL_DIR: u32 = 0x0605_4b50;
const ZIP64_END_OF_CENTRAL_DIR: u32 = 0x0606_4b50;
const ZIP64_LOCATOR: u32 = 0x0706_4b50;
/// Fixed part of the end-of-central-directory record.
const EOCD_LEN: usize = 22;
/// Fixed part of a central directory header.
const CENTRAL_LEN: usize = 46;
/// Fixed part of a local header.
const LOCAL_LEN: usize = 30;

/// One stored entry of the archive.
#[derive(Clone, Debug)]
pub(crate) struct Entry {
    pub name: String,
    /// File offset of the first data byte.
    pub data_offset: u64,
    pub size: u64,
    pub crc: u32,
}

/// The entries of a stored zip archive held in memory.
#[derive(Debug)]
pub(crate) struct ZipArchive<'a> {
    data: &'a [u8],
    pub entries: Vec<Entry>,
    by_name: HashMap<String, usize>,
}

fn zip_err(offset: usize, reason: impl Into<String>) -> FormatError {
    FormatError::Zip {
        offset: offset as u64,
        reason: reason.into(),
    }
}

/// Little-endian field reader over the whole file, with bounds checks.
struct Fields<'a> {
    data: &'a [u8],
}

impl Fields<'_> {
    fn bytes(&self, at: usize, n: usize, what: &str) -> Result<&[u8], FormatError> {
        at.checked_add(n)
            .filter(|&end| end <= self.data.len())
            .map(|end| &self.data[at..end])
            .ok_or_else(|| FormatError::Truncated {
                what: format!("zip {what}"),
                offset: at as u64,
                needed: (at as u64 + n as u64).saturating_sub(self.data.len() as u64),
            })
    }

    fn u16(&self, at: usize, what: &str) -> Result<u16, FormatError> {
        let b = self.bytes(at, 2, what)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&self, at: usize, what: &str) -> Result<u32, FormatError> {
        let b = self.bytes(at, 4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&self, at: usize, what: &str) -> Result<u64, FormatError> {
        let b = self.bytes(at, 8, what)?;
        Ok(u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }
}

/// A file offset or size from the archive, as an in-memory index.
fn index(v: u64, at: usize, what: &str) -> Result<usize, FormatError> {
    usize::try_from(v).map_err(|_| zip_err(at, format!("{what} {v} does not fit in memory")))
}

impl<'a> ZipArchive<'a> {
    /// Reads the central directory of the archive `data`.
    pub(crate) fn parse(data: &'a [u8]) -> Result<ZipArchive<'a>, FormatError> {
        let f = Fields { data };
        let eocd = find_eocd(data)?;
        let mut entry_count = u64::from(f.u16(eocd + 10, "entry count")?);
        let mut cd_size = u64::from(f.u32(eocd + 12, "central directory size")?);
        let mut cd_offset = u64::from(f.u32(eocd + 16, "central directory offset")?);
        if f.u16(eocd + 4, "disk number")? != 0 || f.u16(eocd + 6, "disk number")? != 0 {
            return Err(zip_err(eocd, "multi-disk archives are not supported"));
        }
        // The end of the central directory: the zip64 record when there is one.
        let mut cd_limit = eocd;
        if eocd >= 20 && f.u32(eocd - 20, "zip64 locator")? == ZIP64_LOCATOR {
            let locator = eocd - 20;
            let at = index(
                f.u64(locator + 8, "zip64 record offset")?,
                locator,
                "offset",
            )?;
            if at > locator || f.u32(at, "zip64 record")? != ZIP64_END_OF_CENTRAL_DIR {
                return Err(zip_err(
                    locator,
                    "zip64 locator does not point at a zip64 record",
                ));
            }
            entry_count = f.u64(at + 32, "zip64 entry count")?;
            cd_size = f.u64(at + 40, "zip64 central directory size")?;
            cd_offset = f.u64(at + 48, "zip64 central directory offset")?;
            cd_limit = at;
        }
        let cd_start = index(cd_offset, eocd, "central directory offset")?;
        let cd_end = cd_offset
            .checked_add(cd_size)
            .filter(|&e| e <= cd_limit as u64)
            .ok_or_else(|| zip_err(eocd, "central directory lies outside the archive"))?
            as usize;
        if entry_count > cd_size / CENTRAL_LEN as u64 {
            return Err(zip_err(
                eocd,
                format!("{entry_count} entries cannot fit in a {cd_size}-byte central directory"),
            ));
        }

        let mut entries = Vec::with_capacity(entry_count as usize);
        let mut by_name = HashMap::with_capacity(entry_count as usize);
        let mut at = cd_start;
        for _ in 0..entry_count {
            if at + CENTRAL_LEN > cd_end {
                return Err(zip_err(at, "central directory ends inside an entry header"));
            }
            let entry = central_entry(&f, at, cd_end, cd_start)?;
            if by_name
                .insert(entry.0.name.clone(), entries.len())
                .is_some()
            {
                return Err(zip_err(at, format!("duplicate entry {}", entry.0.name)));
            }
            entries.push(entry.0);
            at = entry.1;
        }
        Ok(ZipArchive {
            data,
            entries,
            by_name,
        })
    }

    /// The entry with this exact name.
    pub(crate) fn find(&self, name: &str) -> Option<&Entry> {
        self.by_name.get(name).map(|&i| &self.entries[i])
    }

    /// The bytes of an entry, checked against its CRC-32.
    pub(crate) fn read(&self, entry: &Entry) -> Result<&'a [u8], FormatError> {
        // Bounds were checked when the entry was parsed.
        let start = entry.data_offset as usize;
        let bytes = &self.data[start..start + entry.size as usize];
        if entry.crc != 0 && crc32(bytes) != entry.crc {
            return Err(FormatError::Checksum {
                name: entry.name.clone(),
                offset: entry.data_offset,
            });
        }
        Ok(bytes)
    }
}

/// Parses the central directory header at `at`; returns the entry and the next header's offset.
fn central_entry(
    f: &Fields,
    at: usize,
    cd_end: usize,
    cd_start: usize,
) -> Result<(Entry, usize), FormatError> {
    if f.u32(at, "central header")? != CENTRAL_HEADER {
        return Err(zip_err(at, "bad central directory header signature"));
    }
    let flags = f.u16(at + 8, "flags")?;
    let method = f.u16(at + 10, "compression method")?;
    let crc = f.u32(at + 16, "CRC-32")?;
    let mut compressed = u64::from(f.u32(at + 20, "compressed size")?);
    let mut size = u64::from(f.u32(at + 24, "size")?);
    let name_len = usize::from(f.u16(at + 28, "name length")?);
    let extra_len = usize::from(f.u16(at + 30, "extra length")?);
    let comment_len = usize::from(f.u16(at + 32, "comment length")?);
    let mut local = u64::from(f.u32(at + 42, "local header offset")?);
    let next = at + CENTRAL_LEN + name_len + extra_len + comment_len;
    if next > cd_end {
        return Err(zip_err(at, "entry header runs past the central directory"));
    }
    let name_bytes = f.bytes(at + CENTRAL_LEN, name_len, "entry name")?;
    let name = std::str::from_utf8(name_bytes)
        .map_err(|_| zip_err(at, "entry name is not UTF-8"))?
        .to_owned();

    // Zip64 extended information: the 64-bit values of the fields saturated at 0xffffffff,
    // in the order size, compressed size, local header offset.
    let extra = f.bytes(at + CENTRAL_LEN + name_len, extra_len, "extra field")?;
    let mut p = 0;
    while p + 4 <= extra.len() {
        let id = u16::from_le_bytes([extra[p], extra[p + 1]]);
        let len = usize::from(u16::from_le_bytes([extra[p + 2], extra[p + 3]]));
        let body = extra
            .get(p + 4..p + 4 + len)
            .ok_or_else(|| zip_err(at, "extra field runs past its end"))?;
        if id == 0x0001 {
            let mut values = body
                .chunks_exact(8)
                .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")));
            let mut widen = |field: &mut u64| -> Result<(), FormatError> {
                if *field == 0xffff_ffff {
                    *field = values
                        .next()
                        .ok_or_else(|| zip_err(at, "zip64 extra field is too short"))?;
                }
                Ok(())
            };
            widen(&mut size)?;
            widen(&mut compressed)?;
            widen(&mut local)?;
        }
        p += 4 + len;
    }

    if flags & 0x0001 != 0 {
        return Err(zip_err(at, format!("entry {name} is encrypted")));
    }
    if method != 0 || compressed != size {
        return Err(zip_err(
            at,
            format!(
                "entry {name} is compressed (method {method}); PyTorch stores entries uncompressed"
            ),
        ));
    }

    let local = index(local, at, "local header offset")?;
    if local >= cd_start || f.u32(local, "local header")? != LOCAL_HEADER {
        return Err(zip_err(local, format!("no local header for entry {name}")));
    }
    let local_name = usize::from(f.u16(local + 26, "local name length")?);
    let local_extra = usize::from(f.u16(local + 28, "local extra length")?);
    let data_offset = local + LOCAL_LEN + local_name + local_extra;
    if (data_offset as u64)
        .checked_add(size)
        .is_none_or(|end| end > cd_start as u64)
    {
        return Err(zip_err(
            local,
            format!("data of entry {name} ({size} bytes) runs into the central directory"),
        ));
    }
    let entry = Entry {
        name,
        data_offset: data_offset as u64,
        size,
        crc,
    };
    Ok((entry, next))
}

/// Offset of the end-of-central-directory record: the last signature within the final
/// 22 + 65535 bytes (the record plus the longest comment).
fn find_eocd(data: &[u8]) -> Result<usize, FormatError> {
    if data.len() < EOCD_LEN {
        return Err(FormatError::Truncated {
            what: "zip end of central directory".into(),
            offset: data.len() as u64,
            needed: (EOCD_LEN - data.len()) as u64,
        });
    }
    let lowest = data.len().saturating_sub(EOCD_LEN + 0xffff);
    (lowest..=data.len() - EOCD_LEN)
        .rev()
        .find(|&at| data[at..at + 4] == END_OF_CENTRAL_DIR.to_le_bytes())
        .ok_or_else(|| {
            zip_err(
                data.len(),
                "no end-of-central-directory record (truncated or not a zip archive)",
            )
        })
}

/// CRC-32 (IEEE 802.3, reflected polynomial 0xedb88320), as recorded in zip headers.
pub(crate) fn crc32(bytes: &[u8]) -> u32 {
    const TABLE: [u32; 256] = {
        let mut table = [0u32; 256];
        let mut i = 0;
        while i < 256 {
            let mut c = i as u32;
            let mut k = 0;
            while k < 8 {
                c = if c & 1 != 0 {
                    0xedb8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
                k += 1;
            }
            table[i] = c;
            i += 1;
        }
        table
    };
    !bytes.iter().fold(!0u32, |c, &b| {
        TABLE[((c ^ u32::from(b)) & 0xff) as usize] ^ (c >> 8)
    })
}

/// Reads a zip checkpoint: its pickle, byte order and the storages the pickle declares.
pub(crate) fn load(
    data: &[u8],
) -> Result<(Pickle, HashMap<String, StorageBytes<'_>>), FormatError> {
    let archive = ZipArchive::parse(data)?;
    let first = archive
        .entries
        .first()
        .ok_or_else(|| FormatError::MissingEntry {
            name: "<top>/data.pkl".into(),
        })?;
    let top = match first.name.split_once('/') {
        Some((top, _)) => top.to_owned(),
        None => {
            return Err(FormatError::MissingEntry {
                name: format!("data.pkl (first entry {} is not in a folder)", first.name),
            })
        }
    };
    let entry = |name: String| {
        archive
            .find(&name)
            .ok_or(FormatError::MissingEntry { name })
    };

    let pkl = entry(format!("{top}/data.pkl"))?;
    let pickle = unpickle(archive.read(pkl)?, pkl.data_offset)?;

    let order = match archive.find(&format!("{top}/byteorder")) {
        None => ByteOrder::Little,
        Some(e) => match archive.read(e)? {
            b"little" => ByteOrder::Little,
            b"big" => ByteOrder::Big,
            other => {
                return Err(zip_err(
                    e.data_offset as usize,
                    format!("unknown byte order {:?}", String::from_utf8_lossy(other)),
                ))
            }
        },
    };

    let mut storages = HashMap::new();
    for (key, decl) in &pickle.storages {
        let e = archive
            .find(&format!("{top}/data/{key}"))
            .ok_or_else(|| FormatError::MissingStorage { key: key.clone() })?;
        let bytes = archive.read(e)?;
        let expected = decl.numel.checked_mul(decl.dtype.size());
        if expected != Some(bytes.len() as u64) {
            return Err(FormatError::Storage {
                key: key.clone(),
                reason: format!(
                    "entry {} has {} bytes, but the pickle declares {} elements of {:?}",
                    e.name,
                    bytes.len(),
                    decl.numel,
                    decl.dtype
                ),
            });
        }
        storages.insert(
            key.clone(),
            StorageBytes {
                dtype: decl.dtype,
                order,
                bytes,
            },
        );
    }
    Ok((pickle, storages))
}
