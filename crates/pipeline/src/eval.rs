//! `dsgs eval`: multi-view consistency, style and content losses, and stage timings of
//! stylized sequences (metrics defined in [`crate::consistency`]).
//!
//! For a bundle and styles, every camera is rendered once in colour (which also gives the depth
//! and alpha the warps use) and once as a feature map; each output is compared along the
//! sequence at short range (`j = i + 1`) and long range (`j = i + 7`). The outputs: the plain
//! colour render (the floor the warp itself reaches, from resampling and view-dependent colour;
//! the only output without styles), then per style or mixture its per-frame 2D baseline
//! (`2d:NAME`, [`baseline_view`]: each colour render stylized on its own, as a 2D method would;
//! with [`EvalSettings::baseline`]) and the stylized frames. The report states the mean step
//! between consecutive views ([`crate::cameras::path_step`]): figures compare only between
//! sequences of the same step (the program's default path is the dense arc of
//! [`crate::cameras::CameraSource::Dense`]). Per stylized output also:
//!
//! * style loss: `style::style_loss` of the output's encoder features (the bundle's encoder at
//!   its variant, as the style statistics were computed) against the target's statistics at
//!   every level, averaged over views;
//! * texture distance: `style::gram_distance_of` between the Gram matrices of the output's
//!   encoder features and of the style image's at every level (the same encoder), averaged over
//!   views: what the style loss's channel means and deviations cannot see, e.g. one texture
//!   given to every painting. For a mixture, the target Gram matrices are the styles' mixed
//!   with the mixture's weights;
//! * texture distance between outputs: the same Gram distance between the frames of every two
//!   of dsgs's outputs (and of every two 2D baselines) of the same view, averaged over views
//!   ([`EvalReport::texture_between`]): near 0 when different paintings give one texture;
//! * content loss: the mean squared difference of the deepest features of the output and of the
//!   plain colour render of the same view, averaged over views.
//!
//! Frames are decoded in tiles within the tile budget, and encoded for the three measures and the
//! perceptual distance whole when the budget allows, else tile by tile ([`FrameLosses`],
//! [`crate::consistency::perceptual_distance`]).
//!
//! With [`EvalSettings::measure_with`] another encoder measures all of them (the targets'
//! statistics and Gram matrices too): the measures of bundles with different networks compare
//! only when one encoder measured them all.
//!
//! With [`EvalSettings::frames_out`] every evaluated frame is also written as a PNG, and the
//! comparison sheet [`COMPARISON_SHEET`] (colour | 2D per-frame | dsgs for each painting, the
//! same views) is made from them.
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
use ndarray::{Array2, Array4};
use nets::Encoder;
use runtime::SceneBundle;
use serde::{Deserialize, Serialize};
use style::{ChannelMoments, ChannelStats, GramSums};

use crate::cameras::evenly_spaced;
use crate::consistency::{
    range_metrics, PairRecord, RangeMetrics, StreamFrame, StreamedConsistency, WarpOptions,
};
use crate::image_io::{self, nchw_from_rgb, RgbImage};
use crate::render::{render_colour, SceneInput};
use crate::shard::{Part, Shard};
use crate::stylize::{self, COLOUR_VIEWS};
use crate::weights::MeasuringEncoder;
use crate::{Sink, Stage, Tally};
use runtime::StageSeconds;

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
    /// Texture distance to the style image's Gram matrices, averaged over views (stylized
    /// outputs only; absent from reports written before it was measured).
    #[serde(default)]
    pub texture_distance: Option<f64>,
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
    /// How far apart consecutive views are on average (`None` for a single view): the metrics
    /// of a sequence can only be compared with those of sequences of the same step.
    #[serde(default)]
    pub path_step: Option<crate::cameras::PathStep>,
    /// The metrics of each output sequence: for a bundle the colour render first, then each
    /// style or the mixture.
    pub outputs: Vec<OutputReport>,
    /// Mean seconds per view of each stage (stylized outputs only).
    pub seconds_per_view: Option<StageSeconds>,
    /// The texture distance between the frames of every two of dsgs's outputs, and of every
    /// two 2D baselines, averaged over views: how different the textures of different
    /// paintings' outputs are (absent from reports written before it was measured).
    #[serde(default)]
    pub texture_between: Vec<TexturePair>,
    /// The comparison sheet written with the frames ([`EvalSettings::frames_out`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comparison: Option<PathBuf>,
    /// The file of the encoder that measured the outputs ([`EvalSettings::measure_with`]);
    /// `None`: the bundle's own encoder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_with: Option<String>,
}

