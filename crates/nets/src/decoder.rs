//! The decoder that inverts the encoder: levels of 3x3 reflection-padded conv + ReLU from the
//! deepest level up, with nearest 2x upsampling between levels, and no activation after the last
//! conv unless the weights say so (the compressed decoder has one).
//!
//! The fullres variant ([`Resolution::Fullres`]) skips the upsamplings; the weights are the same.
//!
//! A *pointwise* decoder ([`Decoder::pointwise`]) has one level of 1x1 convs: a per-pixel MLP
//! from features to colour, with no spatial context and no upsampling (the MLP decoder of the
//! paper's decoder ablation). It decodes a feature map to an image of the same size.

use std::path::Path;

use base::Real;
use ndarray::{Array4, ArrayView4};

use crate::error::NetError;
use crate::layer::{ConvGrad, ConvLayer};
use crate::layout::{decoder_spec, read_conv, DecoderSpec};
use crate::sequential::{self, Step, Tape};
use crate::state_dict::StateDict;
use crate::tiled::{self, Region};
use crate::Resolution;

/// The decoder from `relu{depth}_1` features to an image.
#[derive(Clone, Debug)]
pub struct Decoder<T: Real = f32> {
    /// Deepest level first.
    levels: Vec<Vec<ConvLayer<T>>>,
    final_relu: bool,
    resolution: Resolution,
}

/// What [`Decoder::backward`] needs from a forward pass: every conv input and the ReLU masks.
#[derive(Clone, Debug)]
pub struct DecoderTape<T: Real = f32>(Tape<T>);

/// Gradients of a scalar loss through the decoder.
#[derive(Clone, Debug)]
pub struct DecoderGrads<T: Real = f32> {
    /// With respect to the decoder input.
    pub input: Array4<T>,
    /// With respect to each conv's weight and bias, in [`Decoder::layers`] order.
    pub params: Vec<ConvGrad<T>>,
}

impl<T: Real> Decoder<T> {
    /// Builds the decoder from a state dict in the Sequential (AdaIN/WCT) or named (compressed)
    /// layout. Depth and widths come from the weights.
    pub fn from_state_dict(sd: &StateDict) -> Result<Decoder<T>, NetError> {
        Self::from_spec(sd, decoder_spec(sd, None)?, 3)
    }

    /// Imports a PyTorch checkpoint (`.pth`, legacy or zip format) and builds the network from
    /// it as [`Decoder::from_state_dict`] does. Errors name the file.
    pub fn from_checkpoint(path: &Path) -> Result<Decoder<T>, NetError> {
        let sd = crate::checkpoint::load_checkpoint(path)?;
        Self::from_state_dict(&sd).map_err(|e| NetError::File {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })
    }

    /// A pointwise decoder: the given 1x1 convs run in order as one level, each but the last
    /// followed by a ReLU (and the last too when `final_relu`). Each conv must take the
    /// previous one's output width; names must be distinct (they key the weights file, see
    /// [`crate::weights_file`]: `conv1_{n}` down to `conv1_1` for `n` convs fits the canonical
    /// layout).
    pub fn pointwise(layers: Vec<ConvLayer<T>>, final_relu: bool) -> Result<Decoder<T>, NetError> {
        if layers.is_empty() {
            return Err(NetError::Input(
                "a pointwise decoder needs at least one conv".into(),
            ));
        }
        for (i, l) in layers.iter().enumerate() {
            let (o, c, kh, kw) = l.weight.dim();
            if kh != 1 || kw != 1 || o == 0 || c == 0 || l.bias.len() != o {
                return Err(NetError::Input(format!(
                    "pointwise decoder conv `{}`: weight {:?} and bias [{}], expected [O, C, 1, 1] \
                     and [O]",
                    l.name,
                    l.weight.shape(),
                    l.bias.len()
                )));
            }
            if i > 0 && layers[i - 1].out_channels() != c {
                return Err(NetError::Input(format!(
                    "pointwise decoder conv `{}` takes {c} channels, the conv before it makes {}",
                    l.name,
                    layers[i - 1].out_channels()
                )));
            }
            if layers[..i].iter().any(|p| p.name == l.name) {
                return Err(NetError::Input(format!(
                    "pointwise decoder: two convs are named `{}`",
                    l.name
                )));
            }
        }
        Ok(Decoder {
            levels: vec![layers],
            final_relu,
            resolution: Resolution::Standard,
        })
    }

