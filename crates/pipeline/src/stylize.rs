//! `dsgs stylize`: zero-shot stylization of a scene bundle along a camera sequence.
//!
//! A frame, top down ([`run`]): rasterize the camera's feature map
//! ([`SceneBundle::feature_view`]), then per style lift, transform, decode and clamp
//! ([`SceneBundle::stylize`]; the steps are in [`runtime::frame`]). Each camera's feature map is
//! rasterized once and kept in memory ([`runtime::FeatureView`]), so every further style costs only the
//! lift, the transform and the decode of that map.
//!
//! Styles:
//! * each `--style` image is read, reduced so its longer side is at most `max_side`, and encoded
//!   with the bundle's encoder (at the bundle's variant); its statistics at every level are kept
//!   (the deepest drive the transform, all of them serve the style loss);
//! * with weights, the styles are mixed into one target: the weights are normalised to sum 1 and
//!   each level's mean and std are the weighted sums ([`style::mix_stats`]);
//! * with colour preservation, each style image's colours are first matched
//!   ([`style::preserve_colour`]) to the plain colour renders of up to [`COLOUR_VIEWS`] evenly
//!   spaced cameras of the sequence placed side by side, one content for the whole sequence, so
//!   the target does not change from view to view.
//!
//! Inputs are checked before anything is rendered or written ([`run`]): the strength `alpha`
//! and the mixture weights ([`check_style_settings`]), the cameras' sizes
//! ([`crate::cameras::check_camera_sizes`]), and every style image, read and decoded up front
//! ([`load_styles`]), so a bad file fails the run, naming it, before the first frame.
//!
//! The decoded image is written clamped to `[0, 1]`. The contact sheet's cells are the frames
//! at their size, reduced when the whole sheet would exceed the image size limits
//! ([`image_io::sheet_cell_size`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::error::{bail, Context, Result};
use gaussian::dataset::images::resize;
use gaussian::Camera;
use ndarray::Array4;
use runtime::{SceneBundle, StageSeconds};
use style::{ChannelStats, StyleFeatureStats};

use crate::cameras::evenly_spaced;
use crate::image_io::{self, RgbImage};
use crate::render::{render_colour, ColourRender};
use crate::shard::Part;
use crate::{Sink, Stage, Tally};

/// Camera views whose colour renders make the content of colour preservation.
pub const COLOUR_VIEWS: usize = 8;
/// Default longest side of style images.
pub const DEFAULT_STYLE_SIDE: u32 = 512;

/// A loaded style image with its output name.
#[derive(Clone, Debug)]
pub struct StyleImage {
    /// The output name: the file stem, made unique ([`style_names`]).
    pub name: String,
    /// The file it was read from.
    pub path: PathBuf,
    /// The image, longer side at most the requested maximum.
    pub image: RgbImage,
}

/// Output names from file stems, made unique with `_2`, `_3`, ... suffixes.
pub fn style_names(paths: &[PathBuf]) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for p in paths {
        let stem = p
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .filter(|s| !s.is_empty())
            .unwrap_or_else(|| "style".into());
        let mut name = stem.clone();
        let mut k = 2;
        while names.contains(&name) || name == "colour" {
            name = format!("{stem}_{k}");
            k += 1;
        }
        names.push(name);
    }
    names
}

/// Reads and decodes every style image, each reduced so its longer side is at most `max_side`
/// ([`image_io::load_style_image`]), failing on the first that is missing, not an image or
/// beyond the size limits, with a message naming it (`style image {path}: ...`). A folder
/// stands for its `.png` and `.jpg` files in name order (a folder without any is an error
/// naming it).
pub fn load_styles(paths: &[PathBuf], max_side: u32) -> Result<Vec<StyleImage>> {
    let paths = &style_files(paths)?;
    let names = style_names(paths);
    paths
        .iter()
        .zip(names)
        .map(|(p, name)| {
            Ok(StyleImage {
                name,
                path: p.clone(),
                image: image_io::load_style_image(p, max_side)?,
            })
        })
        .collect()
}

