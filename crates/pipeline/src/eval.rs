//! `dsgs eval`: multi-view consistency, style and content losses, and stage timings of
//! stylized sequences (metrics defined in [`crate::consistency`]).
//!
//! For a bundle and styles, every camera is rendered once in colour (which also gives the depth
//! and alpha the warps use) and once as a feature map; each output (the plain colour render,
//! then each style or the mixture) is compared along the sequence at short range (`j = i + 1`)
//! and long range (`j = i + 7`). Per stylized output also:
//!
//! * style loss: `style::style_loss` of the output's encoder features (the bundle's encoder at
//!   its variant, as the style statistics were computed) against the target's statistics at
//!   every level, averaged over views;
//! * content loss: the mean squared difference of the deepest features of the output and of the
//!   plain colour render of the same view, averaged over views.
//!
//! Frames are decoded in tiles within the tile budget, and encoded for the two losses and the
//! perceptual distance whole when the budget allows, else tile by tile ([`FrameLosses`],
//! [`crate::consistency::perceptual_distance`]).
//!
//! Existing frames (e.g. baked renders) are evaluated the same way against the geometry of a
//! `.ply` or a bundle ([`evaluate_frames`]); the perceptual distance then needs a bundle's
//! encoder.
//!
//! Both stream the sequence ([`StreamedConsistency`]): each view is rendered (or read),
//! stylized and compared with the views before it once, and only the last `LONG_RANGE + 1`
//! views' images, depths and alphas are kept, so memory does not grow with the number of
//! frames. The results are those of comparing the whole sequence in memory, bit for bit. With
//! colour preservation, the views of its content ([`COLOUR_VIEWS`] evenly spaced ones) are
//! rendered in colour once more before the stream starts.

use std::path::{Path, PathBuf};

use crate::error::{bail, Context, Result};
use gaussian::dataset::images::image_size;
use gaussian::Camera;
use ndarray::Array4;
use nets::Encoder;
use serde::{Deserialize, Serialize};
use style::{ChannelMoments, ChannelStats};
use train::SceneBundle;

use crate::cameras::evenly_spaced;
use crate::consistency::{RangeMetrics, StreamFrame, StreamedConsistency, WarpOptions};
use crate::image_io::{self, nchw_from_rgb, RgbImage};
use crate::render::{render_colour, SceneInput};
use crate::stylize::{self, StageSeconds, COLOUR_VIEWS};
use crate::{Sink, Stage, Tally};

/// Offsets along the sequence of the short- and long-range comparisons: short range compares
/// view `i` with `i + 1`.
pub const SHORT_RANGE: usize = 1;
/// The long-range offset: view `i` is compared with `i + 7`.
pub const LONG_RANGE: usize = 7;

/// The metrics of one output sequence.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OutputReport {
    /// The output: `colour` (the plain colour render), a style's name, `mix` (a mixture), or
    /// the name of an evaluated frames directory.
    pub name: String,
    /// Consistency of the pairs `(i, i + SHORT_RANGE)`.
    pub short_range: RangeMetrics,
    /// Consistency of the pairs `(i, i + LONG_RANGE)`.
    pub long_range: RangeMetrics,
    /// Style loss against the target's statistics, averaged over views (stylized outputs only).
    pub style_loss: Option<f64>,
    /// Content loss against the plain colour render's deepest features, averaged over views
    /// (stylized outputs only).
    pub content_loss: Option<f64>,
}

/// The report of `dsgs eval`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalReport {
    /// The evaluated scene: the bundle's name, or the path of the `.ply` or bundle whose
    /// geometry the frames were evaluated against.
    pub scene: String,
    /// The network variant of the stylization (`None` for existing frames).
    pub variant: Option<String>,
    /// The style strength (`None` for existing frames).
    pub alpha: Option<f64>,
    /// Views in the sequence.
    pub frames: usize,
    /// Image width of the views, in pixels.
    pub width: u32,
    /// Image height of the views, in pixels.
    pub height: u32,
    /// The masking thresholds of the warps.
    pub warp: WarpOptions,
    /// The metrics of each output sequence: for a bundle the colour render first, then each
    /// style or the mixture.
    pub outputs: Vec<OutputReport>,
    /// Mean seconds per view of each stage (stylized outputs only).
    pub seconds_per_view: Option<StageSeconds>,
}

