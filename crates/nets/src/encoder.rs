//! The normalised VGG-19 encoder: a 1x1 input conv (RGB in `[0,1]` to the mean-subtracted BGR the
//! VGG weights expect), then levels of 3x3 reflection-padded conv + ReLU blocks with a 2x2
//! max-pool between levels, up to `relu{depth}_1`. It returns the `relu{k}_1` features for
//! `k = 1..=depth`, the activations the AdaIN style loss compares.
//!
//! The fullres variant ([`Resolution::Fullres`]) skips the max-pools, so every feature has the
//! input's resolution; the weights are the same.

use std::path::Path;

use base::Real;
use ndarray::{Array4, ArrayView4};

use crate::error::NetError;
use crate::layer::{ConvGrad, ConvLayer};
use crate::layout::{encoder_spec, read_conv, EncoderSpec};
use crate::pool::PoolRounding;
use crate::sequential::{self, Step, Tape};
use crate::state_dict::StateDict;
use crate::tiled::{self, Region};
use crate::Resolution;

/// The VGG encoder to `relu{depth}_1`.
#[derive(Clone, Debug)]
pub struct Encoder<T: Real = f32> {
    input_conv: ConvLayer<T>,
    /// `levels[k-1]` = the convs of level `k` that run; the last level holds only `conv{depth}_1`.
    levels: Vec<Vec<ConvLayer<T>>>,
    pool: PoolRounding,
    resolution: Resolution,
}

/// What [`Encoder::backward`] needs from a forward pass: the ReLU masks (one bit per element)
/// and the max-pool arg-maxes. Conv inputs are not kept (the encoder is frozen).
#[derive(Clone, Debug)]
pub struct EncoderTape<T: Real = f32>(Tape<T>);

impl<T: Real> Encoder<T> {
    /// Builds the encoder from a state dict in the Sequential (AdaIN/WCT) or named (compressed)
    /// layout, to the deepest `relu{k}_1` the weights reach (e.g. `relu5_1` for the whole
    /// `vgg_normalised.pth`, `relu3_1` for `vgg_normalised_conv3_1.pth`); use
    /// [`Encoder::with_depth`] to stop earlier. Widths come from the weights.
    pub fn from_state_dict(sd: &StateDict) -> Result<Encoder<T>, NetError> {
        Self::from_spec(sd, encoder_spec(sd, None)?)
    }

    /// Imports a PyTorch checkpoint (`.pth`, legacy or zip format) and builds the network from
    /// it as [`Encoder::from_state_dict`] does. Errors name the file.
    pub fn from_checkpoint(path: &Path) -> Result<Encoder<T>, NetError> {
        let sd = crate::checkpoint::load_checkpoint(path)?;
        Self::from_state_dict(&sd).map_err(|e| NetError::File {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })
    }

    pub(crate) fn from_spec(sd: &StateDict, spec: EncoderSpec) -> Result<Encoder<T>, NetError> {
        let input_conv: ConvLayer<T> = read_conv(sd, &spec.input, 1, None)?;
        let mut c = input_conv.out_channels();
        let mut levels = Vec::new();
        for (k, lv) in spec.levels.iter().enumerate() {
            // Levels before the last must be complete; the last one only needs conv{k}_1.
            let take = if k + 1 == spec.levels.len() {
                1
            } else {
                lv.len()
            };
            let mut convs = Vec::with_capacity(take);
            for r in &lv[..take] {
                let layer: ConvLayer<T> = read_conv(sd, r, 3, Some(c))?;
                c = layer.out_channels();
                convs.push(layer);
            }
            levels.push(convs);
        }
        Ok(Encoder {
            input_conv,
            levels,
            pool: spec.pool,
            resolution: Resolution::Standard,
        })
    }

    /// The deepest feature level (`relu{depth}_1`).
    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// Channels of `relu{k}_1` for `k = 1..=depth`.
    pub fn widths(&self) -> Vec<usize> {
        self.levels.iter().map(|lv| lv[0].out_channels()).collect()
    }

    /// Input channels (3 for images).
    pub fn in_channels(&self) -> usize {
        self.input_conv.in_channels()
    }

