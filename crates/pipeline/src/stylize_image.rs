//! `dsgs stylize-image`: 2D AdaIN stylization of photographs with any networks, standard or
//! fullres: the per-image reference against which the 3D results are judged, and the
//! measurement behind each decoder's card.
//!
//! Every content photo is stylized with every style image (and, with `mix`, with their
//! mixture): `g((1 - alpha) phi_k(c) + alpha adain(phi_k(c), s))`, where `phi` is the encoder
//! and `g` the decoder at the chosen variant's resolution; with colour preservation each style
//! is first colour-matched to the photo. The outputs are cropped to the photo's size and
//! clamped to `[0, 1]`. With a standard encoder that pools with floor rounding (the compressed
//! relu4_1 encoder), each photo is first centre-cropped to a multiple of the total pooling.
//!
//! Each output is measured against its style image with the encoder's features at every level:
//! the style loss ([`style::style_loss`], channel means and deviations, as the training losses
//! and `dsgs eval` measure it), the texture distance ([`style::gram_distance`], the correlations
//! between channels), and the content loss against the photo's own deepest features
//! ([`style::content_loss`]); and the outputs of every two different paintings of a photo are
//! measured against each other with the same texture distance
//! ([`StylizeImageReport::mean_texture_between`]), which is near 0 when every painting gives the
//! same texture. The measuring encoder is the stylizing one unless `measure_with`
//! names another (used at standard resolution): the measures of two networks compare only
//! when one encoder measured both, since each encoder's levels have their own widths and
//! scales.
//!
//! Outputs in `OUT/`: one PNG per pair, `CONTENT__STYLE.png`; `contact_sheet.png` (first row:
//! the style images; then one row per photo: the photo, then its outputs in the order of the
//! styles); `report.json` ([`StylizeImageReport`]).

use std::path::{Path, PathBuf};

use ndarray::Array4;
use nets::PoolRounding;
use serde::{Deserialize, Serialize};
use style::{ChannelStats, StyleFeatureStats};
use train::Variant;

use crate::cli::{fraction, non_negative, variant};
use crate::error::{bail, Context, Result};
use crate::image_io::{self, image_files, nchw_from_rgb, rgb_from_nchw, RgbImage};
use crate::pretrain_decoder::NetworkFiles;
use crate::stylize::{check_alpha, normalised_weights};
use crate::{Control, Stage, Tally};

/// The default longest side of content photos and style images, in pixels.
pub const DEFAULT_IMAGE_SIDE: u32 = 512;

/// What to run; as [`clap::Args`], the flags of `dsgs stylize-image` up to `--style-size` (the
/// output folder is the program's to declare, after its own flags).
#[derive(Clone, Debug, clap::Args)]
pub struct StylizeImageSettings {
    /// Content photos: files, or folders whose image files are taken in name order.
    #[arg(
        required = true,
        value_name = "PHOTOS",
        help = "Content photo (file or folder); several may be given"
    )]
    pub contents: Vec<PathBuf>,
    /// Style images: files or folders, as `contents`.
    #[arg(
        long = "style",
        required = true,
        help = "Style image (file or folder); repeat for several (at least one)"
    )]
    pub styles: Vec<PathBuf>,
    /// The encoder and decoder.
    #[command(flatten)]
    pub networks: NetworkFiles,
    /// Standard (pooling) or fullres networks.
    #[arg(
        long,
        value_parser = variant(),
        default_value = "standard",
        help = "Network variant: `standard` (pooling and upsampling) or `fullres` (neither)"
    )]
    pub variant: Variant,
    /// Style strength in `[0, 1]`.
    #[arg(
        long,
        default_value_t = 1.0,
        value_parser = fraction,
        help = "Style strength, in [0, 1]: 0 reconstructs the photo, 1 is the full style"
    )]
    pub alpha: f64,
    /// Also stylize with the mixture of all styles, with these weights (one per style image).
    #[arg(
        long,
        value_delimiter = ',',
        value_parser = non_negative,
        help = "Also stylize with the mixture of the styles, with these weights (comma-separated, \
                one per style image, each 0 or more, not all 0) [default: no mixture]"
    )]
    pub mix: Option<Vec<f64>>,
    /// Match each style's colours to the photo first.
    #[arg(
        long,
        help = "Keep each photo's colours (the style images are colour-matched to it first)"
    )]
    pub preserve_colour: bool,
    /// Longest side of the photos after loading (0: as they are).
    #[arg(
        long = "content-size",
        value_name = "CONTENT_SIZE",
        default_value_t = DEFAULT_IMAGE_SIDE,
        help = "Longest side of the photos after loading, in pixels (0: as they are)"
    )]
    pub content_side: u32,
    /// Longest side of the style images after loading (0: as they are).
    #[arg(
        long = "style-size",
        value_name = "STYLE_SIZE",
        default_value_t = DEFAULT_IMAGE_SIDE,
        help = "Longest side of the style images after loading, in pixels (0: as they are)"
    )]
    pub style_side: u32,
    /// The encoder that measures the outputs, instead of the stylizing one.
    #[arg(
        long = "measure-with",
        value_name = "ENCODER",
        help = "Measure the outputs with this encoder (weights .safetensors or PyTorch checkpoint; \
                at standard resolution), so that the measures of different networks compare \
                [default: the stylizing encoder]"
    )]
    pub measure_with: Option<PathBuf>,
    /// Output folder.
    #[arg(skip)]
    pub out_dir: PathBuf,
}

