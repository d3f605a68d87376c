//! Opening a scene bundle for the stages that read one (stylize, eval, bake, render, the
//! viewer): plain messages for a missing folder or description, and the replacement of its
//! decoder or variant.

use std::path::Path;

use runtime::SceneBundle;
use train::Variant;

use crate::error::{bail, Context, Result};

/// Reads a scene bundle directory ([`SceneBundle::load`]), first saying plainly when `dir` is
/// not there (`bundle folder X not found`) or holds no `bundle.json` (`X: no bundle.json`).
pub fn open_bundle(dir: &Path) -> Result<SceneBundle> {
    let info = runtime::bundle::INFO_FILE;
    let holds = format!(
        "a scene bundle is a folder holding {}, {} and {info}",
        runtime::bundle::SCENE_FILE,
        runtime::bundle::NETS_FILE
    );
    if !dir.exists() {
        bail!("bundle folder {} not found", dir.display());
    }
    if !dir.is_dir() {
        bail!("{}: not a folder ({holds})", dir.display());
    }
    if !dir.join(info).exists() {
        bail!("{}: no {info} ({holds})", dir.display());
    }
    SceneBundle::load(dir).with_context(|| format!("loading the scene bundle {}", dir.display()))
}

/// Loads a bundle ([`open_bundle`]), optionally switching the variant and replacing the decoder
/// (a canonical `.safetensors` or a PyTorch checkpoint holding a decoder).
pub fn load_bundle(
    dir: &Path,
    variant: Option<Variant>,
    decoder: Option<&Path>,
) -> Result<SceneBundle> {
    let bundle = open_bundle(dir)?;
    let variant = variant.unwrap_or(bundle.info.variant);
    if let (Some(p), true) = (decoder, bundle.info.decoder_mode.trains_decoder()) {
        bail!(
            "the bundle {} was trained with its own {} decoder (fit-features --decoder-mode {}); \
             its features fit no other decoder, so --decoder {} cannot replace it",
            dir.display(),
            bundle.info.decoder_mode.as_str(),
            bundle.info.decoder_mode.as_str(),
            p.display()
        );
    }
    let dec = match decoder {
        None => bundle.decoder.clone(),
        Some(p) => crate::weights::load_any(p)
            .with_context(|| format!("reading the decoder {}", p.display()))?
            .decoder
            .with_context(|| format!("{} holds no decoder", p.display()))?,
    };
    let from = decoder.map_or_else(|| dir.display().to_string(), |p| p.display().to_string());
    bundle.with_decoder(dec, variant).with_context(|| {
        format!(
            "using the decoder of {from} with the bundle {}",
            dir.display()
        )
    })
}