/// Settings of a bundle evaluation.
#[derive(Clone, Debug)]
pub struct EvalSettings {
    /// The style images (`--style`, repeated).
    pub styles: Vec<PathBuf>,
    /// Mix the styles with these weights into one output, one per style (`--mix`).
    pub weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style (`--alpha`).
    pub alpha: f64,
    /// Match the style images' colours to the colour renders (`--preserve-colour`).
    pub preserve_colour: bool,
    /// Longest side of the style images after loading (`--style-size`).
    pub style_side: u32,
    /// Masking thresholds of the warps (`--alpha-threshold`, `--depth-tolerance`).
    pub warp: WarpOptions,
    /// Working memory of the networks while decoding a frame, in bytes (`--tile-budget`, in
    /// MiB; see [`stylize::stylize_view`]).
    pub tile_budget: u64,
}

/// The offsets every output is compared at, short range first.
const OFFSETS: [usize; 2] = [SHORT_RANGE, LONG_RANGE];

/// A stream comparing `outputs` sequences at short and long range.
fn stream<'e>(
    outputs: usize,
    warp: &WarpOptions,
    encoder: Option<&'e Encoder<f32>>,
) -> Result<StreamedConsistency<'e>> {
    StreamedConsistency::new(outputs, &OFFSETS, *warp, encoder)
}

/// The short- and long-range metrics of each output of a finished stream.
fn ranges(stream: StreamedConsistency) -> Vec<(RangeMetrics, RangeMetrics)> {
    stream.finish().into_iter().map(|r| (r[0], r[1])).collect()
}

fn check_same_size(cameras: &[Camera]) -> Result<(u32, u32)> {
    let Some(first) = cameras.first() else {
        bail!("no cameras to evaluate");
    };
    let k = first.intrinsics;
    if cameras
        .iter()
        .any(|c| (c.intrinsics.width, c.intrinsics.height) != (k.width, k.height))
    {
        bail!("the cameras differ in image size; give --width and --height");
    }
    Ok((k.width, k.height))
}

/// The style and content losses of the decoded frames of one view: the style loss against a
/// style's per-level statistics, the content loss against the deepest encoding of the view's
/// colour render.
///
/// When one tile of the budget covers every level of the frame's encoding, the frames are
/// encoded whole (`style::style_loss`, `style::content_loss`). Otherwise each level is encoded
/// tile by tile (`Encoder::forward_region`, the same features bit for bit): its statistics are
/// accumulated over the tiles ([`style::ChannelMoments`]) and the content loss's squared
/// differences summed in `f64`, so no full-frame feature map is held; the losses then differ from
/// the whole-frame ones only by the `f64` rounding of the other summation order.
pub struct FrameLosses<'e> {
    encoder: &'e Encoder<f32>,
    colour: Array4<f32>,
    /// The colour render's deepest level, when frames are encoded whole.
    colour_deepest: Option<Array4<f32>>,
    tile_budget: u64,
}

impl<'e> FrameLosses<'e> {
    /// The losses of frames of the same size as `colour`, the view's colour render.
    pub fn new(encoder: &'e Encoder<f32>, colour: &RgbImage, tile_budget: u64) -> Result<Self> {
        let colour = nchw_from_rgb(colour);
        let hw = (colour.dim().2, colour.dim().3);
        let colour_deepest = if crate::consistency::encodes_whole(encoder, hw, tile_budget)? {
            Some(
                encoder
                    .forward(colour.view())?
                    .pop()
                    .expect("encoder depth >= 1"),
            )
        } else {
            None
        };
        Ok(FrameLosses {
            encoder,
            colour,
            colour_deepest,
            tile_budget,
        })
    }

    /// Whether frames are encoded tile by tile.
    pub fn tiled(&self) -> bool {
        self.colour_deepest.is_none()
    }

    /// `(style loss, content loss)` of the decoded frame `image`.
    pub fn of(&self, image: &RgbImage, style: &[ChannelStats<f32>]) -> Result<(f64, f64)> {
        let x = nchw_from_rgb(image);
        if x.dim() != self.colour.dim() {
            bail!(
                "a frame of {}x{} evaluated against a colour render of {}x{}",
                x.dim().3,
                x.dim().2,
                self.colour.dim().3,
                self.colour.dim().2
            );
        }
        if let Some(colour_deepest) = &self.colour_deepest {
            let f = self.encoder.forward(x.view())?;
            let style_loss = style::style_loss(&f, style)? as f64;
            let content =
                style::content_loss(f.last().expect("encoder depth >= 1"), colour_deepest)?;
            return Ok((style_loss, content as f64));
        }
        let enc = self.encoder;
        let hw = (x.dim().2, x.dim().3);
        let depth = enc.depth();
        let mut stats = Vec::with_capacity(depth);
        let (mut squares, mut count) = (0.0f64, 0usize);
        for level in 1..=depth {
            let (oh, ow) = enc.output_size(hw, level)?;
            let (bytes, halo) = enc.tile_cost(hw, level)?;
            let side = nets::tiled::tile_side(self.tile_budget, bytes, halo, oh, ow);
            let mut moments = None;
            for r in nets::tiled::grid(oh, ow, side) {
                let need = enc.input_region(hw, level, r)?;
                let encode = |img: &Array4<f32>| {
                    let part = nets::tiled::crop(img.view(), &need);
                    enc.forward_region(part.view(), hw, level, r)
                };
                let f = encode(&x)?;
                moments
                    .get_or_insert_with(|| ChannelMoments::new(f.dim().0, f.dim().1))
                    .add(&f)?;
                if level == depth {
                    let fc = encode(&self.colour)?;
                    squares += f
                        .iter()
                        .zip(fc.iter())
                        .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
                        .sum::<f64>();
                    count += f.len();
                }
            }
            stats.push(moments.expect("a level has at least one tile").stats()?);
        }
        let style_loss = style::style_loss_of_stats(&stats, style)? as f64;
        // Rounded to `f32` as the whole-frame content loss is.
        let content = (squares / count as f64) as f32;
        Ok((style_loss, content as f64))
    }
}

