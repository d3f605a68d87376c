//! Robustness: truncated and corrupted PyTorch checkpoints (legacy pickle and zip formats) and
//! safetensors weights files must produce `Ok` or `Err`, never a panic, a hang or an absurd
//! allocation. Whatever loads must also survive the next stage: the networks built from an
//! imported state dict run on a small input, and weights read from safetensors save and read
//! back to the same bytes and run.
//!
//! Each test is a fuzz target of the testkit's harness ([`dsgs_testkit::fuzz`]), seeded from real
//! inputs: the smallest real legacy checkpoints of the shared `weights/`, the oracle's zip-format
//! decoder checkpoint (as written, and with its CRC-32s cleared, which the importer reads as "not
//! computed", so that mutations of the pickle reach the unpickler instead of failing the
//! checksum), and a weights file written by `NetWeights::save`'s serialiser from those real
//! networks. Besides the byte-level mutations, the targets change the arguments of pickle
//! opcodes (integers, lengths, memo indices), the element counts of legacy storages, the zip
//! records at the end of the archive, and the safetensors JSON header (dtypes, shapes, offsets,
//! metadata) with its length prefix kept consistent.
//!
//! `DSGS_FUZZ_CASES=N` (or `unbounded`) and `DSGS_FUZZ_SEED` change the number of mutated inputs
//! per target, e.g.
//! `DSGS_FUZZ_CASES=100000 cargo test --release -p dsgs-nets --test fuzz -- --nocapture`
//! (see `docs/robustness.md`).

use dsgs_testkit::fuzz::{
    below, byte_mutators, pick, safetensors_header, text_mutators, CappedAlloc, Mutator, Target,
    BOUNDARY_INTS,
};
use dsgs_testkit::shared_path;
use ndarray::{Array1, Array4};
use nets::checkpoint::load_checkpoint_bytes;
use nets::{Decoder, Encoder, Lifter, NetWeights, StateDict};

#[global_allocator]
static ALLOC: CappedAlloc = CappedAlloc;

fn read(rel: &str) -> Vec<u8> {
    std::fs::read(shared_path(rel)).expect("shared file is readable")
}

/// The networks a state dict describes, run on a small input: whatever the importer and the
/// layout inference accept must run.
fn run_networks(sd: &StateDict) {
    if let Ok(enc) = Encoder::<f32>::from_state_dict(sd) {
        let x = Array4::<f32>::from_elem((1, enc.in_channels(), 16, 16), 0.5);
        enc.forward(x.view())
            .expect("an encoder built from a checkpoint runs");
    }
    if let Ok(dec) = Decoder::<f32>::from_state_dict(sd) {
        let x = Array4::<f32>::from_elem((1, dec.in_channels(), 2, 2), 0.5);
        dec.forward(x.view())
            .expect("a decoder built from a checkpoint runs");
    }
}

fn check_checkpoint(bytes: &[u8]) -> bool {
    let Ok(sd) = load_checkpoint_bytes(bytes) else {
        return false;
    };
    run_networks(&sd);
    true
}

/// Pickle opcodes with an argument, and its width in bytes (`LONG1` is handled apart).
const PICKLE_ARGS: [(u8, usize); 13] = [
    (b'J', 4), // BININT
    (b'K', 1), // BININT1
    (b'M', 2), // BININT2
    (b'X', 4), // BINUNICODE length
    (0x8c, 1), // SHORT_BINUNICODE length
    (b'T', 4), // BINSTRING length
    (b'U', 1), // SHORT_BINSTRING length
    (b'q', 1), // BINPUT
    (b'r', 4), // LONG_BINPUT
    (b'h', 1), // BINGET
    (b'j', 4), // LONG_BINGET
    (0x95, 8), // FRAME length
    (b'G', 8), // BINFLOAT (big-endian)
];

