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
//! Existing frames (e.g. baked renders) are evaluated the same way against the geometry of a
//! `.ply` or a bundle ([`evaluate_frames`]); the perceptual distance then needs a bundle's
//! encoder.

use std::path::{Path, PathBuf};

use crate::error::{bail, Context, Result};
use gaussian::Camera;
use nets::Encoder;
use serde::Serialize;
use train::SceneBundle;

use crate::cameras::evenly_spaced;
use crate::consistency::{sequence_consistency, DepthView, RangeMetrics, WarpOptions};
use crate::image_io::{self, nchw_from_rgb, RgbImage};
use crate::render::{render_colour, ColourRender, SceneInput};
use crate::stylize::{self, StageSeconds, COLOUR_VIEWS};
use crate::{Sink, Stage, Tally};

/// Offsets along the sequence of the short- and long-range comparisons: short range compares
/// view `i` with `i + 1`.
pub const SHORT_RANGE: usize = 1;
/// The long-range offset: view `i` is compared with `i + 7`.
pub const LONG_RANGE: usize = 7;

/// The metrics of one output sequence.
#[derive(Clone, Debug, Serialize)]
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
#[derive(Clone, Debug, Serialize)]
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
    /// Mix the styles with these weights into one output, one per style (`--weights`).
    pub weights: Option<Vec<f64>>,
    /// Style strength: 0 reconstructs the scene, 1 is the full style (`--alpha`).
    pub alpha: f64,
    /// Match the style images' colours to the colour renders (`--preserve-colour`).
    pub preserve_colour: bool,
    /// Longest side of the style images after loading (`--style-size`).
    pub style_side: u32,
    /// Masking thresholds of the warps (`--alpha-threshold`, `--depth-tolerance`).
    pub warp: WarpOptions,
}

fn depth_views<'a>(cameras: &'a [Camera], renders: &'a [ColourRender]) -> Vec<DepthView<'a>> {
    cameras
        .iter()
        .zip(renders)
        .map(|(camera, r)| DepthView {
            camera,
            depth: &r.depth,
            alpha: &r.alpha,
        })
        .collect()
}

fn ranges(
    images: &[RgbImage],
    views: &[DepthView],
    warp: &WarpOptions,
    encoder: Option<&Encoder<f32>>,
) -> Result<(RangeMetrics, RangeMetrics)> {
    Ok((
        sequence_consistency(images, views, SHORT_RANGE, warp, encoder)?,
        sequence_consistency(images, views, LONG_RANGE, warp, encoder)?,
    ))
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

/// Renders and evaluates the stylized sequences of a bundle, reporting one
/// [`Stage::Evaluate`] unit per rendered or decoded view to `sink`.
pub fn evaluate_bundle(
    bundle: &SceneBundle,
    scene_name: &str,
    cameras: &[Camera],
    settings: &EvalSettings,
    sink: &dyn Sink,
) -> Result<EvalReport> {
    let (width, height) = check_same_size(cameras)?;
    let styles = stylize::load_styles(&settings.styles, settings.style_side)?;
    let outputs = if settings.weights.is_some() {
        1
    } else {
        styles.len()
    };
    let mut tally = Tally::start(Stage::Evaluate, cameras.len() * (1 + outputs), sink);
    let mut colour = Vec::with_capacity(cameras.len());
    let mut features = Vec::with_capacity(cameras.len());
    for c in cameras {
        colour.push(render_colour(&bundle.scene, c, bundle.info.background)?);
        features.push(stylize::render_feature_view(bundle, c)?);
        tally.advance(1, "render");
    }
    let content = if settings.preserve_colour {
        let imgs: Vec<&RgbImage> = evenly_spaced(cameras.len(), COLOUR_VIEWS)
            .into_iter()
            .map(|i| &colour[i].image)
            .collect();
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
    let views = depth_views(cameras, &colour);
    let colour_images: Vec<RgbImage> = colour.iter().map(|r| image_io::clamped(&r.image)).collect();
    let encoder = &bundle.encoder;
    let colour_deepest = colour_images
        .iter()
        .map(|img| {
            let f = encoder.forward(nchw_from_rgb(img).view())?;
            Ok(f.into_iter().last().expect("encoder depth >= 1"))
        })
        .collect::<Result<Vec<_>>>()?;
    let (short, long) = ranges(&colour_images, &views, &settings.warp, Some(encoder))?;
    let mut outputs = vec![OutputReport {
        name: "colour".into(),
        short_range: short,
        long_range: long,
        style_loss: None,
        content_loss: None,
    }];
    let mut seconds = StageSeconds::default();
    let mut decoded = 0usize;
    for target in &targets {
        let mut frames = Vec::with_capacity(cameras.len());
        let (mut style_sum, mut content_sum) = (0.0f64, 0.0f64);
        for (v, colour_feat) in features.iter().zip(&colour_deepest) {
            let (img, s) = stylize::stylize_view(bundle, v, target, settings.alpha)?;
            seconds.raster += s.raster;
            seconds.lift_transform += s.lift_transform;
            seconds.decode += s.decode;
            decoded += 1;
            let f = encoder.forward(nchw_from_rgb(&img).view())?;
            style_sum += style::style_loss(&f, &target.stats.levels)? as f64;
            content_sum +=
                style::content_loss(f.last().expect("encoder depth >= 1"), colour_feat)? as f64;
            frames.push(img);
            tally.advance(1, "decode");
        }
        let (short, long) = ranges(&frames, &views, &settings.warp, Some(encoder))?;
        let n = frames.len() as f64;
        outputs.push(OutputReport {
            name: target.name.clone(),
            short_range: short,
            long_range: long,
            style_loss: Some(style_sum / n),
            content_loss: Some(content_sum / n),
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
        outputs,
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
/// the geometry of `scene`.
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
    let mut tally = Tally::start(Stage::Evaluate, files.len(), sink);
    let mut frames = Vec::with_capacity(files.len());
    let mut geometry = Vec::with_capacity(files.len());
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
        frames.push(img);
        geometry.push(render_colour(scene.gaussians(), c, scene.background())?);
        tally.advance(1, "render");
    }
    let views = depth_views(cameras, &geometry);
    let encoder = match scene {
        SceneInput::Bundle { bundle, .. } => Some(&bundle.encoder),
        SceneInput::Ply { .. } => None,
    };
    let (short, long) = ranges(&frames, &views, warp, encoder)?;
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
