//! Stylized frames of a scene bundle: the one place where a view is rendered, lifted,
//! transformed and decoded.
//!
//! A stylized view, top down ([`SceneBundle::frame`], or [`SceneBundle::feature_view`] once per
//! camera and [`SceneBundle::stylize`] once per style):
//!
//! 1. Rasterize the features at the *feature resolution*: the image size reduced by the
//!    encoder's pooling for the standard variant, the image size itself for fullres
//!    ([`SceneBundle::feature_size`]). The camera's intrinsics are rescaled to that size. The
//!    rasterizer's image is HWC; it becomes the networks' NCHW here, the one layout change of
//!    a frame on its way in ([`render_feature_map`]).
//! 2. Lift: `l = relu(W r + b)` ([`nets::Lifter`]).
//! 3. Transform: `t = std_s * l + mean_s`, with the style's deepest-level statistics. Strength
//!    `alpha` interpolates the target statistics between the scene's own mean statistics
//!    ([`BundleInfo::scene_mean`](crate::BundleInfo::scene_mean),
//!    [`BundleInfo::scene_std`](crate::BundleInfo::scene_std), measured on the training
//!    views) and the style's, so `alpha = 0` reconstructs the scene
//!    ([`SceneBundle::target_stats`]). A bundle of the design ablation
//!    ([`FeatureNorm::AfterRaster`]) first normalises the
//!    lifted map with its own per-channel mean and std over the whole view
//!    ([`SceneBundle::view_stats`]): `t = std_s * (l - mean_l) / std_l + mean_s`.
//! 4. Decode and crop to the requested image size (the standard decoder's upsampling can
//!    overshoot by up to `2^levels - 1` pixels), one output tile at a time within a memory
//!    budget ([`SceneBundle::decode_in_tiles`]); the frame is the same, bit for bit, for any
//!    budget.
//! 5. Clamp to `[0, 1]` into an RGB image, row-major with interleaved channels ([`Frame`]), the
//!    one layout change on the way out.

use std::time::Instant;

use gaussian::dataset::images::RgbImage;
use gaussian::{Camera, FeatureGaussians};
use ndarray::{s, Array2, Array4};
use raster::{render, Channels, RenderOptions};
use serde::{Deserialize, Serialize};
use style::{ChannelMoments, ChannelStats, FeatureNorm};

use crate::bundle::SceneBundle;
use crate::error::RuntimeError;

/// Default working memory of the networks while decoding a frame ([`SceneBundle::decode`]):
/// 1 GiB, in which the fullres relu3_1 decoder takes tiles of about 300x300 pixels.
pub const DEFAULT_TILE_BUDGET_BYTES: u64 = 1 << 30;

/// Rows of the feature map lifted at a time by [`SceneBundle::view_stats`].
pub const VIEW_STATS_ROWS: usize = 16;

/// A camera's rasterized feature map, kept so that every further style of the same view costs
/// only the lift, the transform and the decode.
#[derive(Clone, Debug)]
pub struct FeatureView {
    /// The camera.
    pub camera: Camera,
    /// The rasterized feature map, `[1, F, h, w]` at the feature resolution.
    pub features: Array4<f32>,
    /// Wall time of the rasterization, in seconds.
    pub raster_seconds: f64,
}

/// Wall time of the stages of one decoded view, in seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageSeconds {
    /// Rasterizing the feature map.
    pub raster: f64,
    /// Lifting the feature map and transforming it to the style's statistics.
    pub lift_transform: f64,
    /// Decoding the transformed features into an image.
    pub decode: f64,
}

/// A stylized view.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The image, the camera's size, values clamped to `[0, 1]`.
    pub image: RgbImage,
    /// Wall time of each stage.
    pub seconds: StageSeconds,
}