/// The texture distance between two outputs of an evaluation ([`EvalReport::texture_between`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexturePair {
    /// One output's name.
    pub a: String,
    /// The other's.
    pub b: String,
    /// The mean over views of the Gram distance between their frames.
    pub distance: f64,
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
    /// MiB; see [`runtime::SceneBundle::stylize`]).
    pub tile_budget: u64,
    /// Also evaluate the per-frame 2D baseline of each style ([`baseline_view`]; on unless
    /// `--no-baseline`).
    pub baseline: bool,
    /// Also write every evaluated frame as a PNG under this folder (`colour/`, and per style
    /// `2d_NAME/` for its 2D baseline and `NAME/` for dsgs, each `frame_NNNN.png`), and, unless
    /// this is a shard, the comparison sheet [`COMPARISON_SHEET`] made from them.
    pub frames_out: Option<PathBuf>,
    /// The encoder that measures the style, texture and content losses and the perceptual
    /// distance (`--measure-with`, weights or a PyTorch checkpoint, at standard resolution)
    /// instead of the bundle's own: each encoder's levels have their own widths and scales, so
    /// the measures of bundles with different networks compare only when one encoder measured
    /// them all. The stylization itself always uses the bundle's networks.
    pub measure_with: Option<PathBuf>,
    /// The whole evaluation, one shard of it (`--shard K/N`: the losses of its block of views
    /// and the pairs that start in it, into a manifest), or the merge of the shards' partial
    /// results into the report (`dsgs assemble`).
    pub part: Part,
}

/// The name of the shard manifests of `dsgs eval` ([`crate::shard`]).
pub const SHARD_COMMAND: &str = "eval";

/// The folder of the shard manifests of an evaluation whose report goes to `report`: the same
/// path with the extension `shards` (`report.json` -> `report.shards`).
pub fn shard_dir(report: &Path) -> PathBuf {
    report.with_extension("shards")
}

/// The line of a finished shard of an evaluation of `views` views whose report goes to
/// `report`: its block of views and where its partial results are.
pub fn shard_line(shard: Shard, views: usize, report: &Path) -> String {
    let r = shard.range(views);
    format!(
        "shard {shard}: views {} to {} of {views} evaluated; partial results in {}\n",
        r.start,
        r.end.saturating_sub(1),
        shard_dir(report).display()
    )
}

/// A shard's partial results ([`crate::shard::Manifest::data`]): what the report adds up.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ShardSums {
    /// Per view of the shard's block, per stylized output: its measures.
    pub losses: Vec<Vec<FrameLoss>>,
    /// Per view of the shard's block, per pair of outputs compared (every two dsgs outputs,
    /// then every two 2D baselines): the texture distance between the two outputs' frames.
    #[serde(default)]
    pub between: Vec<Vec<f64>>,
    /// Per output (colour first), per offset (short, long): the pairs that start in the block.
    pub pairs: Vec<Vec<Vec<PairRecord>>>,
    /// Sums over the decoded views of the stage seconds.
    pub seconds: StageSeconds,
    /// Views decoded (views times targets, including the views after the block that its pairs
    /// reach).
    pub decoded: usize,
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

/// The measures of one decoded frame ([`FrameLosses::of`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameLoss {
    /// Style loss against the target's statistics.
    pub style: f64,
    /// Texture distance to the target's Gram matrices.
    pub texture: f64,
    /// Content loss against the colour render's deepest features.
    pub content: f64,
}

/// What a frame's style is measured against: a target's statistics (style loss) and Gram
/// matrices (texture distance) at every encoder level.
#[derive(Clone, Copy, Debug)]
pub struct StyleMeasures<'a> {
    /// The statistics, per level.
    pub stats: &'a [ChannelStats<f32>],
    /// The normalised Gram matrices, per level.
    pub grams: &'a [Array2<f64>],
}