/// Renders and evaluates the stylized sequences of a bundle, reporting one
/// [`Stage::Evaluate`] unit per rendered or decoded view to `sink`.
pub fn evaluate_bundle(
    bundle: &SceneBundle,
    scene_name: &str,
    cameras: &[Camera],
    settings: &EvalSettings,
    sink: &dyn Sink,
) -> Result<EvalReport> {
    stylize::check_style_settings(
        settings.alpha,
        settings.weights.as_deref(),
        settings.styles.len(),
    )?;
    crate::cameras::check_camera_sizes(cameras)?;
    let (width, height) = check_same_size(cameras)?;
    let styles = stylize::load_styles(&settings.styles, settings.style_side)?;
    let outputs = if settings.weights.is_some() {
        1
    } else {
        styles.len()
    };
    let content = if settings.preserve_colour {
        // The colour content needs a few views before the stream starts; rendering is
        // deterministic, so these are the stream's own colour renders of those views.
        let renders =
            stylize::colour_renders(bundle, cameras, &evenly_spaced(cameras.len(), COLOUR_VIEWS))?;
        let imgs: Vec<&RgbImage> = renders.iter().map(|r| &r.image).collect();
        Some(stylize::colour_content(&imgs)?)
    } else {
        None
    };
    let targets = stylize::style_targets(
        bundle,
        &styles,
        settings.weights.as_deref(),
        content.as_ref(),
    )?;
    let encoder = &bundle.encoder;
    let mut tally = Tally::start(Stage::Evaluate, cameras.len() * (1 + outputs), sink);
    let mut stream = stream(1 + targets.len(), &settings.warp, Some(encoder))?
        .with_tile_budget(settings.tile_budget);
    let mut seconds = StageSeconds::default();
    let mut decoded = 0usize;
    // Per target: the sums over the views of the style and content losses, in view order.
    let mut sums = vec![(0.0f64, 0.0f64); targets.len()];
    for c in cameras {
        let colour = render_colour(&bundle.scene, c, bundle.info.background)?;
        let features = stylize::render_feature_view(bundle, c)?;
        tally.advance(1, "render");
        let colour_image = image_io::clamped(&colour.image);
        let losses = FrameLosses::new(encoder, &colour_image, settings.tile_budget)?;
        let mut images = Vec::with_capacity(1 + targets.len());
        images.push(colour_image);
        for (target, (style_sum, content_sum)) in targets.iter().zip(&mut sums) {
            let (img, s) = stylize::stylize_view(
                bundle,
                &features,
                target,
                settings.alpha,
                settings.tile_budget,
            )?;
            seconds.raster += s.raster;
            seconds.lift_transform += s.lift_transform;
            seconds.decode += s.decode;
            decoded += 1;
            let (style_loss, content_loss) = losses.of(&img, &target.stats.levels)?;
            *style_sum += style_loss;
            *content_sum += content_loss;
            images.push(img);
            tally.advance(1, "decode");
        }
        drop(features);
        stream.push(StreamFrame {
            camera: *c,
            depth: colour.depth,
            alpha: colour.alpha,
            images,
        })?;
    }
    let mut ranges = ranges(stream).into_iter();
    let (short, long) = ranges.next().expect("the colour output");
    let mut reports = vec![OutputReport {
        name: "colour".into(),
        short_range: short,
        long_range: long,
        style_loss: None,
        content_loss: None,
    }];
    let views = cameras.len() as f64;
    for ((target, (style_sum, content_sum)), (short, long)) in targets.iter().zip(sums).zip(ranges)
    {
        reports.push(OutputReport {
            name: target.name.clone(),
            short_range: short,
            long_range: long,
            style_loss: Some(style_sum / views),
            content_loss: Some(content_sum / views),
        });
    }
    let n = decoded.max(1) as f64;
    tally.finish();
    Ok(EvalReport {
        scene: scene_name.to_string(),
        variant: Some(bundle.info.variant.as_str().to_string()),
        alpha: Some(settings.alpha),
        frames: cameras.len(),
        width,
        height,
        warp: settings.warp,
        outputs: reports,
        seconds_per_view: Some(StageSeconds {
            raster: seconds.raster / n,
            lift_transform: seconds.lift_transform / n,
            decode: seconds.decode / n,
        }),
    })
}