/// Sets the argument of one pickle opcode (found by its byte value, so sometimes a byte that is
/// not an opcode) to a boundary value or nudges it: sizes, lengths, memo indices and the
/// integers that become tensor shapes, strides and offsets.
fn pickle_arguments() -> Mutator {
    Mutator::new("pickle opcode argument", |rng, input| {
        let sites: Vec<(usize, usize)> = input
            .iter()
            .enumerate()
            .filter_map(|(i, b)| {
                if *b == 0x8a {
                    // LONG1: a length byte, then that many little-endian bytes.
                    let n = *input.get(i + 1)? as usize;
                    return Some((i + 2, n.min(8)));
                }
                PICKLE_ARGS
                    .iter()
                    .find(|(op, _)| op == b)
                    .map(|&(_, w)| (i + 1, w))
            })
            .collect();
        let mut out = input.to_vec();
        if sites.is_empty() {
            return out;
        }
        let (at, width) = *pick(rng, &sites);
        let old = (0..width).fold(0u64, |v, k| {
            v | (*input.get(at + k).unwrap_or(&0) as u64) << (8 * k)
        });
        let v = match below(rng, 4) {
            0 => old.wrapping_add(1),
            1 => old.wrapping_sub(1),
            2 => old.wrapping_shl(1 + below(rng, 30) as u32),
            _ => *pick(rng, &BOUNDARY_INTS),
        };
        for k in 0..width {
            if let Some(b) = out.get_mut(at + k) {
                *b = (v >> (8 * k)) as u8;
            }
        }
        out
    })
}

/// The offsets of the element counts of a legacy checkpoint's float storages: after the key
/// list pickle (which ends with `APPENDS STOP`, `e.`), each storage is an 8-byte count and
/// `4 * count` bytes, up to the end of the file. Empty if the chain does not fit.
fn legacy_storage_counts(input: &[u8]) -> Vec<usize> {
    for start in input
        .windows(2)
        .enumerate()
        .filter(|(_, w)| w == b"e.")
        .map(|(i, _)| i + 2)
    {
        let mut counts = Vec::new();
        let mut at = start;
        while at + 8 <= input.len() {
            let n = u64::from_le_bytes(input[at..at + 8].try_into().unwrap());
            let Some(next) = n
                .checked_mul(4)
                .and_then(|b| b.checked_add(at as u64 + 8))
                .filter(|&e| e <= input.len() as u64)
            else {
                break;
            };
            counts.push(at);
            at = next as usize;
        }
        if at == input.len() && !counts.is_empty() {
            return counts;
        }
    }
    Vec::new()
}

/// Sets the element count of one legacy storage to a boundary value or nudges it.
fn legacy_storage_count() -> Mutator {
    Mutator::new("legacy storage count", |rng, input| {
        let counts = legacy_storage_counts(input);
        let mut out = input.to_vec();
        if counts.is_empty() {
            return out;
        }
        let at = *pick(rng, &counts);
        let old = u64::from_le_bytes(input[at..at + 8].try_into().unwrap());
        let v = match below(rng, 3) {
            0 => old.wrapping_add(1),
            1 => old.wrapping_sub(1),
            _ => *pick(rng, &BOUNDARY_INTS),
        };
        out[at..at + 8].copy_from_slice(&v.to_le_bytes());
        out
    })
}

#[test]
fn legacy_checkpoints_never_panic() {
    let conv = read("weights/wct-relu1_1-3_1/feature_invertor_conv1_1.pth");
    let vgg = read("weights/wct-relu1_1-3_1/vgg_normalised_conv1_1.pth");
    for seed in [&conv, &vgg] {
        assert!(!legacy_storage_counts(seed).is_empty());
    }
    // The pickles of these files fill their first kilobyte; the rest is storage data.
    let focused = byte_mutators()
        .iter()
        .map(|m| m.within(0..1024))
        .collect::<Vec<_>>();
    Target::new("legacy checkpoint", 10_000)
        .seed(conv)
        .seed(vgg)
        .mutators(focused)
        .mutators([pickle_arguments(), legacy_storage_count()])
        .run(check_checkpoint);
}

