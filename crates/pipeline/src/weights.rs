//! `dsgs weights`: importing PyTorch checkpoints into the canonical safetensors format, and
//! describing any weights file.
//!
//! A PyTorch checkpoint (legacy pickle or zip) holds one network; whether it is an encoder or a
//! decoder is recognised from its layers. The canonical file holds any of encoder, decoder and
//! lifter, with metadata describing their depth and widths.
//!
//! The network pairs `run` and `demo` use by name ([`Pair`]): the encoder always comes from a
//! PyTorch checkpoint under the shared folder; the relu4_1 pair's decoder is dsgs's own,
//! pre-trained by `dsgs pretrain-decoder` and built into the library ([`BUILT_IN_DECODER`]; its
//! card is `weights/relu41-decoder.md` beside the file).

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{bail, Context, Result};
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, Lifter, NetWeights};

/// The decoder of the relu4_1 pair, a canonical weights file holding only a decoder: the
/// compressed relu4_1 decoder fine-tuned by AdaIN's recipe on photographs and paintings (for
/// research use, like the data it was trained on; the card `weights/relu41-decoder.md` says
/// how it was made and what it measures).
pub const BUILT_IN_DECODER: &[u8] = include_bytes!("../weights/relu41-decoder.safetensors");

/// The built-in decoder of the relu4_1 pair ([`BUILT_IN_DECODER`]).
pub fn built_in_decoder() -> Result<Decoder<f32>> {
    NetWeights::from_bytes(BUILT_IN_DECODER)?
        .decoder
        .context("the built-in weights hold no decoder")
}

/// A pair of networks known by name (`--networks` of `run` and `demo`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pair {
    /// The 16x-compressed VGG-19 encoder to relu4_1 (the paper's depth and receptive field)
    /// with dsgs's pre-trained decoder ([`BUILT_IN_DECODER`]).
    Relu41,
    /// The normalised VGG-19 encoder to relu3_1 with the WCT feature invertor, a reconstruction
    /// decoder: it recolours more than it paints.
    WctRelu31,
}

impl Pair {
    /// Every value, by its command-line name.
    pub const NAMES: &'static [&'static str] = &["relu4_1", "wct-relu3_1"];

    /// The command-line name.
    pub fn as_str(self) -> &'static str {
        match self {
            Pair::Relu41 => "relu4_1",
            Pair::WctRelu31 => "wct-relu3_1",
        }
    }

    /// The encoder's PyTorch checkpoint, under the shared folder.
    pub fn encoder(self) -> &'static str {
        match self {
            Pair::Relu41 => "weights/compressed-16x-relu4_1/4SE.pth",
            Pair::WctRelu31 => "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
        }
    }

    /// The decoder's PyTorch checkpoint under the shared folder; `None`: the built-in decoder.
    pub fn decoder(self) -> Option<&'static str> {
        match self {
            Pair::Relu41 => None,
            Pair::WctRelu31 => Some("weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth"),
        }
    }

    /// The feature render's supersampling factor stage 3 uses with this pair: the relu4_1
    /// encoder pools by 8, and its 1/8 feature map rendered directly misses the Gaussians
    /// between pixel centres (docs/results.md measures the difference); the relu3_1 pair keeps
    /// the direct render it was measured with.
    pub fn supersample(self) -> u32 {
        match self {
            Pair::Relu41 => 8,
            Pair::WctRelu31 => 1,
        }
    }
}

impl Pair {
    /// The weight of stage 3's content and style terms with this pair (`lambda_content` and
    /// `lambda_style`; 0: the lifted features are fitted to the encoder's by the alignment
    /// loss alone). With the relu4_1 pair the two terms, shared by every training painting,
    /// teach the features one texture that every painting then shows, and move them away from
    /// the encoder's (docs/results.md, "What stage 3's content and style terms do"); the
    /// relu3_1 pair keeps the paper's weights, with which it was measured.
    pub fn content_style_weight(self) -> f64 {
        match self {
            Pair::Relu41 => 0.0,
            Pair::WctRelu31 => 1.0,
        }
    }
}

impl std::str::FromStr for Pair {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "relu4_1" => Ok(Pair::Relu41),
            "wct-relu3_1" => Ok(Pair::WctRelu31),
            _ => Err(format!(
                "unknown networks `{s}` (expected one of: {})",
                Pair::NAMES.join(", ")
            )),
        }
    }
}

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

/// Imports an encoder and/or a decoder into one canonical weights bundle: each a PyTorch
/// checkpoint, or a canonical file whose encoder (decoder) is taken, so that one network of a
/// trained pair can be written alone.
pub fn import(encoder: Option<&Path>, decoder: Option<&Path>) -> Result<NetWeights> {
    if encoder.is_none() && decoder.is_none() {
        bail!("nothing to import: give --encoder and/or --decoder");
    }
    let mut weights = NetWeights::default();
    if let Some(p) = encoder {
        let w = load_any(p)?;
        weights.encoder = Some(w.encoder.with_context(|| match w.decoder {
            Some(_) => format!("{} holds a decoder, not an encoder", p.display()),
            None => format!("{} holds no encoder", p.display()),
        })?);
    }
    if let Some(p) = decoder {
        let w = load_any(p)?;
        weights.decoder = Some(w.decoder.with_context(|| match w.encoder {
            Some(_) => format!("{} holds an encoder, not a decoder", p.display()),
            None => format!("{} holds no decoder", p.display()),
        })?);
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