impl SceneBundle {
    /// The stylized view of `camera` under the style's deepest-level statistics `style` at
    /// strength `alpha` (in `[0, 1]`), decoded in tiles within about `tile_budget` bytes of
    /// network memory (the frame does not depend on it): [`SceneBundle::feature_view`] then
    /// [`SceneBundle::stylize`].
    pub fn frame(
        &self,
        camera: &Camera,
        style: &ChannelStats<f32>,
        alpha: f64,
        tile_budget: u64,
    ) -> Result<Frame, RuntimeError> {
        self.stylize(&self.feature_view(camera)?, style, alpha, tile_budget)
    }

    /// Rasterizes the feature map of `camera`, timed.
    pub fn feature_view(&self, camera: &Camera) -> Result<FeatureView, RuntimeError> {
        let t = Instant::now();
        let features = self.render_features(camera)?;
        Ok(FeatureView {
            camera: *camera,
            features,
            raster_seconds: t.elapsed().as_secs_f64(),
        })
    }

    /// Lifts, transforms and decodes a feature view under the style's deepest-level
    /// statistics `style` at strength `alpha` ([`SceneBundle::target_stats`]), in tiles within
    /// about `tile_budget` bytes ([`SceneBundle::decode_in_tiles`]), clamped to `[0, 1]`.
    pub fn stylize(
        &self,
        view: &FeatureView,
        style: &ChannelStats<f32>,
        alpha: f64,
        tile_budget: u64,
    ) -> Result<Frame, RuntimeError> {
        let stats = self.target_stats(style, alpha)?;
        let k = view.camera.intrinsics;
        let (image, [lift_transform, decode]) =
            self.decode_in_tiles(&view.features, &stats, k.width, k.height, tile_budget)?;
        Ok(Frame {
            image: rgb_clamped(&image)?,
            seconds: StageSeconds {
                raster: view.raster_seconds,
                lift_transform,
                decode,
            },
        })
    }

    /// Rasterizes the features seen by `camera` at the feature resolution: `[1, F, h, w]`, with
    /// the camera of [`SceneBundle::feature_camera`].
    pub fn render_features(&self, camera: &Camera) -> Result<Array4<f32>, RuntimeError> {
        let feature_camera = self.feature_camera(camera);
        let k = feature_camera.intrinsics;
        render_feature_map(
            &self.scene,
            &feature_camera,
            (k.width, k.height),
            &self.info.feature_background,
            self.info.supersample,
        )
    }

    /// The target statistics for strength `alpha`: `alpha * style + (1 - alpha) * scene`.
    pub fn target_stats(
        &self,
        style: &ChannelStats<f32>,
        alpha: f64,
    ) -> Result<ChannelStats<f32>, RuntimeError> {
        if !(0.0..=1.0).contains(&alpha) {
            return Err(RuntimeError::Config(format!(
                "style strength {alpha} is outside [0, 1] (0: the scene as it is, 1: the full style)"
            )));
        }
        let c = self.lifter.out_channels();
        if style.channels() != c || style.batch() != 1 {
            return Err(RuntimeError::Shape(format!(
                "style statistics are {}x{}, expected 1x{c}",
                style.batch(),
                style.channels()
            )));
        }
        let a = alpha as f32;
        let mix = |s: &Array2<f32>, scene: &[f32]| {
            Array2::from_shape_fn((1, c), |(_, j)| a * s[[0, j]] + (1.0 - a) * scene[j])
        };
        Ok(ChannelStats::new(
            mix(&style.mean, &self.info.scene_mean),
            mix(&style.std, &self.info.scene_std),
        )?)
    }

    /// The per-channel mean and std of the lifted feature map over the whole view, which a
    /// bundle of the design ablation ([`FeatureNorm::AfterRaster`]) normalises with; `None`
    /// for the paper's design. The map is lifted [`VIEW_STATS_ROWS`] rows at a time and the
    /// moments merged in row order ([`ChannelMoments`]), so the result does not depend on how
    /// the frame is decoded.
    pub fn view_stats(
        &self,
        features: &Array4<f32>,
    ) -> Result<Option<ChannelStats<f32>>, RuntimeError> {
        if self.info.normalize == FeatureNorm::BeforeRaster {
            return Ok(None);
        }
        let (n, _, fh, _) = features.dim();
        let mut moments = ChannelMoments::new(n, self.lifter.out_channels());
        for y0 in (0..fh).step_by(VIEW_STATS_ROWS) {
            let band = features.slice(s![.., .., y0..(y0 + VIEW_STATS_ROWS).min(fh), ..]);
            let lifted = self.lifter.forward(band)?;
            moments.add(&lifted)?;
        }
        Ok(Some(moments.stats()?))
    }