    /// `kernel` is the convs' size: 3 for the decoders of the weight files, 1 for a pointwise
    /// decoder (canonical files record it, see [`crate::weights_file`]).
    pub(crate) fn from_spec(
        sd: &StateDict,
        spec: DecoderSpec,
        kernel: usize,
    ) -> Result<Decoder<T>, NetError> {
        if kernel == 1 && spec.levels.len() != 1 {
            return Err(NetError::Layout(format!(
                "decoder: a pointwise (1x1) decoder has one level, found {}",
                spec.levels.len()
            )));
        }
        let mut c: Option<usize> = None;
        let mut levels = Vec::new();
        for lv in &spec.levels {
            let mut convs = Vec::new();
            for r in lv {
                let layer: ConvLayer<T> = read_conv(sd, r, kernel, c)?;
                c = Some(layer.out_channels());
                convs.push(layer);
            }
            levels.push(convs);
        }
        Ok(Decoder {
            levels,
            final_relu: spec.final_relu,
            resolution: Resolution::Standard,
        })
    }

    /// Number of levels (`relu{depth}_1` is the input).
    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// Input channels (the encoder width at `relu{depth}_1`).
    pub fn in_channels(&self) -> usize {
        self.levels[0][0].in_channels()
    }

    /// Output channels (3 for images).
    pub fn out_channels(&self) -> usize {
        self.layers().last().expect("non-empty").out_channels()
    }

    /// Number of convs per level, deepest level first.
    pub fn convs_per_level(&self) -> Vec<usize> {
        self.levels.iter().map(Vec::len).collect()
    }

    /// The convs' kernel size: 3, or 1 for a pointwise decoder ([`Decoder::pointwise`]).
    pub fn kernel(&self) -> usize {
        self.levels[0][0].kernel()
    }

    /// Whether this is a pointwise decoder (1x1 convs, [`Decoder::pointwise`]).
    pub fn is_pointwise(&self) -> bool {
        self.kernel() == 1
    }

    /// Whether a ReLU follows the last conv.
    pub fn final_relu(&self) -> bool {
        self.final_relu
    }

    /// Standard or fullres.
    pub fn resolution(&self) -> Resolution {
        self.resolution
    }

    /// The same weights with the given resolution variant.
    pub fn with_resolution(mut self, resolution: Resolution) -> Decoder<T> {
        self.resolution = resolution;
        self
    }

    /// All convs in execution order.
    pub fn layers(&self) -> impl Iterator<Item = &ConvLayer<T>> {
        self.levels.iter().flatten()
    }

    /// All convs in execution order, mutably (for optimisers). Changing a shape breaks the network.
    pub fn layers_mut(&mut self) -> impl Iterator<Item = &mut ConvLayer<T>> {
        self.levels.iter_mut().flatten()
    }

    /// The same decoder in another precision.
    pub fn cast<U: Real>(&self) -> Decoder<U> {
        Decoder {
            levels: self
                .levels
                .iter()
                .map(|lv| lv.iter().map(ConvLayer::cast).collect())
                .collect(),
            final_relu: self.final_relu,
            resolution: self.resolution,
        }
    }