    /// Number of 3x3 convs per level (the last level has one).
    pub fn convs_per_level(&self) -> Vec<usize> {
        self.levels.iter().map(Vec::len).collect()
    }

    /// How max-pooling rounds odd sizes.
    pub fn pool_rounding(&self) -> PoolRounding {
        self.pool
    }

    /// Standard or fullres.
    pub fn resolution(&self) -> Resolution {
        self.resolution
    }

    /// The same encoder cut at `relu{depth}_1`.
    pub fn with_depth(mut self, depth: usize) -> Result<Encoder<T>, NetError> {
        if depth == 0 || depth > self.depth() {
            return Err(NetError::Input(format!(
                "encoder depth {depth} requested, the weights reach relu{}_1",
                self.depth()
            )));
        }
        self.levels.truncate(depth);
        self.levels[depth - 1].truncate(1);
        Ok(self)
    }

    /// The same weights with the given resolution variant.
    pub fn with_resolution(mut self, resolution: Resolution) -> Encoder<T> {
        self.resolution = resolution;
        self
    }

    /// All convs in execution order (`conv0`, `conv1_1`, ...).
    pub fn layers(&self) -> impl Iterator<Item = &ConvLayer<T>> {
        std::iter::once(&self.input_conv).chain(self.levels.iter().flatten())
    }

    /// All convs in execution order, mutably. Changing a shape breaks the network.
    pub fn layers_mut(&mut self) -> impl Iterator<Item = &mut ConvLayer<T>> {
        std::iter::once(&mut self.input_conv).chain(self.levels.iter_mut().flatten())
    }

    /// The same encoder in another precision.
    pub fn cast<U: Real>(&self) -> Encoder<U> {
        Encoder {
            input_conv: self.input_conv.cast(),
            levels: self
                .levels
                .iter()
                .map(|lv| lv.iter().map(ConvLayer::cast).collect())
                .collect(),
            pool: self.pool,
            resolution: self.resolution,
        }
    }

