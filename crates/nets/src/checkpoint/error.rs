//! Errors of the checkpoint importer.
//!
//! [`FormatError`] says what is wrong with the bytes, naming the byte offset (always counted from
//! the start of the file, also inside zip entries), the storage key or the tensor name.
//! [`CheckpointError`] adds the file it came from. An unsupported pickle opcode is named by its
//! standard name (`opcode_name`).

use std::path::PathBuf;

/// A checkpoint file that could not be imported.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The file could not be read at all.
    #[error("cannot read checkpoint {}: {error}", path.display())]
    Io {
        /// The checkpoint file.
        path: PathBuf,
        /// The underlying I/O error.
        error: std::io::Error,
    },
    /// The file was read but its contents are not an importable checkpoint.
    #[error("checkpoint {}: {problem}", path.display())]
    Invalid {
        /// The checkpoint file.
        path: PathBuf,
        /// What is wrong with its contents.
        problem: FormatError,
    },
}

/// What is wrong with the bytes of a checkpoint.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FormatError {
    /// Neither a zip archive nor a pickle.
    #[error(
        "not a PyTorch checkpoint: it starts with {found:02x?}, expected a zip archive \
         (50 4b 03 04) or a pickle (80)"
    )]
    UnknownFormat {
        /// The file's first (up to 4) bytes.
        found: Vec<u8>,
    },

    /// The data ends before a field that must be there.
    #[error("truncated: {what} at byte {offset} needs {needed} more bytes than the file has")]
    Truncated {
        /// The field being read (e.g. `pickle GLOBAL name`).
        what: String,
        /// Byte offset in the file where the field starts.
        offset: u64,
        /// How many bytes beyond the end of the data the field would need.
        needed: u64,
    },

    /// A pickle opcode outside the subset that state dicts use.
    #[error(
        "pickle opcode {opcode:#04x} ({}) at byte {offset} is not allowed in a state dict",
        opcode_name(*opcode)
    )]
    UnsupportedOpcode {
        /// The opcode byte.
        opcode: u8,
        /// Byte offset of the opcode in the file.
        offset: u64,
    },

    /// A pickle global outside the whitelist.
    #[error("pickle global {module}.{name} at byte {offset} is not allowed in a state dict")]
    UnsupportedGlobal {
        /// The global's module (e.g. `torch._utils`).
        module: String,
        /// The global's name within the module.
        name: String,
        /// Byte offset of the opcode that names it.
        offset: u64,
    },

    /// A pickle that is well formed byte-wise but does not make sense.
    #[error("malformed pickle at byte {offset}: {reason}")]
    Pickle {
        /// Byte offset of the offending opcode in the file.
        offset: u64,
        /// What does not make sense.
        reason: String,
    },

    /// A pickle that exceeds a resource limit of the importer.
    #[error("pickle at byte {offset} exceeds the limit of {limit} {what}")]
    Limit {
        /// Byte offset of the opcode that crossed the limit.
        offset: u64,
        /// The limited resource, plural (e.g. `memo entries`, `stack values`).
        what: &'static str,
        /// The importer's maximum for that resource.
        limit: u64,
    },

    /// The legacy header pickles (magic number, protocol version, system info) are wrong.
    #[error("legacy checkpoint header at byte {offset}: {reason}")]
    Header {
        /// Byte offset of the offending header pickle.
        offset: u64,
        /// What is wrong with it.
        reason: String,
    },

    /// A structurally broken zip archive.
    #[error("corrupt zip archive at byte {offset}: {reason}")]
    Zip {
        /// Byte offset of the broken structure (e.g. a local header or the central directory).
        offset: u64,
        /// What is broken.
        reason: String,
    },

    /// A zip entry the format requires is absent.
    #[error("zip archive has no entry {name}")]
    MissingEntry {
        /// The required entry's name (e.g. `<top>/data.pkl`).
        name: String,
    },

    /// A zip entry whose bytes do not match its recorded CRC-32.
    #[error("zip entry {name} at byte {offset} fails its CRC-32 check (corrupt data)")]
    Checksum {
        /// The entry's name in the archive.
        name: String,
        /// Byte offset of the entry's data in the file.
        offset: u64,
    },

    /// A storage referenced by a tensor whose bytes are not in the file.
    #[error("storage {key} is referenced by the pickle but its data is not in the file")]
    MissingStorage {
        /// The storage key the pickle's persistent id names.
        key: String,
    },

    /// A storage whose recorded size or type is inconsistent.
    #[error("storage {key}: {reason}")]
    Storage {
        /// The storage key.
        key: String,
        /// What is inconsistent.
        reason: String,
    },

    /// A tensor whose shape, strides or offset do not fit its storage.
    #[error("tensor {name}: {reason}")]
    Tensor {
        /// The tensor's name in the state dict.
        name: String,
        /// Why it does not fit.
        reason: String,
    },

    /// The unpickled object is not a (possibly wrapped or nested) dict of tensors.
    #[error("unsupported checkpoint layout: {reason}")]
    Layout {
        /// What was found instead.
        reason: String,
    },
}