/// The archive with the CRC-32 of every local and central header set to 0 ("not computed").
fn without_crcs(zip: &[u8]) -> Vec<u8> {
    let mut out = zip.to_vec();
    for i in 0..zip.len().saturating_sub(20) {
        match &zip[i..i + 4] {
            b"PK\x03\x04" => out[i + 14..i + 18].fill(0),
            b"PK\x01\x02" => out[i + 16..i + 20].fill(0),
            _ => {}
        }
    }
    out
}

#[test]
fn zip_checkpoints_never_panic() {
    let zip = read("oracle/fixtures/decoder_zip.pth");
    let unchecked = without_crcs(&zip);
    assert_ne!(unchecked, zip);
    assert_eq!(
        load_checkpoint_bytes(&unchecked).unwrap(),
        load_checkpoint_bytes(&zip).unwrap()
    );
    // The header and pickle (3.5 kB) lie in the first 8 kB; the central directory, the zip64
    // records and the end record in the last 8 kB.
    let mut focused = Vec::new();
    for m in byte_mutators() {
        focused.push(m.within(0..8192));
        focused.push(m.within_last(8192));
    }
    Target::new("zip checkpoint", 5_000)
        .seed(zip)
        .seed(unchecked)
        .mutators(focused)
        .mutators([pickle_arguments().within(0..8192)])
        .run(check_checkpoint);
}

/// A weights file of real networks: the WCT relu1_1 encoder and decoder and a 4-to-64 lifter;
/// and one of the encoder alone.
fn weights_files() -> [Vec<u8>; 2] {
    let path = |f: &str| shared_path(&format!("weights/wct-relu1_1-3_1/{f}"));
    let encoder: Encoder = Encoder::from_checkpoint(&path("vgg_normalised_conv1_1.pth")).unwrap();
    let decoder: Decoder = Decoder::from_checkpoint(&path("feature_invertor_conv1_1.pth")).unwrap();
    let c = decoder.in_channels();
    let lifter = Lifter::new(
        Array4::from_shape_fn((c, 4, 1, 1), |(o, i, _, _)| (o + i) as f32 / 64.0),
        Array1::from_elem(c, 0.25),
    )
    .unwrap();
    let all = NetWeights {
        encoder: Some(encoder.clone()),
        decoder: Some(decoder),
        lifter: Some(lifter),
    };
    let encoder_only = NetWeights {
        encoder: Some(encoder),
        ..Default::default()
    };
    [all.to_bytes().unwrap(), encoder_only.to_bytes().unwrap()]
}

#[test]
fn safetensors_weights_never_panic() {
    let [all, encoder_only] = weights_files();
    Target::new("safetensors weights", 10_000)
        .seed(all)
        .seed(encoder_only)
        .mutators(safetensors_header(
            [byte_mutators(), text_mutators()].concat(),
        ))
        .run(|bytes| {
            let Ok(w) = NetWeights::from_bytes(bytes) else {
                return false;
            };
            let saved = w.to_bytes().expect("loaded weights serialise");
            let back = NetWeights::from_bytes(&saved).expect("saved weights load");
            assert_eq!(back.to_bytes().unwrap(), saved, "a save/load round trip");
            if let Some(l) = &w.lifter {
                let x = Array4::<f32>::from_elem((1, l.in_channels(), 2, 2), 0.5);
                l.forward(x.view())
                    .expect("a lifter read from a weights file runs");
            }
            if let Some(d) = &w.decoder {
                let x = Array4::<f32>::from_elem((1, d.in_channels(), 2, 2), 0.5);
                d.forward(x.view())
                    .expect("a decoder read from a weights file runs");
            }
            if let Some(e) = &w.encoder {
                let x = Array4::<f32>::from_elem((1, e.in_channels(), 16, 16), 0.5);
                e.forward(x.view())
                    .expect("an encoder read from a weights file runs");
            }
            true
        });
}