    fn steps(&self) -> Vec<Step<'_, T>> {
        let mut steps = vec![Step::Conv {
            layer: &self.input_conv,
            relu: false,
        }];
        for (k, lv) in self.levels.iter().enumerate() {
            if k > 0 && self.resolution == Resolution::Standard {
                steps.push(Step::Pool(self.pool));
            }
            for (j, layer) in lv.iter().enumerate() {
                steps.push(Step::Conv { layer, relu: true });
                if j == 0 {
                    steps.push(Step::Output);
                }
            }
        }
        steps
    }

    /// The steps up to the output of `relu{level}_1`.
    fn steps_to(&self, level: usize) -> Result<Vec<Step<'_, T>>, NetError> {
        if level == 0 || level > self.depth() {
            return Err(NetError::Input(format!(
                "encoder: level {level} asked of an encoder to relu{}_1",
                self.depth()
            )));
        }
        let mut steps = self.steps();
        let mut outputs = 0;
        let end = steps
            .iter()
            .position(|s| {
                outputs += matches!(s, Step::Output) as usize;
                outputs == level
            })
            .expect("one output per level");
        steps.truncate(end + 1);
        Ok(steps)
    }

    /// The size `(height, width)` of `relu{level}_1` for an image of `input_hw`.
    pub fn output_size(
        &self,
        input_hw: (usize, usize),
        level: usize,
    ) -> Result<(usize, usize), NetError> {
        let steps = self.steps_to(level)?;
        let dims = sequential::check_shapes(
            &steps,
            (1, self.in_channels(), input_hw.0, input_hw.1),
            "encoder",
        )?;
        let (_, _, h, w) = *dims.last().expect("one output per level");
        Ok((h, w))
    }

    /// The region of an image of `input_hw` that the region `out` of `relu{level}_1` depends on
    /// (see [`crate::tiled`]).
    pub fn input_region(
        &self,
        input_hw: (usize, usize),
        level: usize,
        out: Region,
    ) -> Result<Region, NetError> {
        let steps = self.steps_to(level)?;
        Ok(tiled::plan(&steps, self.in_channels(), input_hw, out, "encoder")?[0])
    }

    /// The region `out` of `relu{level}_1` of an image of `input_hw`, from `x`, which holds the
    /// image's region [`Encoder::input_region`]: equal to that region of the feature from
    /// [`Encoder::forward`] of the whole image, holding only the tile's activations.
    pub fn forward_region(
        &self,
        x: ArrayView4<T>,
        input_hw: (usize, usize),
        level: usize,
        out: Region,
    ) -> Result<Array4<T>, NetError> {
        let steps = self.steps_to(level)?;
        let regions = tiled::plan(&steps, self.in_channels(), input_hw, out, "encoder")?;
        tiled::run_regions(&steps, &regions, x, "encoder")
    }

    /// `relu{level}_1` of [`Encoder::forward`], computed one output tile of at most
    /// `tile x tile` pixels at a time (the same result, see [`crate::tiled`]).
    pub fn forward_tiled(
        &self,
        x: ArrayView4<T>,
        level: usize,
        tile: usize,
    ) -> Result<Array4<T>, NetError> {
        tiled::run_tiled(&self.steps_to(level)?, x, tile, "encoder")
    }

    /// The working memory of a tile of `relu{level}_1` per pixel of its region and halo, in
    /// bytes, for an image of `input_hw`, and the halo in output pixels (see
    /// [`tiled::tile_side`]).
    pub fn tile_cost(
        &self,
        input_hw: (usize, usize),
        level: usize,
    ) -> Result<(f64, usize), NetError> {
        let steps = self.steps_to(level)?;
        Ok((
            tiled::bytes_per_output_pixel(&steps, input_hw),
            tiled::halo(&steps, input_hw),
        ))
    }

    /// The features `relu1_1 ..= relu{depth}_1` of a batch `x [N, 3, H, W]`.
    pub fn forward(&self, x: ArrayView4<T>) -> Result<Vec<Array4<T>>, NetError> {
        Ok(sequential::forward(&self.steps(), x, false, false, "encoder")?.0)
    }

    /// [`Encoder::forward`], also returning the tape for [`Encoder::backward`].
    pub fn forward_with_tape(
        &self,
        x: ArrayView4<T>,
    ) -> Result<(Vec<Array4<T>>, EncoderTape<T>), NetError> {
        let (feats, tape) = sequential::forward(&self.steps(), x, true, false, "encoder")?;
        Ok((feats, EncoderTape(tape.expect("tape requested"))))
    }

    /// The gradient with respect to the input of `sum_k <cotangents[k-1], relu{k}_1>`: give a
    /// cotangent (same shape as the feature) for any subset of the levels, `None` for the others;
    /// the slice may be shorter than the depth. Levels deeper than the deepest cotangent cost
    /// nothing.
    pub fn backward(
        &self,
        tape: &EncoderTape<T>,
        cotangents: &[Option<ArrayView4<T>>],
    ) -> Result<Array4<T>, NetError> {
        Ok(sequential::backward(&self.steps(), &tape.0, cotangents, false, "encoder")?.input)
    }

    /// Like [`Encoder::backward`], also returning the gradients of every conv's parameters (in
    /// [`Encoder::layers`] order). Needs a tape from [`Encoder::forward_with_param_tape`].
    pub fn backward_with_params(
        &self,
        tape: &EncoderTape<T>,
        cotangents: &[Option<ArrayView4<T>>],
    ) -> Result<(Array4<T>, Vec<ConvGrad<T>>), NetError> {
        let b = sequential::backward(&self.steps(), &tape.0, cotangents, true, "encoder")?;
        Ok((b.input, b.params))
    }

    /// [`Encoder::forward_with_tape`] that also keeps every conv input, as parameter gradients
    /// need (more memory).
    pub fn forward_with_param_tape(
        &self,
        x: ArrayView4<T>,
    ) -> Result<(Vec<Array4<T>>, EncoderTape<T>), NetError> {
        let (feats, tape) = sequential::forward(&self.steps(), x, true, true, "encoder")?;
        Ok((feats, EncoderTape(tape.expect("tape requested"))))
    }
}