    /// Lifts, transforms and decodes a feature map from [`SceneBundle::render_features`] into
    /// an RGB image `[1, 3, height, width]` (cropped; values as the decoder makes them), in
    /// tiles within [`DEFAULT_TILE_BUDGET_BYTES`] ([`SceneBundle::decode_in_tiles`]).
    pub fn decode(
        &self,
        features: &Array4<f32>,
        stats: &ChannelStats<f32>,
        width: u32,
        height: u32,
    ) -> Result<Array4<f32>, RuntimeError> {
        Ok(self
            .decode_in_tiles(features, stats, width, height, DEFAULT_TILE_BUDGET_BYTES)?
            .0)
    }

    /// The side of the square output tiles [`SceneBundle::decode_in_tiles`] uses for a
    /// feature map of `feature_hw` decoded to `width x height` within `budget_bytes`.
    pub fn decode_tile_side(
        &self,
        feature_hw: (usize, usize),
        width: u32,
        height: u32,
        budget_bytes: u64,
    ) -> usize {
        let (oh, ow) = self.decoder.output_size(feature_hw);
        let (decoder_bytes, halo) = self.decoder.tile_cost(feature_hw);
        // The lifted map and its transform live beside the features' crop, at the features'
        // resolution.
        let scale = (feature_hw.0 * feature_hw.1) as f64 / (oh * ow).max(1) as f64;
        let lift_bytes =
            scale * 4.0 * (self.lifter.in_channels() + 2 * self.lifter.out_channels()) as f64;
        nets::tiled::tile_side(
            budget_bytes,
            decoder_bytes + lift_bytes,
            halo,
            height as usize,
            width as usize,
        )
    }

    /// Lifts, transforms and decodes a feature map into an RGB image `[1, 3, height, width]`
    /// (cropped; values as the decoder makes them) one output tile at a time, the tile side
    /// chosen so that the networks' working memory stays within about `budget_bytes`
    /// ([`SceneBundle::decode_tile_side`]); also returns the wall time of lift + transform and
    /// of the decoder, in seconds.
    ///
    /// A stylized frame, top down: [`SceneBundle::render_features`] (rasterize the per-Gaussian
    /// features at the feature resolution), then here, per tile of the image: crop the
    /// features to the region the decoder needs for the tile ([`nets::Decoder::input_region`]), lift
    /// to the encoder width, transform with the target statistics
    /// (`T(x) = std(s) x + mean(s)`, from [`SceneBundle::target_stats`]), decode the tile
    /// ([`nets::Decoder::forward_region`]). Lifting and the transform act on each pixel alone and the
    /// decoder's tiles equal the whole image's ([`nets::tiled`]), so the image is the same,
    /// bit for bit, for any budget; no map wider than the features covers the whole frame.
    /// A bundle of the design ablation normalises each lifted tile with the statistics of the
    /// whole view ([`SceneBundle::view_stats`]) before the transform.
    pub fn decode_in_tiles(
        &self,
        features: &Array4<f32>,
        stats: &ChannelStats<f32>,
        width: u32,
        height: u32,
        budget_bytes: u64,
    ) -> Result<(Array4<f32>, [f64; 2]), RuntimeError> {
        let (_, _, fh, fw) = features.dim();
        let (oh, ow) = self.decoder.output_size((fh, fw));
        let (th, tw) = (height as usize, width as usize);
        if oh < th || ow < tw {
            return Err(RuntimeError::Shape(format!(
                "decoded image is {ow}x{oh}, smaller than the requested {tw}x{th}"
            )));
        }
        let side = self.decode_tile_side((fh, fw), width, height, budget_bytes);
        let t0 = Instant::now();
        let view_stats = self.view_stats(features)?;
        let stats_seconds = t0.elapsed().as_secs_f64();
        let mut image = Array4::<f32>::zeros((1, self.decoder.out_channels(), th, tw));
        let mut seconds = [stats_seconds, 0.0];
        for r in nets::tiled::grid(th, tw, side) {
            let t0 = Instant::now();
            let need = self.decoder.input_region((fh, fw), r)?;
            let part = nets::tiled::crop(features.view(), &need);
            let mut lifted = self.lifter.forward(part.view())?;
            drop(part);
            if let Some(v) = &view_stats {
                lifted = style::normalize(&lifted, v)?;
            }
            let t = style::style_transform(&lifted, stats)?;
            drop(lifted);
            let t1 = Instant::now();
            let y = self.decoder.forward_region(t.view(), (fh, fw), r)?;
            image
                .slice_mut(s![.., .., r.y0..r.y1, r.x0..r.x1])
                .assign(&y);
            let t2 = Instant::now();
            seconds[0] += (t1 - t0).as_secs_f64();
            seconds[1] += (t2 - t1).as_secs_f64();
        }
        Ok((image, seconds))
    }
}