/// The measures of one output.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairReport {
    /// The photo's file stem.
    pub content: String,
    /// The style's file stem, or `mix`.
    pub style: String,
    /// The output file, relative to the output folder.
    pub file: String,
    /// Style loss against the style image's statistics (summed over levels).
    pub style_loss: f64,
    /// Texture distance to the style image (Gram matrices, summed over levels).
    pub texture_distance: f64,
    /// Content loss against the photo's deepest features.
    pub content_loss: f64,
}

/// `report.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StylizeImageReport {
    /// `standard` or `fullres`.
    pub variant: String,
    /// Style strength.
    pub alpha: f64,
    /// Whether the style colours were matched to each photo.
    pub preserve_colour: bool,
    /// The file of the encoder that measured the outputs, or `stylizing encoder`.
    pub measured_with: String,
    /// Every output, photo by photo, styles in order.
    pub pairs: Vec<PairReport>,
    /// Means over all outputs of the three measures: style, texture, content.
    pub mean_style_loss: f64,
    /// Mean texture distance.
    pub mean_texture_distance: f64,
    /// Mean content loss.
    pub mean_content_loss: f64,
    /// The texture distance between the outputs of every two different paintings of the same
    /// photo (Gram matrices at every level of the measuring encoder), averaged over the photos
    /// and pairs: near 0 when every painting gives the photo the same texture (`None` with
    /// fewer than two paintings; the mixture is left out).
    #[serde(default)]
    pub mean_texture_between: Option<f64>,
}

impl StylizeImageReport {
    /// A table of every output's measures and a line of their means, naming `out_dir`, the
    /// folder holding the outputs, the contact sheet and the report.
    pub fn summary(&self, out_dir: &Path) -> String {
        let mut s = format!(
            "{:<24} {:<24} {:>10} {:>10} {:>10}\n",
            "photo", "style", "style", "texture", "content"
        );
        for p in &self.pairs {
            s += &format!(
                "{:<24} {:<24} {:>10.4} {:>10.4} {:>10.4}\n",
                p.content, p.style, p.style_loss, p.texture_distance, p.content_loss
            );
        }
        if let Some(b) = self.mean_texture_between {
            s += &format!("texture distance between different paintings' outputs: {b:.4}\n");
        }
        s += &format!(
            "mean: style loss {:.4}, texture distance {:.4}, content loss {:.4} (measured with \
             the {}); outputs, contact_sheet.png and report.json in {}\n",
            self.mean_style_loss,
            self.mean_texture_distance,
            self.mean_content_loss,
            if self.measured_with == "stylizing encoder" {
                "stylizing encoder".to_string()
            } else {
                format!("encoder of {}", self.measured_with)
            },
            out_dir.display()
        );
        s
    }
}

/// `img` centre-cropped to the largest size whose sides are multiples of `m` (at least `m`).
fn crop_to_multiple(img: RgbImage, m: u32) -> RgbImage {
    let (w, h) = ((img.width / m * m).max(m), (img.height / m * m).max(m));
    if (w, h) == (img.width, img.height) || w > img.width || h > img.height {
        return img;
    }
    let (x0, y0) = ((img.width - w) / 2, (img.height - h) / 2);
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in y0..y0 + h {
        let start = ((y * img.width + x0) * 3) as usize;
        data.extend_from_slice(&img.data[start..start + (w * 3) as usize]);
    }
    RgbImage {
        width: w,
        height: h,
        data,
    }
}

fn stem(p: &Path) -> String {
    p.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "image".into())
}