    fn steps(&self) -> Vec<Step<'_, T>> {
        let total: usize = self.levels.iter().map(Vec::len).sum();
        let mut steps = Vec::new();
        let mut i = 0;
        for (k, lv) in self.levels.iter().enumerate() {
            if k > 0 && self.resolution == Resolution::Standard {
                steps.push(Step::Up);
            }
            for layer in lv {
                i += 1;
                let relu = i < total || self.final_relu;
                steps.push(Step::Conv { layer, relu });
            }
        }
        steps.push(Step::Output);
        steps
    }

    /// Decodes features `[N, C, h, w]` to `[N, 3, H, W]`.
    pub fn forward(&self, x: ArrayView4<T>) -> Result<Array4<T>, NetError> {
        let (mut outs, _) = sequential::forward(&self.steps(), x, false, false, "decoder")?;
        Ok(outs.pop().expect("one output"))
    }

    /// [`Decoder::forward`], also returning the tape for [`Decoder::backward`] (the input
    /// gradient only: the tape keeps the ReLU masks, not the conv inputs).
    pub fn forward_with_tape(
        &self,
        x: ArrayView4<T>,
    ) -> Result<(Array4<T>, DecoderTape<T>), NetError> {
        self.forward_taped(x, false)
    }

    /// [`Decoder::forward_with_tape`] that also keeps every conv input, as
    /// [`Decoder::backward_with_params`] needs (more memory).
    pub fn forward_with_param_tape(
        &self,
        x: ArrayView4<T>,
    ) -> Result<(Array4<T>, DecoderTape<T>), NetError> {
        self.forward_taped(x, true)
    }

    fn forward_taped(
        &self,
        x: ArrayView4<T>,
        keep_inputs: bool,
    ) -> Result<(Array4<T>, DecoderTape<T>), NetError> {
        let (mut outs, tape) = sequential::forward(&self.steps(), x, true, keep_inputs, "decoder")?;
        Ok((
            outs.pop().expect("one output"),
            DecoderTape(tape.expect("tape requested")),
        ))
    }

    /// The size `(height, width)` of the decoded image for an input of `input_hw` (before any
    /// crop): the input size, doubled per upsampling.
    pub fn output_size(&self, input_hw: (usize, usize)) -> (usize, usize) {
        let ups = self
            .steps()
            .iter()
            .filter(|s| matches!(s, Step::Up))
            .count();
        (input_hw.0 << ups, input_hw.1 << ups)
    }

    /// The region of an input of `input_hw` that the decoded image's region `out` depends on
    /// (see [`crate::tiled`]).
    pub fn input_region(&self, input_hw: (usize, usize), out: Region) -> Result<Region, NetError> {
        Ok(tiled::plan(&self.steps(), self.in_channels(), input_hw, out, "decoder")?[0])
    }

    /// The region `out` of the image decoded from an input of `input_hw`, from `x`, which holds
    /// the input's region [`Decoder::input_region`]: equal to that region of
    /// [`Decoder::forward`] of the whole input, holding only the tile's activations.
    pub fn forward_region(
        &self,
        x: ArrayView4<T>,
        input_hw: (usize, usize),
        out: Region,
    ) -> Result<Array4<T>, NetError> {
        let steps = self.steps();
        let regions = tiled::plan(&steps, self.in_channels(), input_hw, out, "decoder")?;
        tiled::run_regions(&steps, &regions, x, "decoder")
    }

    /// [`Decoder::forward`] computed one output tile of at most `tile x tile` pixels at a
    /// time (the same result, see [`crate::tiled`]).
    pub fn forward_tiled(&self, x: ArrayView4<T>, tile: usize) -> Result<Array4<T>, NetError> {
        tiled::run_tiled(&self.steps(), x, tile, "decoder")
    }

    /// The working memory of a decoder tile per pixel of its region and halo, in bytes, for
    /// an input of `input_hw`, and the halo in output pixels (see [`tiled::tile_side`]).
    pub fn tile_cost(&self, input_hw: (usize, usize)) -> (f64, usize) {
        let steps = self.steps();
        (
            tiled::bytes_per_output_pixel(&steps, input_hw),
            tiled::halo(&steps, input_hw),
        )
    }

    /// The gradient of `<dy, decoder(x)>` with respect to the input `x` (no parameter
    /// gradients: half the work of [`Decoder::backward_with_params`]). Takes a tape from either
    /// forward pass.
    pub fn backward(
        &self,
        tape: &DecoderTape<T>,
        dy: ArrayView4<T>,
    ) -> Result<Array4<T>, NetError> {
        Ok(sequential::backward(&self.steps(), &tape.0, &[Some(dy)], false, "decoder")?.input)
    }

    /// Gradients of `<dy, decoder(x)>` with respect to the input and to every parameter. Needs
    /// a tape from [`Decoder::forward_with_param_tape`].
    pub fn backward_with_params(
        &self,
        tape: &DecoderTape<T>,
        dy: ArrayView4<T>,
    ) -> Result<DecoderGrads<T>, NetError> {
        let b = sequential::backward(&self.steps(), &tape.0, &[Some(dy)], true, "decoder")?;
        Ok(DecoderGrads {
            input: b.input,
            params: b.params,
        })
    }
}