/// Crops `[N, C, H', W']` to `[N, C, height, width]` (top-left), failing if it is smaller.
pub fn crop(image: Array4<f32>, width: u32, height: u32) -> Result<Array4<f32>, RuntimeError> {
    let (h, w) = (image.shape()[2], image.shape()[3]);
    let (th, tw) = (height as usize, width as usize);
    if h < th || w < tw {
        return Err(RuntimeError::Shape(format!(
            "decoded image is {w}x{h}, smaller than the requested {tw}x{th}"
        )));
    }
    if h == th && w == tw {
        return Ok(image);
    }
    Ok(image.slice(s![.., .., ..th, ..tw]).to_owned())
}

/// Rasterizes `scene`'s features from `camera`, with the intrinsics rescaled to `size`: each
/// pixel the mean of a `supersample x supersample` block of a render that much finer
/// ([`raster::supersample`]; 1: one sample per pixel).
pub fn render_feature_map(
    scene: &FeatureGaussians<f32>,
    camera: &Camera,
    size: (u32, u32),
    background: &[f32],
    supersample: u32,
) -> Result<Array4<f32>, RuntimeError> {
    let s = supersample;
    let cam = camera.resized(size.0 * s, size.1 * s);
    let opts = RenderOptions::new(Channels::Features, background.to_vec());
    let out = render(&cam, scene, &opts)?;
    let f = scene.feature_dim;
    let (w, h) = (size.0 as usize, size.1 as usize);
    let img = raster::supersample::box_mean(&out.raster.image, w, h, f, s as usize)?;
    // The rasterizer's image is HWC; the networks take NCHW.
    Ok(Array4::from_shape_fn((1, f, h, w), |(_, c, y, x)| {
        img[(y * w + x) * f + c]
    }))
}

/// `[1, 3, H, W]` as an RGB image clamped to `[0, 1]`; an image of another shape is an error.
pub fn rgb_clamped(image: &Array4<f32>) -> Result<RgbImage, RuntimeError> {
    let (n, c, h, w) = image.dim();
    if n != 1 || c != 3 {
        return Err(RuntimeError::Shape(format!(
            "a colour image is 1x3xHxW; the decoder made {n}x{c}x{h}x{w}"
        )));
    }
    let mut rgb = Vec::with_capacity(3 * h * w);
    for y in 0..h {
        for x in 0..w {
            for ch in 0..3 {
                rgb.push(image[[0, ch, y, x]].clamp(0.0, 1.0));
            }
        }
    }
    Ok(RgbImage {
        width: w as u32,
        height: h as u32,
        data: rgb,
    })
}