/// Runs the stylizations, reporting [`Stage::Stylize`] progress (one unit per output), and
/// writes the outputs.
pub fn run(settings: &StylizeImageSettings, control: &Control) -> Result<StylizeImageReport> {
    check_alpha(settings.alpha)?;
    let content_files = image_files(&settings.contents, "content")?;
    let style_files = image_files(&settings.styles, "style")?;
    let mix = match &settings.mix {
        Some(w) => Some(normalised_weights(w, style_files.len())?),
        None => None,
    };
    // Every input is read before anything is computed or written.
    let load = |p: &PathBuf, side: u32| image_io::load_style_image(p, side);
    let contents: Vec<RgbImage> = content_files
        .iter()
        .map(|p| load(p, settings.content_side))
        .collect::<Result<_>>()?;
    let styles: Vec<RgbImage> = style_files
        .iter()
        .map(|p| load(p, settings.style_side))
        .collect::<Result<_>>()?;
    let res = settings.variant.resolution();
    let encoder = settings.networks.load_encoder()?.with_resolution(res);
    let decoder = settings.networks.load_decoder()?.with_resolution(res);
    let measurer = match &settings.measure_with {
        Some(path) => Some(crate::weights::load_measuring_encoder(path)?.encoder),
        None => None,
    };
    let measurer = measurer.as_ref().unwrap_or(&encoder);
    // An encoder that pools with floor rounding drops the last row or column of odd sizes, so
    // its decoder gives back less than the photo: such photos are centre-cropped to a multiple
    // of the total pooling first.
    let contents: Vec<RgbImage> = if settings.variant == Variant::Standard
        && encoder.pool_rounding() == PoolRounding::Floor
    {
        let m = 1u32 << encoder.depth().saturating_sub(1).min(16);
        contents
            .into_iter()
            .map(|c| crop_to_multiple(c, m))
            .collect()
    } else {
        contents
    };
    if decoder.in_channels() != *encoder.widths().last().unwrap_or(&0) {
        bail!(
            "the decoder takes {} channels, the encoder's deepest level has {}",
            decoder.in_channels(),
            encoder.widths().last().unwrap_or(&0)
        );
    }
    std::fs::create_dir_all(&settings.out_dir)
        .with_context(|| format!("creating {}", settings.out_dir.display()))?;

    let mut names: Vec<String> = style_files.iter().map(|p| stem(p)).collect();
    if mix.is_some() {
        names.push("mix".into());
    }
    let total = contents.len() * names.len();
    let mut tally = Tally::start(Stage::Stylize, total, control.sink);
    // The statistics of the plain style images: the stylizing encoder's for the transform
    // without colour preservation, the measuring encoder's (the same unless `measure_with`)
    // for the measures.
    let stats_of = |enc: &nets::Encoder<f32>| -> Result<Vec<StyleFeatureStats<f32>>> {
        Ok(styles
            .iter()
            .map(|s| style::encode_style(enc, &nchw_from_rgb(s)))
            .collect::<std::result::Result<_, _>>()?)
    };
    let style_stats = stats_of(&encoder)?;
    let measure_stats = match &settings.measure_with {
        Some(_) => stats_of(measurer)?,
        None => style_stats.clone(),
    };
    let measure_feats: Vec<Vec<Array4<f32>>> = styles
        .iter()
        .map(|s| measurer.forward(nchw_from_rgb(s).view()))
        .collect::<std::result::Result<_, _>>()?;

    let mut pairs = Vec::new();
    let mut rows = Vec::new();
    let mut between = Vec::new();
    for (ci, (content, cfile)) in contents.iter().zip(&content_files).enumerate() {
        let x = nchw_from_rgb(content);
        let feats = encoder.forward(x.view())?;
        let deepest = feats.last().expect("encoder depth >= 1");
        let measured_content = match &settings.measure_with {
            Some(_) => measurer
                .forward(x.view())?
                .pop()
                .expect("encoder depth >= 1"),
            None => deepest.clone(),
        };
        // The target statistics of each style for this photo.
        let targets: Vec<ChannelStats<f32>> = if settings.preserve_colour {
            styles
                .iter()
                .map(|s| {
                    let matched = style::preserve_colour(&nchw_from_rgb(s), &x)?;
                    Ok(style::encode_style(&encoder, &matched)?.deepest().clone())
                })
                .collect::<Result<_>>()?
        } else {
            style_stats.iter().map(|s| s.deepest().clone()).collect()
        };
        let mut all = targets.clone();
        if let Some(w) = &mix {
            let members: Vec<(&ChannelStats<f32>, f64)> =
                targets.iter().zip(w.iter().copied()).collect();
            all.push(style::mix_stats(&members)?);
        }
        let mut row = Vec::with_capacity(all.len() + 1);
        let mut painting_grams = Vec::with_capacity(styles.len());
        for (si, target) in all.iter().enumerate() {
            let t = style::adain_alpha(deepest, target, settings.alpha)?;
            let y = decoder.forward(t.view())?;
            let y = runtime::frame::crop(y, content.width, content.height)?;
            let img = image_io::clamped(&rgb_from_nchw(&y)?);
            let out_feats = measurer.forward(nchw_from_rgb(&img).view())?;
            // The measures: against the style image (for the mixture, the weighted sum over
            // the style images).
            let (mut sl, mut td) = (0.0, 0.0);
            let parts: Vec<(usize, f64)> = match (&mix, si < styles.len()) {
                (_, true) => vec![(si, 1.0)],
                (Some(w), false) => w.iter().copied().enumerate().collect(),
                (None, false) => unreachable!("a mixture column only with weights"),
            };
            for (k, wk) in parts {
                sl += wk * style::style_loss(&out_feats, &measure_stats[k].levels)? as f64;
                td += wk * style::gram_distance(&out_feats, &measure_feats[k])?;
            }
            let cl = style::content_loss(out_feats.last().expect("depth >= 1"), &measured_content)?
                as f64;
            if si < styles.len() {
                let grams = out_feats.iter().map(|f| style::gram(f, 0));
                painting_grams.push(grams.collect::<Result<Vec<_>, _>>()?);
            }
            let file = format!("{}__{}.png", stem(cfile), names[si]);
            image_io::write_png(&settings.out_dir.join(&file), &img)?;
            pairs.push(PairReport {
                content: stem(cfile),
                style: names[si].clone(),
                file,
                style_loss: sl,
                texture_distance: td,
                content_loss: cl,
            });
            row.push(img);
            tally.advance(1, &format!("photo {} of {}", ci + 1, contents.len()));
        }
        for (i, a) in painting_grams.iter().enumerate() {
            for b in &painting_grams[i + 1..] {
                between.push(style::gram_distance_of(a, b)?);
            }
        }
        rows.push((content.clone(), row));
    }
    tally.finish();
    write_sheet(settings, &styles, mix.is_some(), &rows)?;
    let n = pairs.len().max(1) as f64;
    let mean = |f: fn(&PairReport) -> f64| pairs.iter().map(f).sum::<f64>() / n;
    let report = StylizeImageReport {
        variant: settings.variant.as_str().into(),
        alpha: settings.alpha,
        preserve_colour: settings.preserve_colour,
        measured_with: match &settings.measure_with {
            Some(p) => p.display().to_string(),
            None => "stylizing encoder".into(),
        },
        mean_style_loss: mean(|p| p.style_loss),
        mean_texture_distance: mean(|p| p.texture_distance),
        mean_content_loss: mean(|p| p.content_loss),
        mean_texture_between: (!between.is_empty())
            .then(|| between.iter().sum::<f64>() / between.len() as f64),
        pairs,
    };
    let json = serde_json::to_vec_pretty(&report).context("encoding the report")?;
    let path = settings.out_dir.join("report.json");
    base::write_atomic(&path, &json).with_context(|| format!("writing {}", path.display()))?;
    Ok(report)
}