/// The PNG files of a directory, sorted by name.
pub fn frame_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("reading the frames directory {}", dir.display()))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{}: no .png frames", dir.display());
    }
    Ok(files)
}

/// Evaluates existing frames (`*.png` of `frames_dir`, in name order, one per camera) against
/// the geometry of `scene`. Every frame's size is read from its header before the first is
/// evaluated, so a frame of the wrong size or a file that is not an image is reported at once.
pub fn evaluate_frames(
    scene: &SceneInput,
    cameras: &[Camera],
    frames_dir: &Path,
    warp: &WarpOptions,
    sink: &dyn Sink,
) -> Result<EvalReport> {
    let (width, height) = check_same_size(cameras)?;
    let files = frame_files(frames_dir)?;
    if files.len() != cameras.len() {
        bail!(
            "{}: {} frames for {} cameras (match --cameras/--frames to the frames)",
            frames_dir.display(),
            files.len(),
            cameras.len()
        );
    }
    for f in &files {
        let (w, h) = image_size(f)?;
        if (w, h) != (width, height) {
            bail!(
                "{}: frame is {w}x{h}, the cameras are {width}x{height}",
                f.display()
            );
        }
    }
    let encoder = match scene {
        SceneInput::Bundle { bundle, .. } => Some(&bundle.encoder),
        SceneInput::Ply { .. } => None,
    };
    let mut tally = Tally::start(Stage::Evaluate, files.len(), sink);
    let mut stream = stream(1, warp, encoder)?;
    for (f, c) in files.iter().zip(cameras) {
        let img = image_io::load_image(f)?;
        if (img.width, img.height) != (width, height) {
            bail!(
                "{}: frame is {}x{}, the cameras are {width}x{height}",
                f.display(),
                img.width,
                img.height
            );
        }
        let geometry = render_colour(scene.gaussians(), c, scene.background())?;
        stream.push(StreamFrame {
            camera: *c,
            depth: geometry.depth,
            alpha: geometry.alpha,
            images: vec![img],
        })?;
        tally.advance(1, "render");
    }
    let (short, long) = ranges(stream)[0];
    let name = frames_dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "frames".into());
    tally.finish();
    Ok(EvalReport {
        scene: scene.path().display().to_string(),
        variant: None,
        alpha: None,
        frames: cameras.len(),
        width,
        height,
        warp: *warp,
        outputs: vec![OutputReport {
            name,
            short_range: short,
            long_range: long,
            style_loss: None,
            content_loss: None,
        }],
        seconds_per_view: None,
    })
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".into(), |x| format!("{x:.digits$}"))
}

/// A short text table of a report.
pub fn table(r: &EvalReport) -> String {
    let mut s = format!(
        "{} frames at {}x{}; consistency: masked RMSE (RGB in [0,1]) / perceptual distance, \
         short range j=i+{SHORT_RANGE}, long range j=i+{LONG_RANGE}\n",
        r.frames, r.width, r.height
    );
    s += &format!(
        "{:<16} {:>10} {:>10} {:>10} {:>10} {:>11} {:>11}\n",
        "output", "short rmse", "short perc", "long rmse", "long perc", "style loss", "content"
    );
    for o in &r.outputs {
        s += &format!(
            "{:<16} {:>10} {:>10} {:>10} {:>10} {:>11} {:>11}\n",
            o.name,
            opt(o.short_range.rmse, 5),
            opt(o.short_range.perceptual, 5),
            opt(o.long_range.rmse, 5),
            opt(o.long_range.perceptual, 5),
            opt(o.style_loss, 4),
            opt(o.content_loss, 4)
        );
    }
    if let Some(t) = &r.seconds_per_view {
        s += &format!(
            "seconds per view: raster {:.4}, lift+transform {:.4}, decode {:.4}\n",
            t.raster, t.lift_transform, t.decode
        );
    }
    s
}

/// Writes the report as JSON (atomically).
pub fn write_report(path: &Path, r: &EvalReport) -> Result<()> {
    let json = serde_json::to_vec_pretty(r).context("serialising the report")?;
    base::write_atomic(path, &json).with_context(|| format!("writing {}", path.display()))
}