/// The style loss, texture distance and content loss of the decoded frames of one view: the
/// style loss against a style's per-level statistics, the texture distance against its per-level
/// Gram matrices, the content loss against the deepest encoding of the view's colour render.
///
/// When one tile of the budget covers every level of the frame's encoding, the frames are
/// encoded whole (`style::style_loss`, `style::content_loss`). Otherwise each level is encoded
/// tile by tile (`Encoder::forward_region`, the same features bit for bit): its statistics are
/// accumulated over the tiles ([`style::ChannelMoments`], [`style::GramSums`]) and the content
/// loss's squared differences summed in `f64`, so no full-frame feature map is held; the
/// measures then differ from the whole-frame ones only by the `f64` rounding of the other
/// summation order.
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

    /// The measures of the decoded frame `image` against `style`.
    pub fn of(&self, image: &RgbImage, style: StyleMeasures) -> Result<FrameLoss> {
        Ok(self.measure(image, style)?.0)
    }

    /// [`FrameLosses::of`] and the frame's own Gram matrices at every level, for comparing
    /// frames with each other.
    pub fn measure(
        &self,
        image: &RgbImage,
        style: StyleMeasures,
    ) -> Result<(FrameLoss, Vec<Array2<f64>>)> {
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
            let style_loss = style::style_loss(&f, style.stats)? as f64;
            let grams = f
                .iter()
                .map(|l| style::gram(l, 0))
                .collect::<Result<Vec<_>, _>>()?;
            let content =
                style::content_loss(f.last().expect("encoder depth >= 1"), colour_deepest)?;
            let loss = FrameLoss {
                style: style_loss,
                texture: style::gram_distance_of(&grams, style.grams)?,
                content: content as f64,
            };
            return Ok((loss, grams));
        }
        let enc = self.encoder;
        let hw = (x.dim().2, x.dim().3);
        let depth = enc.depth();
        let mut stats = Vec::with_capacity(depth);
        let mut grams = Vec::with_capacity(depth);
        let (mut squares, mut count) = (0.0f64, 0usize);
        for level in 1..=depth {
            let (oh, ow) = enc.output_size(hw, level)?;
            let (bytes, halo) = enc.tile_cost(hw, level)?;
            let side = nets::tiled::tile_side(self.tile_budget, bytes, halo, oh, ow);
            let mut moments = None;
            let mut gram_sums = None;
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
                gram_sums
                    .get_or_insert_with(|| GramSums::new(f.dim().1))
                    .add(&f, 0)?;
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
            grams.push(gram_sums.expect("a level has at least one tile").gram()?);
        }
        let style_loss = style::style_loss_of_stats(&stats, style.stats)? as f64;
        // Rounded to `f32` as the whole-frame content loss is.
        let content = (squares / count as f64) as f32;
        let loss = FrameLoss {
            style: style_loss,
            texture: style::gram_distance_of(&grams, style.grams)?,
            content: content as f64,
        };
        Ok((loss, grams))
    }
}

/// The name of the plain colour render's output.
pub const COLOUR_OUTPUT: &str = "colour";

/// The name of output `o` of an evaluation: 0 the colour render, then the stylized outputs
/// (`stylized`, as [`stylized_outputs`] gives them) of `targets`.
fn output_name(targets: &[stylize::StyleTarget], stylized: &[(usize, bool)], o: usize) -> String {
    match o.checked_sub(1).map(|k| stylized[k]) {
        None => COLOUR_OUTPUT.into(),
        Some((t, true)) => format!("{BASELINE_PREFIX}{}", targets[t].name),
        Some((t, false)) => targets[t].name.clone(),
    }
}

/// The comparison sheet of an evaluation with `frames_out`: columns of evenly spaced views
/// (at most [`COMPARISON_VIEWS`]) after a first column of paintings; rows: the colour render,
/// then per style its per-frame 2D baseline (with the baseline) and dsgs's output.
pub const COMPARISON_SHEET: &str = "comparison.png";

/// The most views in the comparison sheet.
pub const COMPARISON_VIEWS: usize = 6;

/// The folder name of an output's frames under `frames_out`: the output's name, with the
/// baseline's `2d:` prefix written `2d_`.
pub fn frames_folder(output: &str) -> String {
    output.replace(':', "_")
}