/// The style image files of `paths`: each file as given, each folder's `.png` and `.jpg` files
/// in name order ([`crate::image_io::image_files`]). At least one path must be given.
pub fn style_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    if paths.is_empty() {
        bail!("no style image given (--style IMG)");
    }
    let mut expanded = Vec::with_capacity(paths.len());
    for p in paths {
        if p.is_dir() {
            expanded.extend(crate::image_io::image_files(
                std::slice::from_ref(p),
                "style",
            )?);
        } else {
            expanded.push(p.clone());
        }
    }
    Ok(expanded)
}

/// One stylization target: an output name and the statistics of every encoder level.
#[derive(Clone, Debug)]
pub struct StyleTarget {
    /// The output name: the style's name, or `mix` for a mixture.
    pub name: String,
    /// Per-channel mean and std of the style's encoder features at every level.
    pub stats: StyleFeatureStats<f32>,
}

/// Checks mixture weights: one per style, each finite and non-negative, not all zero; returns
/// them normalised to sum 1. The error names the offending value.
pub fn normalised_weights(weights: &[f64], styles: usize) -> Result<Vec<f64>> {
    if weights.len() != styles {
        bail!(
            "--mix has {} values for {styles} style image(s)",
            weights.len()
        );
    }
    for (i, w) in weights.iter().enumerate() {
        if !(w.is_finite() && *w >= 0.0) {
            bail!(
                "--mix: weight {} is {w}; each weight must be a finite number, 0 or more",
                i + 1
            );
        }
    }
    let sum: f64 = weights.iter().sum();
    if !(sum > 0.0 && sum.is_finite()) {
        let list: Vec<String> = weights.iter().map(|w| w.to_string()).collect();
        bail!(
            "--mix {}: {}",
            list.join(","),
            if sum > 0.0 {
                "the weights are too large to add up"
            } else {
                "the weights are all zero; at least one must be above 0"
            }
        );
    }
    Ok(weights.iter().map(|w| w / sum).collect())
}

/// Checks a style strength: a number from 0 (the scene as it is) to 1 (the full style). The
/// error names the value.
pub fn check_alpha(alpha: f64) -> Result<()> {
    if !(0.0..=1.0).contains(&alpha) {
        bail!(
            "--alpha {alpha}: the style strength must be a number from 0 (the scene as it is) \
             to 1 (the full style)"
        );
    }
    Ok(())
}

/// Checks the style settings shared by stylization, evaluation and baking before any work:
/// the strength ([`check_alpha`]) and, when given, the mixture weights for `styles` style
/// images ([`normalised_weights`]).
pub fn check_style_settings(alpha: f64, weights: Option<&[f64]>, styles: usize) -> Result<()> {
    check_alpha(alpha)?;
    if let Some(w) = weights {
        normalised_weights(w, styles)?;
    }
    Ok(())
}

/// The content of colour preservation: the colour renders of the given views side by side
/// (clamped), as `[1, 3, H, sum W]`.
pub fn colour_content(renders: &[&RgbImage]) -> Result<Array4<f32>> {
    let Some(first) = renders.first() else {
        bail!("colour preservation needs at least one colour render");
    };
    let h = first.height;
    let mut rows = Vec::new();
    for r in renders {
        if r.height != h {
            bail!("colour renders differ in height");
        }
        rows.push(image_io::clamped(r));
    }
    let sheet = image_io::contact_sheet(&[rows])?;
    Ok(image_io::nchw_from_rgb(&sheet))
}

/// Encodes the styles into targets: one per style, or one mixture (`"mix"`) with weights
/// ([`encode_styles`], then [`mix_targets`]).
pub fn style_targets(
    bundle: &SceneBundle,
    styles: &[StyleImage],
    weights: Option<&[f64]>,
    colour: Option<&Array4<f32>>,
) -> Result<Vec<StyleTarget>> {
    let encoded = encode_styles(&bundle.encoder, styles, colour)?;
    mix_targets(encoded, weights)
}

/// The style image as the encoder sees it: its colours first matched to `colour` when given
/// ([`style::preserve_colour`]).
pub fn style_input(s: &StyleImage, colour: Option<&Array4<f32>>) -> Result<Array4<f32>> {
    let img = image_io::nchw_from_rgb(&s.image);
    match colour {
        Some(content) => style::preserve_colour(&img, content)
            .with_context(|| format!("colour preservation of {}", s.path.display())),
        None => Ok(img),
    }
}

