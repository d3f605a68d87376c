//! The encoding cache (see "Encoding cache" in the [module documentation](super)): one file per
//! encoded view or style, named by a hash of everything its encoding depends on, its format
//! ([`write_entry`], [`decode_entry`]), the thread that writes the files while encoding goes on,
//! and the flat form of a style's statistics stored in it.

use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc};
use std::time::UNIX_EPOCH;

use ndarray::Array4;
use nets::Encoder;
use style::{ChannelStats, FeatureNorm, StyleFeatureStats};

use crate::error::TrainError;
use base::Fnv1a;
use runtime::bundle::{weights_fingerprint, Variant};

/// The start of every cache file.
const ENCODING_MAGIC: &[u8; 8] = b"DSGSENC2";

/// The encoding cache of one setup: the folder, the part of every key that does not depend on
/// the image, and the files used so far.
pub(super) struct EncodingCache<'a> {
    pub(super) dir: &'a Path,
    prefix: String,
    used: Vec<String>,
    pub(super) reused: usize,
    pub(super) rebuilt: usize,
    pub(super) write_error: Option<String>,
    /// The thread writing the files, started at the first write.
    writer: Option<CacheWriter>,
}

/// Values a cache file is written from: a view's target, shared with the training data, or
/// values of the file's own.
pub(super) enum CacheValues {
    Shared(Arc<Array4<f32>>),
    Own(Vec<f32>),
}

impl CacheValues {
    fn as_slice(&self) -> &[f32] {
        match self {
            CacheValues::Shared(a) => a.as_slice().expect("targets are in standard layout"),
            CacheValues::Own(v) => v,
        }
    }
}

/// A cache file to write: its path, its key and its values (the concatenation of the parts).
struct CacheFile {
    path: PathBuf,
    key: String,
    parts: Vec<CacheValues>,
}

/// A thread that writes cache files in the order they are sent, so that encoding never waits
/// for the disk. It stops at the first failure and returns it.
struct CacheWriter {
    files: mpsc::Sender<CacheFile>,
    thread: std::thread::JoinHandle<Option<String>>,
}

impl CacheWriter {
    fn start() -> std::io::Result<CacheWriter> {
        let (files, queue) = mpsc::channel::<CacheFile>();
        let thread = std::thread::Builder::new()
            .name("encoding-cache".into())
            .spawn(move || {
                for file in queue {
                    let parts: Vec<&[f32]> = file.parts.iter().map(CacheValues::as_slice).collect();
                    let written = base::write_atomic_unsynced_with(&file.path, |f| {
                        write_entry(f, &file.key, &parts)
                    });
                    if let Err(e) = written {
                        return Some(format!("{}: {e}", file.path.display()));
                    }
                }
                None
            })?;
        Ok(CacheWriter { files, thread })
    }

    /// Waits for every file sent to be written; the first failure, if any.
    fn finish(self) -> Option<String> {
        drop(self.files);
        self.thread
            .join()
            .unwrap_or_else(|_| Some("the cache writer stopped unexpectedly".into()))
    }
}

/// What the cached values were computed by: the program's version and its executable's size
/// and modification time (`None` when they cannot be read: nothing is cached then).
fn program_identity() -> Option<String> {
    let exe = std::env::current_exe().ok()?;
    let meta = std::fs::metadata(exe).ok()?;
    let modified = meta.modified().ok()?.duration_since(UNIX_EPOCH).ok()?;
    Some(format!(
        "{} {} {}",
        env!("CARGO_PKG_VERSION"),
        meta.len(),
        modified.as_nanos()
    ))
}

impl<'a> EncodingCache<'a> {
    pub(super) fn new(
        dir: &'a Path,
        encoder: &Encoder<f32>,
        variant: Variant,
        normalize: FeatureNorm,
    ) -> Option<Self> {
        let program = program_identity()?;
        Some(EncodingCache {
            dir,
            prefix: format!(
                "{program}\n{}\n{}\n{}",
                weights_fingerprint(encoder),
                variant.as_str(),
                normalize.as_str()
            ),
            used: Vec::new(),
            reused: 0,
            rebuilt: 0,
            write_error: None,
            writer: None,
        })
    }

    /// The file name of the encoding of a `width x height` RGB image as a `kind` (`view` or
    /// `style`), and its key.
    pub(super) fn entry(
        &self,
        kind: &str,
        width: u32,
        height: u32,
        rgb: &[f32],
    ) -> (String, String) {
        let mut h = Fnv1a::new();
        h.eat(ENCODING_MAGIC);
        h.eat(self.prefix.as_bytes());
        h.eat(kind.as_bytes());
        h.eat(&width.to_le_bytes());
        h.eat(&height.to_le_bytes());
        for &v in rgb {
            h.eat_f32(v);
        }
        let key = h.hex();
        (format!("{kind}-{key}.bin"), key)
    }

    /// The `len` values stored under `name` for `key`, if the file is sound (format, key,
    /// length and checksum); a file that is present but unsound counts as rebuilt.
    pub(super) fn read(&mut self, name: &str, key: &str, len: usize) -> Option<Vec<f32>> {
        self.used.push(name.to_string());
        let bytes = std::fs::read(self.dir.join(name)).ok()?;
        let values = decode_entry(&bytes, key, len);
        match values {
            Some(_) => self.reused += 1,
            None => self.rebuilt += 1,
        }
        values
    }