/// Writes [`COMPARISON_SHEET`] under `dir` from the frames there: `names` are the outputs
/// after the colour render, `thumbs` the first cell of each of their rows.
fn write_comparison(
    dir: &Path,
    cameras: &[Camera],
    names: &[String],
    thumbs: &[Option<&RgbImage>],
) -> Result<PathBuf> {
    let views = evenly_spaced(cameras.len(), COMPARISON_VIEWS);
    let (cw, ch) = image_io::sheet_cell_size(
        cameras[0].intrinsics.width,
        cameras[0].intrinsics.height,
        1 + views.len(),
        1 + names.len(),
    );
    let row = |name: &str, first: RgbImage| -> Result<Vec<RgbImage>> {
        let mut row = vec![first];
        for &i in &views {
            let img = image_io::load_image(&stylize::frame_path(dir, &frames_folder(name), i))?;
            row.push(gaussian::dataset::images::resize(
                &image_io::clamped(&img),
                cw,
                ch,
            ));
        }
        Ok(row)
    };
    let white = RgbImage {
        width: cw,
        height: ch,
        data: vec![1.0; cw as usize * ch as usize * 3],
    };
    let mut rows = vec![row(COLOUR_OUTPUT, white)?];
    for (name, thumb) in names.iter().zip(thumbs) {
        let first = match thumb {
            Some(t) => image_io::thumbnail(t, cw, ch),
            None => image_io::blank(cw, ch),
        };
        rows.push(row(name, first)?);
    }
    let path = dir.join(COMPARISON_SHEET);
    image_io::write_png(&path, &image_io::contact_sheet(&rows)?)?;
    Ok(path)
}

/// The prefix of the name of a style's per-frame 2D baseline output (`2d:mondrian`).
pub const BASELINE_PREFIX: &str = "2d:";

/// The per-frame 2D baseline of a view: its colour render (clamped, `[0, 1]`) encoded, its
/// deepest features transformed by AdaIN with that frame's own statistics towards the target's
/// (`style::stylize` at strength `alpha`), and decoded whole by the bundle's decoder; clamped.
/// What a 2D method that sees each frame alone does, against which the view-consistent design
/// of the features is measured.
///
/// A standard encoder that pools with floor rounding (the compressed relu4_1 pair) drops the
/// last rows and columns of a side that is not a multiple of its total pooling `f`, and its
/// decoder would give back less than the frame: such a frame is extended to the next
/// multiple of `f` by repeating its last row and column ([`pad_to_multiple`]) before it is
/// encoded, and the decoded image cropped back to the frame.
pub fn baseline_view(
    bundle: &SceneBundle,
    colour: &RgbImage,
    target: &stylize::StyleTarget,
    alpha: f64,
) -> Result<RgbImage> {
    let (h, w) = (colour.height as usize, colour.width as usize);
    let floor = bundle.info.variant == runtime::Variant::Standard
        && bundle.encoder.pool_rounding() == nets::PoolRounding::Floor;
    let multiple = if floor {
        1usize << (bundle.encoder.depth().max(1) - 1)
    } else {
        1
    };
    let x = pad_to_multiple(nchw_from_rgb(colour), multiple);
    let y = style::stylize::stylize(
        &bundle.encoder,
        &bundle.decoder,
        &x,
        target.stats.deepest(),
        alpha,
    )?;
    let y = runtime::frame::crop(y, w as u32, h as u32)?;
    Ok(image_io::clamped(&image_io::rgb_from_nchw(&y)?))
}

/// `x` (`[N, C, H, W]`) extended at the bottom and right to sides that are multiples of
/// `multiple`, the new rows and columns repeating the last ones; `x` itself when they already
/// are.
pub fn pad_to_multiple(x: Array4<f32>, multiple: usize) -> Array4<f32> {
    let (n, c, h, w) = x.dim();
    let m = multiple.max(1);
    let (ph, pw) = (h.div_ceil(m) * m, w.div_ceil(m) * m);
    if (ph, pw) == (h, w) || h == 0 || w == 0 {
        return x;
    }
    Array4::from_shape_fn((n, c, ph, pw), |(b, k, y, xx)| {
        x[[b, k, y.min(h - 1), xx.min(w - 1)]]
    })
}

/// The texture targets, one per style target of [`stylize::style_targets`]: the normalised Gram
/// matrices of each style image's encoding at every level (after the same colour matching), or
/// for a mixture the styles' matrices mixed with its normalised weights.
fn target_grams(
    encoder: &Encoder<f32>,
    styles: &[stylize::StyleImage],
    weights: Option<&[f64]>,
    colour: Option<&Array4<f32>>,
) -> Result<Vec<Vec<Array2<f64>>>> {
    let mut each = Vec::with_capacity(styles.len());
    for s in styles {
        let img = stylize::style_input(s, colour)?;
        let f = encoder
            .forward(img.view())
            .with_context(|| format!("encoding the style {}", s.path.display()))?;
        each.push(
            f.iter()
                .map(|l| style::gram(l, 0))
                .collect::<Result<Vec<_>, _>>()?,
        );
    }
    let Some(w) = weights else {
        return Ok(each);
    };
    let w = stylize::normalised_weights(w, each.len())?;
    let mut mixed: Vec<Array2<f64>> = each[0].iter().map(|g| g * 0.0).collect();
    for (grams, wt) in each.iter().zip(w) {
        for (m, g) in mixed.iter_mut().zip(grams) {
            m.scaled_add(wt, g);
        }
    }
    Ok(vec![mixed])
}

