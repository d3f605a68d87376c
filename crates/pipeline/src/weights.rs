//! `dsgs weights`: importing PyTorch checkpoints into the canonical safetensors format, and
//! describing any weights file.
//!
//! A PyTorch checkpoint (legacy pickle or zip) holds one network; whether it is an encoder or a
//! decoder is recognised from its layers. The canonical file holds any of encoder, decoder and
//! lifter, with metadata describing their depth and widths.

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{bail, Context, Result};
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, Lifter, NetWeights};

/// The networks a single PyTorch checkpoint can hold.
pub enum Network {
    /// An encoder (e.g. `vgg_normalised.pth`).
    Encoder(Encoder),
    /// A decoder (e.g. `decoder.pth`).
    Decoder(Decoder),
}

/// Whether a path names a canonical safetensors weights file (by extension).
pub fn is_canonical(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("safetensors"))
}

/// Reads a PyTorch checkpoint and builds the network it holds, trying encoder then decoder.
pub fn import_network(path: &Path) -> Result<Network> {
    let sd = load_checkpoint(path)?;
    let as_encoder = Encoder::from_state_dict(&sd);
    if let Ok(e) = as_encoder {
        return Ok(Network::Encoder(e));
    }
    match Decoder::from_state_dict(&sd) {
        Ok(d) => Ok(Network::Decoder(d)),
        Err(dec_err) => {
            let enc_err = as_encoder.err().map(|e| e.to_string()).unwrap_or_default();
            bail!(
                "{} is neither an encoder nor a decoder checkpoint\n  as an encoder: {enc_err}\n  as a decoder: {dec_err}",
                path.display()
            )
        }
    }
}

/// Imports an encoder and/or a decoder checkpoint into one canonical weights bundle.
pub fn import(encoder: Option<&Path>, decoder: Option<&Path>) -> Result<NetWeights> {
    if encoder.is_none() && decoder.is_none() {
        bail!("nothing to import: give --encoder and/or --decoder");
    }
    let mut weights = NetWeights::default();
    if let Some(p) = encoder {
        match import_network(p)? {
            Network::Encoder(e) => weights.encoder = Some(e),
            Network::Decoder(_) => bail!("{} holds a decoder, not an encoder", p.display()),
        }
    }
    if let Some(p) = decoder {
        match import_network(p)? {
            Network::Decoder(d) => weights.decoder = Some(d),
            Network::Encoder(_) => bail!("{} holds an encoder, not a decoder", p.display()),
        }
    }
    if let (Some(e), Some(d)) = (&weights.encoder, &weights.decoder) {
        let deepest = *e.widths().last().unwrap_or(&0);
        if d.in_channels() != deepest {
            bail!(
                "the decoder takes {} channels but the encoder's relu{}_1 has {deepest}: they are not a pair",
                d.in_channels(),
                e.depth()
            );
        }
    }
    Ok(weights)
}

/// Loads networks from either a canonical weights file or a PyTorch checkpoint.
pub fn load_any(path: &Path) -> Result<NetWeights> {
    if is_canonical(path) {
        return Ok(NetWeights::load(path)?);
    }
    let mut w = NetWeights::default();
    match import_network(path)? {
        Network::Encoder(e) => w.encoder = Some(e),
        Network::Decoder(d) => w.decoder = Some(d),
    }
    Ok(w)
}

fn params<'a>(layers: impl Iterator<Item = &'a nets::ConvLayer>) -> usize {
    layers.map(|l| l.weight.len() + l.bias.len()).sum()
}

fn list(v: &[usize]) -> String {
    v.iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

/// A human-readable description of the networks in a weights file.
pub fn describe(path: &Path) -> Result<String> {
    let w = load_any(path).with_context(|| format!("reading {}", path.display()))?;
    let mut s = String::new();
    let kind = if is_canonical(path) {
        "canonical dsgs weights"
    } else {
        "PyTorch checkpoint"
    };
    writeln!(s, "{}: {kind}", path.display())?;
    if let Some(e) = &w.encoder {
        writeln!(s, "encoder: normalised VGG to relu{}_1", e.depth())?;
        writeln!(s, "  widths relu1_1..: {}", list(&e.widths()))?;
        writeln!(s, "  3x3 convs per level: {}", list(&e.convs_per_level()))?;
        writeln!(s, "  max-pool rounding: {:?}", e.pool_rounding())?;
        writeln!(s, "  parameters: {}", params(e.layers()))?;
    }
    if let Some(d) = &w.decoder {
        writeln!(
            s,
            "decoder: {} -> {} channels over {} levels",
            d.in_channels(),
            d.out_channels(),
            d.depth()
        )?;
        writeln!(
            s,
            "  3x3 convs per level (deepest first): {}",
            list(&d.convs_per_level())
        )?;
        writeln!(s, "  ReLU after the last conv: {}", d.final_relu())?;
        writeln!(s, "  parameters: {}", params(d.layers()))?;
    }
    if let Some(l) = &w.lifter {
        describe_lifter(&mut s, l)?;
    }
    Ok(s)
}

fn describe_lifter(s: &mut String, l: &Lifter) -> std::fmt::Result {
    writeln!(
        s,
        "lifter: 1x1 conv + ReLU, {} -> {} channels",
        l.in_channels(),
        l.out_channels()
    )
}

/// An encoder that measures outputs in place of the stylizing one (`--measure-with` of
/// `dsgs eval` and `dsgs stylize-image`), and a fingerprint of its file's bytes.
pub struct MeasuringEncoder {
    /// The encoder, at standard resolution.
    pub encoder: Encoder<f32>,
    /// The file it was read from, as given.
    pub path: String,
    /// FNV-1a of the file's bytes, so that a sharded evaluation's parts agree on it.
    pub fingerprint: String,
}

/// Reads the encoder of `path` (canonical weights or a PyTorch checkpoint) for measuring.
pub fn load_measuring_encoder(path: &Path) -> Result<MeasuringEncoder> {
    let encoder = load_any(path)
        .with_context(|| format!("reading the measuring encoder {}", path.display()))?
        .encoder
        .with_context(|| format!("{} holds no encoder", path.display()))?
        .with_resolution(nets::Resolution::Standard);
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut h = base::Fnv1a::new();
    h.eat(&bytes);
    Ok(MeasuringEncoder {
        encoder,
        path: path.display().to_string(),
        fingerprint: h.hex(),
    })
}