    /// Stores the concatenation of `parts` under `name` for `key`, on the writer thread; a
    /// failure ends the writing, not the run, and [`EncodingCache::finish`] reports it.
    pub(super) fn write(&mut self, name: &str, key: &str, parts: Vec<CacheValues>) {
        if self.write_error.is_some() {
            return;
        }
        if self.writer.is_none() {
            match CacheWriter::start() {
                Ok(w) => self.writer = Some(w),
                Err(e) => {
                    self.write_error = Some(format!("could not start the cache writer: {e}"));
                    return;
                }
            }
        }
        let file = CacheFile {
            path: self.dir.join(name),
            key: key.to_string(),
            parts,
        };
        // A send fails only once the writer has stopped at a failure, which `finish` reports.
        let _ = self.writer.as_ref().expect("started").files.send(file);
    }

    /// Waits for every file to be written, and keeps the first failure in `write_error`.
    pub(super) fn finish(&mut self) {
        if let Some(e) = self.writer.take().and_then(CacheWriter::finish) {
            self.write_error.get_or_insert(e);
        }
    }

    /// Removes the cache files of this folder that the run did not use (best effort).
    pub(super) fn prune(&self) {
        let Ok(entries) = std::fs::read_dir(self.dir) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let ours =
                (name.starts_with("view-") || name.starts_with("style-")) && name.ends_with(".bin");
            if ours && !self.used.contains(&name) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// A setup that stops early (an error) still waits for the files already sent.
impl Drop for EncodingCache<'_> {
    fn drop(&mut self) {
        self.finish();
    }
}

/// A cache file: the magic, the key (16 hexadecimal digits), the number of values (`u64`), the
/// values (`f32`), all little-endian, then the CRC-32 (IEEE) checksum of everything before it
/// (8 hexadecimal digits). A checksum that runs at memory speed, not a hash: the key already
/// names the contents, the checksum only tells a damaged file.
///
/// The values are the concatenation of `parts`, written to `out` in pieces, so that no second
/// copy of them is formed.
fn write_entry(out: &mut impl std::io::Write, key: &str, parts: &[&[f32]]) -> std::io::Result<()> {
    /// Values converted and written per piece (256 KiB).
    const PIECE: usize = 1 << 16;
    let mut crc = crc32fast::Hasher::new();
    let mut put = |out: &mut dyn std::io::Write, bytes: &[u8]| {
        crc.update(bytes);
        out.write_all(bytes)
    };
    let len: usize = parts.iter().map(|p| p.len()).sum();
    put(out, ENCODING_MAGIC)?;
    put(out, key.as_bytes())?;
    put(out, &(len as u64).to_le_bytes())?;
    // The conversion buffer of big-endian machines (little-endian ones write the values' bytes).
    let mut bytes = Vec::new();
    for piece in parts.iter().flat_map(|p| p.chunks(PIECE)) {
        if cfg!(target_endian = "little") {
            // The values' own bytes are already little-endian.
            put(out, bytemuck::cast_slice(piece))?;
        } else {
            bytes.clear();
            bytes.extend(piece.iter().flat_map(|v| v.to_le_bytes()));
            put(out, &bytes)?;
        }
    }
    out.write_all(format!("{:08x}", crc.finalize()).as_bytes())
}

/// The values of a cache file written by [`write_entry`] for `key` with `len` values, or
/// `None` if anything does not match.
fn decode_entry(bytes: &[u8], key: &str, len: usize) -> Option<Vec<f32>> {
    let head = ENCODING_MAGIC.len() + key.len() + 8;
    if bytes.len() != head + 4 * len + 8 {
        return None;
    }
    let (body, checksum) = bytes.split_at(bytes.len() - 8);
    if checksum != format!("{:08x}", crc32fast::hash(body)).as_bytes()
        || &body[..8] != ENCODING_MAGIC
        || &body[8..8 + key.len()] != key.as_bytes()
        || body[8 + key.len()..head] != (len as u64).to_le_bytes()
    {
        return None;
    }
    Some(if cfg!(target_endian = "little") {
        // Little-endian bytes are the values' own (copied, as `bytes` may be unaligned).
        bytemuck::pod_collect_to_vec(&body[head..])
    } else {
        body[head..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    })
}

/// The flat values of per-level statistics: each level's means, then its standard deviations.
pub(super) fn stats_values(stats: &StyleFeatureStats<f32>) -> Vec<f32> {
    stats
        .levels
        .iter()
        .flat_map(|l| l.mean.iter().chain(l.std.iter()).copied())
        .collect()
}

/// Statistics of one image at levels of the given widths from [`stats_values`].
pub(super) fn stats_from_values(
    values: &[f32],
    widths: &[usize],
) -> Result<StyleFeatureStats<f32>, TrainError> {
    let mut levels = Vec::with_capacity(widths.len());
    let mut at = 0;
    for &c in widths {
        let row = |from: usize| {
            ndarray::Array2::from_shape_vec((1, c), values[from..from + c].to_vec()).map_err(
                |error| TrainError::Array {
                    what: "cannot rebuild cached style statistics".into(),
                    error,
                },
            )
        };
        levels.push(ChannelStats::new(row(at)?, row(at + c)?)?);
        at += 2 * c;
    }
    Ok(StyleFeatureStats { levels })
}