/// The pairs of stylized outputs whose frames are compared with each other, as indices into
/// [`stylized_outputs`]: every two of dsgs's outputs, then every two of the per-frame 2D
/// baselines (so that "every painting gives the same texture" shows as a small distance).
fn output_pairs(stylized: &[(usize, bool)]) -> Vec<(usize, usize)> {
    let mut pairs = Vec::new();
    for baseline in [false, true] {
        let of: Vec<usize> = (0..stylized.len())
            .filter(|&k| stylized[k].1 == baseline)
            .collect();
        for (i, &a) in of.iter().enumerate() {
            pairs.extend(of[i + 1..].iter().map(|&b| (a, b)));
        }
    }
    pairs
}

/// The stylized outputs of an evaluation, after the colour render: per target its baseline
/// (with `baseline`) then itself, as `(target index, is the baseline)`.
fn stylized_outputs(targets: usize, baseline: bool) -> Vec<(usize, bool)> {
    (0..targets)
        .flat_map(|t| {
            let b = baseline.then_some((t, true));
            b.into_iter().chain(std::iter::once((t, false)))
        })
        .collect()
}

/// The fingerprint of an evaluation: the bundle, the cameras, the targets, the strength, the
/// warp thresholds and the tile budget (the losses of frames encoded in tiles differ from whole
/// ones in the last bits).
fn fingerprint(
    bundle: &SceneBundle,
    cameras: &[Camera],
    targets: &[stylize::StyleTarget],
    settings: &EvalSettings,
    measurer: Option<&MeasuringEncoder>,
) -> String {
    let mut h = base::Fnv1a::new();
    h.eat_str(SHARD_COMMAND);
    h.eat_str(&bundle.fingerprint());
    h.eat_u64(cameras.len() as u64);
    cameras.iter().for_each(|c| stylize::hash_camera(&mut h, c));
    stylize::hash_targets(&mut h, targets);
    h.eat_f64(settings.alpha);
    h.eat_f32(settings.warp.alpha_threshold);
    h.eat_f64(settings.warp.depth_tolerance);
    h.eat_u64(settings.tile_budget);
    h.eat_u64(settings.baseline as u64);
    if let Some(m) = measurer {
        h.eat_str(&m.fingerprint);
    }
    h.hex()
}

/// Renders and evaluates the stylized sequences of a bundle in one process (`settings.part`
/// must be [`Part::Whole`]; see [`evaluate_sharded`]), reporting one [`Stage::Evaluate`] unit
/// per rendered or decoded view to `sink`.
pub fn evaluate_bundle(
    bundle: &SceneBundle,
    scene_name: &str,
    cameras: &[Camera],
    settings: &EvalSettings,
    sink: &dyn Sink,
) -> Result<EvalReport> {
    if settings.part != Part::Whole {
        bail!("a shard or an assembly of an evaluation needs its report path (evaluate_sharded)");
    }
    Ok(evaluate(bundle, scene_name, cameras, settings, None, sink)?.expect("a whole run reports"))
}

/// [`evaluate_bundle`] for any part of a run whose report goes to `report`:
///
/// * [`Part::Whole`]: the report;
/// * [`Part::Shard`]: the losses of the shard's block of views and the pairs
///   `(i, i + offset)` that start in it (rendering the views up to `LONG_RANGE` past it), into
///   the manifest `{shard_dir(report)}/eval-K-of-N.json`; returns `Ok(None)`;
/// * [`Part::Assemble`]: the shards' partial results added up in sequence order: the
///   one-process report bit for bit, but for the measured seconds.
pub fn evaluate_sharded(
    bundle: &SceneBundle,
    scene_name: &str,
    cameras: &[Camera],
    settings: &EvalSettings,
    report: &Path,
    sink: &dyn Sink,
) -> Result<Option<EvalReport>> {
    let dir = shard_dir(report);
    evaluate(bundle, scene_name, cameras, settings, Some(&dir), sink)
}