/// The standard name of a pickle opcode, for error messages.
fn opcode_name(op: u8) -> &'static str {
    match op {
        b'(' => "MARK",
        b'.' => "STOP",
        b'0' => "POP",
        b'1' => "POP_MARK",
        b'2' => "DUP",
        b'F' => "FLOAT",
        b'I' => "INT",
        b'J' => "BININT",
        b'K' => "BININT1",
        b'L' => "LONG",
        b'M' => "BININT2",
        b'N' => "NONE",
        b'P' => "PERSID",
        b'Q' => "BINPERSID",
        b'R' => "REDUCE",
        b'S' => "STRING",
        b'T' => "BINSTRING",
        b'U' => "SHORT_BINSTRING",
        b'V' => "UNICODE",
        b'X' => "BINUNICODE",
        b'a' => "APPEND",
        b'b' => "BUILD",
        b'c' => "GLOBAL",
        b'd' => "DICT",
        b'}' => "EMPTY_DICT",
        b'e' => "APPENDS",
        b'g' => "GET",
        b'h' => "BINGET",
        b'i' => "INST",
        b'j' => "LONG_BINGET",
        b'l' => "LIST",
        b']' => "EMPTY_LIST",
        b'o' => "OBJ",
        b'p' => "PUT",
        b'q' => "BINPUT",
        b'r' => "LONG_BINPUT",
        b's' => "SETITEM",
        b't' => "TUPLE",
        b')' => "EMPTY_TUPLE",
        b'u' => "SETITEMS",
        b'G' => "BINFLOAT",
        0x80 => "PROTO",
        0x81 => "NEWOBJ",
        0x82 => "EXT1",
        0x83 => "EXT2",
        0x84 => "EXT4",
        0x85 => "TUPLE1",
        0x86 => "TUPLE2",
        0x87 => "TUPLE3",
        0x88 => "NEWTRUE",
        0x89 => "NEWFALSE",
        0x8a => "LONG1",
        0x8b => "LONG4",
        b'B' => "BINBYTES",
        b'C' => "SHORT_BINBYTES",
        0x8c => "SHORT_BINUNICODE",
        0x8d => "BINUNICODE8",
        0x8e => "BINBYTES8",
        0x8f => "EMPTY_SET",
        0x90 => "ADDITEMS",
        0x91 => "FROZENSET",
        0x92 => "NEWOBJ_EX",
        0x93 => "STACK_GLOBAL",
        0x94 => "MEMOIZE",
        0x95 => "FRAME",
        0x96 => "BYTEARRAY8",
        0x97 => "NEXT_BUFFER",
        0x98 => "READONLY_BUFFER",
        _ => "not a pickle opcode",
    }
}