/// `contact_sheet.png`: the style images (and a blank cell for the mixture) above the photos
/// and their outputs, every cell the size of the first photo's at most 256 pixels a side.
fn write_sheet(
    settings: &StylizeImageSettings,
    styles: &[RgbImage],
    mixed: bool,
    rows: &[(RgbImage, Vec<RgbImage>)],
) -> Result<()> {
    let first = &rows[0].0;
    let s = (256.0 / first.width.max(first.height) as f64).min(1.0);
    let (w, h) = (
        ((first.width as f64 * s).round() as u32).max(1),
        ((first.height as f64 * s).round() as u32).max(1),
    );
    let cols = 1 + styles.len() + usize::from(mixed);
    let (w, h) = image_io::sheet_cell_size(w, h, cols, rows.len() + 1);
    let mut header = vec![image_io::blank(w, h)];
    header.extend(styles.iter().map(|s| image_io::thumbnail(s, w, h)));
    if mixed {
        header.push(image_io::blank(w, h));
    }
    let mut sheet = vec![header];
    for (photo, outs) in rows {
        let mut row = vec![image_io::thumbnail(photo, w, h)];
        row.extend(outs.iter().map(|o| image_io::thumbnail(o, w, h)));
        sheet.push(row);
    }
    let img = image_io::contact_sheet(&sheet)?;
    image_io::write_png(&settings.out_dir.join("contact_sheet.png"), &img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn photos_are_cropped_to_the_centre_multiple() {
        let (w, h) = (21u32, 10u32);
        let img = RgbImage {
            width: w,
            height: h,
            data: (0..w * h * 3).map(|i| i as f32).collect(),
        };
        let c = crop_to_multiple(img.clone(), 8);
        assert_eq!((c.width, c.height), (16, 8));
        // Centred: columns 2..18 of rows 1..9.
        for y in 0..8 {
            for x in 0..16 {
                let src = (((y + 1) * w + x + 2) * 3) as usize;
                let dst = ((y * 16 + x) * 3) as usize;
                assert_eq!(c.data[dst..dst + 3], img.data[src..src + 3]);
            }
        }
        // Already a multiple, or too small to crop: unchanged.
        assert_eq!(crop_to_multiple(c.clone(), 8).data, c.data);
        let small = crop_to_multiple(img.clone(), 32);
        assert_eq!((small.width, small.height), (w, h));
    }
}