fn evaluate(
    bundle: &SceneBundle,
    scene_name: &str,
    cameras: &[Camera],
    settings: &EvalSettings,
    shard_dir: Option<&Path>,
    sink: &dyn Sink,
) -> Result<Option<EvalReport>> {
    let started = std::time::Instant::now();
    stylize::check_style_settings(
        settings.alpha,
        settings.weights.as_deref(),
        settings.styles.len(),
    )?;
    crate::cameras::check_camera_sizes(cameras)?;
    stylize::check_view_sizes(bundle, cameras)?;
    let (width, height) = check_same_size(cameras)?;
    // Without styles only the colour render is evaluated: the floor the warp itself reaches.
    let styles = if settings.styles.is_empty() {
        Vec::new()
    } else {
        stylize::load_styles(&settings.styles, settings.style_side)?
    };
    let shard_dir = match (&settings.part, shard_dir) {
        (Part::Whole, _) => None,
        (_, Some(d)) => Some(d),
        (_, None) => bail!("a sharded evaluation needs a report path (--output REPORT.json)"),
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
    let measuring = settings
        .measure_with
        .as_deref()
        .map(crate::weights::load_measuring_encoder)
        .transpose()?;
    let encoder = measuring.as_ref().map_or(&bundle.encoder, |m| &m.encoder);
    // The targets' statistics as the measuring encoder sees them (the stylizing targets' own
    // when it is the bundle's).
    let measured_targets = match &measuring {
        Some(m) => stylize::mix_targets(
            stylize::encode_styles(&m.encoder, &styles, content.as_ref())?,
            settings.weights.as_deref(),
        )?,
        None => targets.clone(),
    };
    let grams = target_grams(
        encoder,
        &styles,
        settings.weights.as_deref(),
        content.as_ref(),
    )?;
    let measures = Measures {
        encoder,
        targets: &measured_targets,
        grams: &grams,
    };
    let fingerprint = fingerprint(bundle, cameras, &targets, settings, measuring.as_ref());
    let n = cameras.len();
    let sums: Vec<ShardSums> = match (&settings.part, shard_dir) {
        (Part::Assemble, Some(dir)) => {
            let manifests = crate::shard::collect(
                dir,
                &crate::shard::Expected {
                    command: SHARD_COMMAND,
                    fingerprint: &fingerprint,
                    items: n,
                    root: dir,
                },
            )?;
            manifests
                .into_iter()
                .map(|m| {
                    serde_json::from_value(m.data).with_context(|| {
                        format!(
                            "{}: the partial results of shard {} are not readable",
                            dir.display(),
                            m.shard
                        )
                    })
                })
                .collect::<Result<_>>()?
        }
        _ => {
            let block = settings.part.range(n);
            let views = block.start..(block.end + LONG_RANGE).min(n);
            let views = if block.is_empty() { 0..0 } else { views };
            let part = evaluate_block(
                bundle,
                cameras,
                &targets,
                &measures,
                settings,
                block.clone(),
                views,
                sink,
            )?;
            if let (Part::Shard { shard, invocation }, Some(dir)) = (&settings.part, shard_dir) {
                let manifest = crate::shard::Manifest {
                    format: crate::shard::MANIFEST_FORMAT.into(),
                    command: SHARD_COMMAND.into(),
                    shard: *shard,
                    items: n,
                    range: block,
                    fingerprint,
                    invocation: invocation.clone(),
                    files: Vec::new(),
                    seconds: started.elapsed().as_secs_f64(),
                    data: serde_json::to_value(&part).context("serialising the shard's sums")?,
                };
                crate::shard::write_manifest(dir, &manifest)?;
                return Ok(None);
            }
            vec![part]
        }
    };

    // The report: losses summed over the views in sequence order, pairs added in the order of
    // their first view, as one stream over the whole sequence adds them.
    let stylized = stylized_outputs(targets.len(), settings.baseline);
    let outputs = 1 + stylized.len();
    let views = n as f64;
    let mut reports = Vec::with_capacity(outputs);
    for o in 0..outputs {
        let range = |k: usize, offset: usize| {
            range_metrics(offset, sums.iter().flat_map(|s| &s.pairs[o][k]))
        };
        let mean = if o == 0 {
            None
        } else {
            let mut sum = FrameLoss::default();
            for l in sums.iter().flat_map(|s| &s.losses).map(|l| l[o - 1]) {
                sum.style += l.style;
                sum.texture += l.texture;
                sum.content += l.content;
            }
            Some(sum)
        };
        reports.push(OutputReport {
            name: output_name(&targets, &stylized, o),
            short_range: range(0, SHORT_RANGE),
            long_range: range(1, LONG_RANGE),
            style_loss: mean.map(|m| m.style / views),
            texture_distance: mean.map(|m| m.texture / views),
            content_loss: mean.map(|m| m.content / views),
        });
    }
    let names: Vec<String> = reports.iter().skip(1).map(|o| o.name.clone()).collect();
    let texture_between = output_pairs(&stylized)
        .iter()
        .enumerate()
        .map(|(k, &(a, b))| {
            let sum: f64 = sums.iter().flat_map(|s| &s.between).map(|v| v[k]).sum();
            TexturePair {
                a: names[a].clone(),
                b: names[b].clone(),
                distance: sum / views,
            }
        })
        .collect();
    let decoded: usize = sums.iter().map(|s| s.decoded).sum();
    let d = decoded.max(1) as f64;
    let total = |f: fn(&StageSeconds) -> f64| sums.iter().map(|s| f(&s.seconds)).sum::<f64>() / d;
    let comparison = match &settings.frames_out {
        Some(dir) if !cameras.is_empty() => {
            let names: Vec<String> = (1..=stylized.len())
                .map(|o| output_name(&targets, &stylized, o))
                .collect();
            // A painting's thumbnail beside its rows; blank for a mixture.
            let thumbs: Vec<Option<&RgbImage>> = stylized
                .iter()
                .map(|&(t, _)| {
                    settings
                        .weights
                        .is_none()
                        .then(|| styles.get(t).map(|s| &s.image))
                        .flatten()
                })
                .collect();
            Some(write_comparison(dir, cameras, &names, &thumbs)?)
        }
        _ => None,
    };
    Ok(Some(EvalReport {
        scene: scene_name.to_string(),
        variant: Some(bundle.info.variant.as_str().to_string()),
        alpha: Some(settings.alpha),
        frames: n,
        width,
        height,
        warp: settings.warp,
        path_step: crate::cameras::path_step(cameras),
        outputs: reports,
        seconds_per_view: (decoded > 0).then(|| StageSeconds {
            raster: total(|s| s.raster),
            lift_transform: total(|s| s.lift_transform),
            decode: total(|s| s.decode),
        }),
        texture_between,
        comparison,
        measured_with: measuring.map(|m| m.path),
    }))
}

/// What the outputs are measured with: the measuring encoder and, per target, its statistics
/// and Gram matrices at every level of that encoder.
struct Measures<'a> {
    encoder: &'a Encoder<f32>,
    targets: &'a [stylize::StyleTarget],
    grams: &'a [Vec<Array2<f64>>],
}