/// One target per style: its statistics at every level of `encoder` (a bundle's, or one that
/// measures), its colours first matched to `colour` when given ([`style::preserve_colour`]).
pub fn encode_styles(
    encoder: &nets::Encoder<f32>,
    styles: &[StyleImage],
    colour: Option<&Array4<f32>>,
) -> Result<Vec<StyleTarget>> {
    let mut encoded = Vec::new();
    for s in styles {
        let img = style_input(s, colour)?;
        let stats = style::encode_style(encoder, &img)
            .with_context(|| format!("encoding the style {}", s.path.display()))?;
        encoded.push(StyleTarget {
            name: s.name.clone(),
            stats,
        });
    }
    Ok(encoded)
}

/// The targets as they are without weights, or their mixture (`"mix"`): the weights (one per
/// target, [`normalised_weights`]) applied to each level's mean and std ([`style::mix_stats`]).
pub fn mix_targets(encoded: Vec<StyleTarget>, weights: Option<&[f64]>) -> Result<Vec<StyleTarget>> {
    let Some(w) = weights else {
        return Ok(encoded);
    };
    let w = normalised_weights(w, encoded.len())?;
    let depth = encoded[0].stats.levels.len();
    let levels = (0..depth)
        .map(|l| {
            let members: Vec<(&ChannelStats<f32>, f64)> = encoded
                .iter()
                .zip(&w)
                .map(|(t, &wt)| (&t.stats.levels[l], wt))
                .collect();
            style::mix_stats(&members)
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(vec![StyleTarget {
        name: "mix".into(),
        stats: StyleFeatureStats { levels },
    }])
}

/// Checks that the bundle's networks can stylize every camera's view
/// ([`SceneBundle::check_view_size`]), naming the first camera too small by its index.
pub fn check_view_sizes(bundle: &SceneBundle, cameras: &[Camera]) -> Result<()> {
    for (i, c) in cameras.iter().enumerate() {
        let k = &c.intrinsics;
        if let Err(m) = bundle.check_view_size(k.width, k.height) {
            bail!("camera {i}: {m}");
        }
    }
    Ok(())
}

/// Settings of `dsgs stylize`.
#[derive(Clone, Debug)]
pub struct StylizeSettings {
    /// The style images (`--style`, repeated; at least one).
    pub styles: Vec<PathBuf>,
    /// Mix the styles with these weights into one output, one per style (`--mix`).
    pub weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style (`--alpha`).
    pub alpha: f64,
    /// Keep the scene's colours: the style images are colour-matched to the colour renders
    /// (`--preserve-colour`).
    pub preserve_colour: bool,
    /// Longest side of the style images after loading (`--style-size`).
    pub style_side: u32,
    /// Output directory (`--output`): a folder of `frame_XXXX.png` per output, the animations
    /// and `contact_sheet.png`.
    pub out_dir: PathBuf,
    /// Also write an animated GIF per output (`--gif`).
    pub gif: bool,
    /// Also write an MP4 per output, through `ffmpeg` on `PATH` (`--mp4`).
    pub mp4: bool,
    /// Frames per second of the animations (`--fps`).
    pub fps: f64,
    /// Columns of the contact sheet (views, evenly spaced; `--sheet-views`).
    pub sheet_views: usize,
    /// Working memory of the networks per frame, in bytes (`--tile-budget`, in MiB): frames
    /// are decoded in tiles that fit it ([`SceneBundle::decode_in_tiles`]).
    pub tile_budget: u64,
    /// The whole run, one shard of it (`--shard K/N`: its frames and manifest), or the merge of
    /// the shards (`dsgs assemble`).
    pub part: Part,
}

/// What `dsgs stylize` wrote.
#[derive(Clone, Debug, Default)]
pub struct StylizeOutput {
    /// Per output: its name and the frame paths this call wrote (a shard: its block; an
    /// assembly: none).
    pub outputs: Vec<(String, Vec<PathBuf>)>,
    /// The animated GIFs, one per output (with `gif`).
    pub gifs: Vec<PathBuf>,
    /// The MP4 videos, one per output (with `mp4`).
    pub mp4s: Vec<PathBuf>,
    /// The contact sheet: a row per output under the colour row, its style in the first column.
    pub contact_sheet: Option<PathBuf>,
    /// The shard's manifest (a shard only).
    pub manifest: Option<PathBuf>,
    /// Frames decoded by this call (views times outputs).
    pub decoded: usize,
    /// Mean stage seconds per view of the frames this call decoded.
    pub seconds: StageSeconds,
}

impl StylizeOutput {
    /// What a call of [`run`] with `settings` over `frames` cameras wrote, a line each: a
    /// shard's block, manifest and how to merge the shards, or every output's frames; then the
    /// animations, the contact sheet and the mean stage times.
    pub fn summary(&self, frames: usize, settings: &StylizeSettings) -> String {
        let out = &settings.out_dir;
        let mut s = String::new();
        if let Part::Shard { shard, .. } = &settings.part {
            let r = shard.range(frames);
            s += &format!(
                "shard {shard}: frames {} to {} of {frames} written for {} output(s) in {}\n",
                r.start,
                r.end.saturating_sub(1),
                self.outputs.len(),
                out.display()
            );
            if let Some(m) = &self.manifest {
                s += &format!("manifest {}\n", m.display());
            }
            s += &format!(
                "when every shard has finished: dsgs assemble {}\n",
                out.display()
            );
        } else {
            for (name, _) in &self.outputs {
                s += &format!("{name}: {frames} frames in {}\n", out.join(name).display());
            }
        }
        for p in self
            .gifs
            .iter()
            .chain(&self.mp4s)
            .chain(&self.contact_sheet)
        {
            s += &format!("wrote {}\n", p.display());
        }
        if self.decoded > 0 {
            let t = self.seconds;
            s += &format!(
                "seconds per view: raster {:.4}, lift+transform {:.4}, decode {:.4}\n",
                t.raster, t.lift_transform, t.decode
            );
        }
        s
    }
}

/// The name of the shard manifests of `dsgs stylize` ([`crate::shard`]).
pub const SHARD_COMMAND: &str = "stylize";

/// The folder of the shard manifests of a stylization into `out_dir`.
pub fn shard_dir(out_dir: &Path) -> PathBuf {
    out_dir.join("shards")
}

/// The path of frame `i` of output `name`.
pub fn frame_path(out_dir: &Path, name: &str, i: usize) -> PathBuf {
    out_dir.join(name).join(format!("frame_{i:04}.png"))
}

/// Colour renders of the views at `indices`.
pub fn colour_renders(
    bundle: &SceneBundle,
    cameras: &[Camera],
    indices: &[usize],
) -> Result<Vec<ColourRender>> {
    indices
        .iter()
        .map(|&i| render_colour(&bundle.scene, &cameras[i], bundle.info.background))
        .collect()
}

/// Feeds a camera's intrinsics and pose bits to `h`.
pub(crate) fn hash_camera(h: &mut base::Fnv1a, c: &Camera) {
    let k = c.intrinsics;
    for v in [k.fx, k.fy, k.cx, k.cy] {
        h.eat_f64(v);
    }
    h.eat_u64(k.width as u64);
    h.eat_u64(k.height as u64);
    c.camera_from_world
        .to_cols_array()
        .iter()
        .for_each(|&v| h.eat_f64(v));
}

/// Feeds the name and every level's statistics of each target to `h`.
pub(crate) fn hash_targets(h: &mut base::Fnv1a, targets: &[StyleTarget]) {
    for t in targets {
        h.eat_str(&t.name);
        for l in &t.stats.levels {
            l.mean
                .iter()
                .chain(l.std.iter())
                .for_each(|&v| h.eat_f32(v));
        }
    }
}

/// The fingerprint of a stylization: the bundle ([`SceneBundle::fingerprint`]), the cameras,
/// the targets and the strength; every frame of the run is a function of these.
fn fingerprint(
    bundle: &SceneBundle,
    cameras: &[Camera],
    targets: &[StyleTarget],
    alpha: f64,
) -> String {
    let mut h = base::Fnv1a::new();
    h.eat_str(SHARD_COMMAND);
    h.eat_str(&bundle.fingerprint());
    h.eat_u64(cameras.len() as u64);
    cameras.iter().for_each(|c| hash_camera(&mut h, c));
    hash_targets(&mut h, targets);
    h.eat_f64(alpha);
    h.hex()
}

/// Runs `dsgs stylize` on a loaded bundle along `cameras`, reporting one [`Stage::Stylize`]
/// unit per rasterized view and per decoded frame to `sink`.
///
/// Frames are rasterized and decoded one camera at a time (every output of a camera from its
/// one feature map) and written as they are made. The animations and the contact sheet are
/// then made from the written frames, read back, so that a run in shards
/// ([`Part::Shard`], then [`Part::Assemble`]) gives the same files byte for byte.
pub fn run(
    bundle: &SceneBundle,
    cameras: &[Camera],
    settings: &StylizeSettings,
    sink: &dyn Sink,
) -> Result<StylizeOutput> {
    let started = Instant::now();
    if cameras.is_empty() {
        bail!("no cameras to render");
    }
    let part = &settings.part;
    let merges = !matches!(part, Part::Shard { .. });
    // Fail early on everything that does not need rendering: the settings, the cameras' sizes,
    // ffmpeg, and every style image, decoded before the first frame.
    check_style_settings(
        settings.alpha,
        settings.weights.as_deref(),
        settings.styles.len(),
    )?;
    crate::cameras::check_camera_sizes(cameras)?;
    check_view_sizes(bundle, cameras)?;
    let ffmpeg = if settings.mp4 && merges {
        Some(image_io::ffmpeg()?)
    } else {
        None
    };
    let styles = load_styles(&settings.styles, settings.style_side)?;
    let out_dir = &settings.out_dir;
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;

    let colour_idx = evenly_spaced(cameras.len(), COLOUR_VIEWS);
    let content = if settings.preserve_colour {
        let renders = colour_renders(bundle, cameras, &colour_idx)?;
        let imgs: Vec<&RgbImage> = renders.iter().map(|r| &r.image).collect();
        Some(colour_content(&imgs)?)
    } else {
        None
    };
    let targets = style_targets(
        bundle,
        &styles,
        settings.weights.as_deref(),
        content.as_ref(),
    )?;
    let fingerprint = fingerprint(bundle, cameras, &targets, settings.alpha);
    if *part == Part::Assemble {
        crate::shard::collect(
            &shard_dir(out_dir),
            &crate::shard::Expected {
                command: SHARD_COMMAND,
                fingerprint: &fingerprint,
                items: cameras.len(),
                root: out_dir,
            },
        )?;
    }

    let range = part.range(cameras.len());
    let mut tally = Tally::start(Stage::Stylize, range.len() * (1 + targets.len()), sink);
    let mut out = StylizeOutput {
        outputs: targets
            .iter()
            .map(|t| (t.name.clone(), Vec::new()))
            .collect(),
        ..Default::default()
    };
    let mut total = StageSeconds::default();
    for i in range.clone() {
        let view = bundle.feature_view(&cameras[i])?;
        total.raster += view.raster_seconds;
        tally.advance(1, "rasterize");
        for (target, (_, frames)) in targets.iter().zip(&mut out.outputs) {
            let frame = bundle.stylize(
                &view,
                target.stats.deepest(),
                settings.alpha,
                settings.tile_budget,
            )?;
            let s = frame.seconds;
            let img = frame.image;
            total.lift_transform += s.lift_transform;
            total.decode += s.decode;
            out.decoded += 1;
            let path = frame_path(out_dir, &target.name, i);
            image_io::write_png(&path, &img)?;
            frames.push(path);
            tally.advance(1, "decode");
        }
    }
    let views = range.len().max(1) as f64;
    let n = out.decoded.max(1) as f64;
    out.seconds = StageSeconds {
        raster: total.raster / views,
        lift_transform: total.lift_transform / n,
        decode: total.decode / n,
    };

    if let Part::Shard { shard, invocation } = part {
        let files = out
            .outputs
            .iter()
            .flat_map(|(_, frames)| frames)
            .map(|p| crate::shard::record_file(out_dir, p))
            .collect::<Result<Vec<_>>>()?;
        let manifest = crate::shard::Manifest {
            format: crate::shard::MANIFEST_FORMAT.into(),
            command: SHARD_COMMAND.into(),
            shard: *shard,
            items: cameras.len(),
            range,
            fingerprint,
            invocation: invocation.clone(),
            files,
            seconds: started.elapsed().as_secs_f64(),
            data: serde_json::Value::Null,
        };
        out.manifest = Some(crate::shard::write_manifest(
            &shard_dir(out_dir),
            &manifest,
        )?);
        tally.finish();
        return Ok(out);
    }

    // The animations and the contact sheet, from the frames on disk. The sheet's first column
    // shows each row's style (white for the colour row, black for a mixture of several
    // styles); its cells are the frames, reduced if the sheet would be too large.
    let sheet_idx = evenly_spaced(cameras.len(), settings.sheet_views.max(1));
    let sheet_colour = colour_renders(bundle, cameras, &sheet_idx)?;
    let (cw, ch) = image_io::sheet_cell_size(
        cameras[0].intrinsics.width,
        cameras[0].intrinsics.height,
        1 + sheet_idx.len(),
        1 + targets.len(),
    );
    let cell = |img: &RgbImage| resize(&image_io::clamped(img), cw, ch);
    let corner = RgbImage {
        width: cw,
        height: ch,
        data: vec![1.0; cw as usize * ch as usize * 3],
    };
    let mut sheet_rows = vec![std::iter::once(corner)
        .chain(sheet_colour.iter().map(|r| cell(&r.image)))
        .collect::<Vec<_>>()];
    for (t, target) in targets.iter().enumerate() {
        let mut row = vec![match (settings.weights.is_some(), styles.get(t)) {
            (false, Some(st)) => image_io::thumbnail(&st.image, cw, ch),
            _ => image_io::blank(cw, ch),
        }];
        for &i in &sheet_idx {
            let img = image_io::load_image(&frame_path(out_dir, &target.name, i))?;
            row.push(cell(&img));
        }
        if settings.gif {
            // One frame in memory at a time, whatever the length of the sequence.
            let p = out_dir.join(format!("{}.gif", target.name));
            let bytes = image_io::encode_gif_with(cameras.len(), settings.fps, |i| {
                let img = image_io::load_image(&frame_path(out_dir, &target.name, i))?;
                Ok(std::borrow::Cow::Owned(img))
            })?;
            base::write_atomic(&p, &bytes).with_context(|| format!("writing {}", p.display()))?;
            out.gifs.push(p);
        }
        if let Some(ff) = &ffmpeg {
            let p = out_dir.join(format!("{}.mp4", target.name));
            image_io::encode_mp4(ff, &out_dir.join(&target.name), settings.fps, &p)?;
            out.mp4s.push(p);
        }
        sheet_rows.push(row);
    }
    let sheet = image_io::contact_sheet(&sheet_rows)?;
    let sheet_path = out_dir.join("contact_sheet.png");
    image_io::write_png(&sheet_path, &sheet)?;
    out.contact_sheet = Some(sheet_path);
    tally.finish();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_stems() {
        let p: Vec<PathBuf> = ["a/x.jpg", "b/x.png", "y.jpg", "colour.jpg"]
            .iter()
            .map(PathBuf::from)
            .collect();
        assert_eq!(style_names(&p), vec!["x", "x_2", "y", "colour_2"]);
    }

    #[test]
    fn weights_are_checked_and_normalised() {
        assert_eq!(
            normalised_weights(&[1.0, 3.0], 2).unwrap(),
            vec![0.25, 0.75]
        );
        assert!(normalised_weights(&[1.0], 2).is_err());
        assert!(normalised_weights(&[1.0, -1.0], 2).is_err());
        assert!(normalised_weights(&[0.0, 0.0], 2).is_err());
    }
}