/// Renders, stylizes and compares the views `views` of the sequence: the losses of the views
/// in `block` and the pairs that start in it.
#[allow(clippy::too_many_arguments)]
fn evaluate_block(
    bundle: &SceneBundle,
    cameras: &[Camera],
    targets: &[stylize::StyleTarget],
    measures: &Measures,
    settings: &EvalSettings,
    block: std::ops::Range<usize>,
    views: std::ops::Range<usize>,
    sink: &dyn Sink,
) -> Result<ShardSums> {
    let encoder = measures.encoder;
    let stylized = stylized_outputs(targets.len(), settings.baseline);
    let mut tally = Tally::start(Stage::Evaluate, views.len() * (1 + stylized.len()), sink);
    let mut stream = stream(1 + stylized.len(), &settings.warp, Some(encoder))?
        .with_tile_budget(settings.tile_budget)
        .with_pairs(views.start, block.clone());
    let mut out = ShardSums::default();
    for (i, c) in cameras.iter().enumerate().take(views.end).skip(views.start) {
        let colour = render_colour(&bundle.scene, c, bundle.info.background)?;
        let features = bundle.feature_view(c)?;
        tally.advance(1, "render");
        let colour_image = image_io::clamped(&colour.image);
        let losses = block
            .contains(&i)
            .then(|| FrameLosses::new(encoder, &colour_image, settings.tile_budget))
            .transpose()?;
        let mut images = Vec::with_capacity(1 + stylized.len());
        let mut view_losses = Vec::with_capacity(stylized.len());
        let mut view_grams = Vec::with_capacity(stylized.len());
        for &(t, is_baseline) in &stylized {
            let target = &targets[t];
            let img = if is_baseline {
                baseline_view(bundle, &colour_image, target, settings.alpha)?
            } else {
                let frame = bundle.stylize(
                    &features,
                    target.stats.deepest(),
                    settings.alpha,
                    settings.tile_budget,
                )?;
                let (img, s) = (frame.image, frame.seconds);
                out.seconds.raster += s.raster;
                out.seconds.lift_transform += s.lift_transform;
                out.seconds.decode += s.decode;
                out.decoded += 1;
                img
            };
            if let Some(l) = &losses {
                let against = StyleMeasures {
                    stats: &measures.targets[t].stats.levels,
                    grams: &measures.grams[t],
                };
                let (loss, grams) = l.measure(&img, against)?;
                view_losses.push(loss);
                view_grams.push(grams);
            }
            images.push(img);
            tally.advance(1, "decode");
        }
        images.insert(0, colour_image);
        if let (Some(dir), true) = (&settings.frames_out, block.contains(&i)) {
            for (o, img) in images.iter().enumerate() {
                let name = frames_folder(&output_name(targets, &stylized, o));
                let path = stylize::frame_path(dir, &name, i);
                if let Some(parent) = path.parent() {
                    std::fs::create_dir_all(parent)
                        .with_context(|| format!("creating {}", parent.display()))?;
                }
                image_io::write_png(&path, img)?;
            }
        }
        if losses.is_some() {
            out.losses.push(view_losses);
            let between = output_pairs(&stylized)
                .iter()
                .map(|&(a, b)| style::gram_distance_of(&view_grams[a], &view_grams[b]))
                .collect::<Result<Vec<_>, _>>()?;
            out.between.push(between);
        }
        drop(features);
        stream.push(StreamFrame {
            camera: *c,
            depth: colour.depth,
            alpha: colour.alpha,
            images,
        })?;
    }
    out.pairs = stream.pair_records().to_vec();
    if out.pairs.is_empty() {
        out.pairs = vec![vec![Vec::new(); OFFSETS.len()]; 1 + stylized.len()];
    }
    tally.finish();
    Ok(out)
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
/// The perceptual distance uses the encoder of `measure_with` when given, else the bundle's
/// (none for a `.ply`).
pub fn evaluate_frames(
    scene: &SceneInput,
    cameras: &[Camera],
    frames_dir: &Path,
    warp: &WarpOptions,
    measure_with: Option<&Path>,
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
    let measuring = measure_with
        .map(crate::weights::load_measuring_encoder)
        .transpose()?;
    let encoder = match (&measuring, scene) {
        (Some(m), _) => Some(&m.encoder),
        (None, SceneInput::Bundle { bundle, .. }) => Some(&bundle.encoder),
        (None, SceneInput::Ply { .. }) => None,
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
        path_step: crate::cameras::path_step(cameras),
        outputs: vec![OutputReport {
            name,
            short_range: short,
            long_range: long,
            style_loss: None,
            texture_distance: None,
            content_loss: None,
        }],
        seconds_per_view: None,
        texture_between: Vec::new(),
        comparison: None,
        measured_with: measuring.map(|m| m.path),
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
    if let Some(p) = r.path_step {
        s += &format!(
            "consecutive views {:.3} degrees and {:.4} scene units apart on average\n",
            p.degrees, p.distance
        );
    }
    // The name column fits the longest name (a painting's file name can be long).
    let w = r
        .outputs
        .iter()
        .map(|o| o.name.chars().count())
        .max()
        .unwrap_or(0)
        .max(16);
    s += &format!(
        "{:<w$} {:>10} {:>10} {:>10} {:>10} {:>11} {:>11} {:>11}\n",
        "output",
        "short rmse",
        "short perc",
        "long rmse",
        "long perc",
        "style loss",
        "texture",
        "content"
    );
    for o in &r.outputs {
        s += &format!(
            "{:<w$} {:>10} {:>10} {:>10} {:>10} {:>11} {:>11} {:>11}\n",
            o.name,
            opt(o.short_range.rmse, 5),
            opt(o.short_range.perceptual, 5),
            opt(o.long_range.rmse, 5),
            opt(o.long_range.perceptual, 5),
            opt(o.style_loss, 4),
            opt(o.texture_distance, 4),
            opt(o.content_loss, 4)
        );
    }
    for p in &r.texture_between {
        s += &format!(
            "texture distance between {} and {}: {:.4}\n",
            p.a, p.b, p.distance
        );
    }
    if let Some(m) = &r.measured_with {
        s += &format!("losses and perceptual distances measured with the encoder of {m}\n");
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
