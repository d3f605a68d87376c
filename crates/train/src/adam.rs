//! Adam with the semantics of `torch.optim.Adam` (no weight decay, no AMSGrad).
//!
//! For every parameter tensor, at step `t` (counted from 1, per tensor):
//!
//! ```text
//! m     = m + (1 - beta1) * (g - m)            (torch: exp_avg.lerp_(grad, 1 - beta1))
//! v     = beta2 * v + (1 - beta2) * g * g
//! denom = sqrt(v) / sqrt(1 - beta2^t) + eps    (eps added after the square root)
//! p     = p - lr / (1 - beta1^t) * m / denom
//! ```
//!
//! The bias corrections and the step size are computed in `f64`, as PyTorch computes them in
//! Python floats; the element-wise arithmetic runs in the parameter type `T`.
//!
//! Each parameter tensor is seen as `rows x width` (for Gaussians: one row per Gaussian). Its
//! moments can be filtered, extended and reset row-wise, so the state stays consistent when the
//! Gaussians are pruned, cloned or split. Like the 3DGS trainer, new rows start with zero moments
//! and the per-tensor step count is kept.

use gaussian::Real;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::TrainError;

/// Elements per parallel work item. Element-wise updates are independent, so any chunking gives
/// bit-identical results; the size only balances scheduling overhead.
const PAR_CHUNK: usize = 1 << 14;

/// The hyper-parameters shared by all parameter tensors.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AdamConfig {
    /// Decay rate of the first-moment (mean) estimate; PyTorch and 3DGS: 0.9.
    pub beta1: f64,
    /// Decay rate of the second-moment (uncentred variance) estimate; PyTorch and 3DGS: 0.999.
    pub beta2: f64,
    /// Added to `sqrt(v_hat)`. PyTorch's default is 1e-8; the 3DGS trainer uses 1e-15.
    pub eps: f64,
}

impl Default for AdamConfig {
    /// `torch.optim.Adam` defaults: betas (0.9, 0.999), eps 1e-8.
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }
}

/// The optimiser state of one parameter tensor of `rows x width` elements.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamState<T: Real> {
    /// A stable name, used in checkpoints and error messages.
    pub name: String,
    /// Learning rate of this tensor (PyTorch's per-group `lr`).
    pub lr: f64,
    width: usize,
    step: u64,
    exp_avg: Vec<T>,
    exp_avg_sq: Vec<T>,
}

impl<T: Real> ParamState<T> {
    /// Zero-initialised state for `rows x width` elements.
    pub fn new(name: &str, lr: f64, rows: usize, width: usize) -> Self {
        ParamState {
            name: name.to_string(),
            lr,
            width,
            step: 0,
            exp_avg: vec![T::zero(); rows * width],
            exp_avg_sq: vec![T::zero(); rows * width],
        }
    }

    /// Restores a state from saved parts (checkpoints). Fails when the lengths disagree.
    pub fn from_parts(
        name: &str,
        lr: f64,
        width: usize,
        step: u64,
        exp_avg: Vec<T>,
        exp_avg_sq: Vec<T>,
    ) -> Result<Self, TrainError> {
        if width == 0 || exp_avg.len() != exp_avg_sq.len() || !exp_avg.len().is_multiple_of(width) {
            return Err(TrainError::Shape(format!(
                "Adam state `{name}`: exp_avg has {} and exp_avg_sq {} elements, not a multiple of \
                 width {width} and equal",
                exp_avg.len(),
                exp_avg_sq.len()
            )));
        }
        Ok(ParamState {
            name: name.to_string(),
            lr,
            width,
            step,
            exp_avg,
            exp_avg_sq,
        })
    }

    /// Elements per row.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.exp_avg.len() / self.width
    }

    /// Number of steps taken (PyTorch's `state['step']`).
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// First moment (`exp_avg`), row-major.
    pub fn exp_avg(&self) -> &[T] {
        &self.exp_avg
    }

    /// Second moment (`exp_avg_sq`), row-major.
    pub fn exp_avg_sq(&self) -> &[T] {
        &self.exp_avg_sq
    }

    /// Keeps the rows where `keep` is true, in order.
    pub fn retain_rows(&mut self, keep: &[bool]) -> Result<(), TrainError> {
        self.check_rows(keep.len(), "mask")?;
        let w = self.width;
        for buf in [&mut self.exp_avg, &mut self.exp_avg_sq] {
            let mut out = Vec::with_capacity(buf.len());
            for (row, &k) in buf.chunks_exact(w).zip(keep) {
                if k {
                    out.extend_from_slice(row);
                }
            }
            *buf = out;
        }
        Ok(())
    }

    /// Appends `n` rows with zero moments.
    pub fn extend_rows(&mut self, n: usize) {
        let len = self.exp_avg.len() + n * self.width;
        self.exp_avg.resize(len, T::zero());
        self.exp_avg_sq.resize(len, T::zero());
    }

    /// Sets both moments of every row to zero, keeping the step count (what 3DGS does when it
    /// replaces a tensor in the optimiser, e.g. at an opacity reset).
    pub fn zero_moments(&mut self) {
        self.exp_avg.fill(T::zero());
        self.exp_avg_sq.fill(T::zero());
    }

    fn check_rows(&self, rows: usize, what: &str) -> Result<(), TrainError> {
        if rows != self.rows() {
            return Err(TrainError::Shape(format!(
                "Adam state `{}` has {} rows but the {what} has {rows}",
                self.name,
                self.rows()
            )));
        }
        Ok(())
    }
}

/// Adam over a list of parameter tensors, each with its own learning rate and state.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam<T: Real> {
    /// The hyper-parameters shared by every parameter tensor.
    pub config: AdamConfig,
    params: Vec<ParamState<T>>,
}

impl<T: Real> Adam<T> {
    /// An optimiser without parameters.
    pub fn new(config: AdamConfig) -> Self {
        Adam {
            config,
            params: Vec::new(),
        }
    }

    /// Registers a parameter tensor of `rows x width` elements and returns its index.
    pub fn add_param(&mut self, name: &str, lr: f64, rows: usize, width: usize) -> usize {
        self.params.push(ParamState::new(name, lr, rows, width));
        self.params.len() - 1
    }

    /// Registers a restored state and returns its index.
    pub fn push_state(&mut self, state: ParamState<T>) -> usize {
        self.params.push(state);
        self.params.len() - 1
    }

    /// The states, in registration order.
    pub fn params(&self) -> &[ParamState<T>] {
        &self.params
    }

    /// Mutable access to one state (learning rate, row operations).
    pub fn param_mut(&mut self, index: usize) -> &mut ParamState<T> {
        &mut self.params[index]
    }

    /// The index of the tensor called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.params.iter().position(|p| p.name == name)
    }

    /// Sets the learning rate of one tensor.
    pub fn set_lr(&mut self, index: usize, lr: f64) {
        self.params[index].lr = lr;
    }

    /// One Adam step of a contiguous tensor: `params` and `grads` are laid out like the state.
    pub fn step(&mut self, index: usize, params: &mut [T], grads: &[T]) -> Result<(), TrainError> {
        let width = self.params[index].width;
        self.step_strided(index, params, grads, width, 0)
    }

    /// One Adam step of a column block of a wider row-major array: element `c` of row `r` of the
    /// tensor is `params[r * stride + offset + c]`, and likewise in `grads`. This updates e.g. the
    /// SH DC coefficients inside an interleaved SH array without copying.
    pub fn step_strided(
        &mut self,
        index: usize,
        params: &mut [T],
        grads: &[T],
        stride: usize,
        offset: usize,
    ) -> Result<(), TrainError> {
        let cfg = self.config;
        let state = &mut self.params[index];
        let width = state.width;
        let rows = state.rows();
        if offset + width > stride || params.len() != rows * stride || grads.len() != rows * stride
        {
            return Err(TrainError::Shape(format!(
                "Adam step of `{}`: state is {rows} x {width}, but params have {} and grads {} \
                 elements for stride {stride} and offset {offset}",
                state.name,
                params.len(),
                grads.len()
            )));
        }
        state.step += 1;
        let t = state.step as i32;
        let bias_correction1 = 1.0 - cfg.beta1.powi(t);
        let bias_correction2_sqrt = (1.0 - cfg.beta2.powi(t)).sqrt();
        let neg_step_size = T::lit(-(state.lr / bias_correction1));
        let bc2_sqrt = T::lit(bias_correction2_sqrt);
        let one_minus_beta1 = T::lit(1.0 - cfg.beta1);
        let beta2 = T::lit(cfg.beta2);
        let one_minus_beta2 = T::lit(1.0 - cfg.beta2);
        let eps = T::lit(cfg.eps);

        let rows_per_chunk = (PAR_CHUNK / stride).max(1);
        // One element's update; the same operations in the same order for every layout, so a
        // contiguous tensor updated as one flat run (which vectorises) gives the same bits as
        // row by row.
        let update = |p: &mut [T], g: &[T], m: &mut [T], v: &mut [T]| {
            for (((pi, &gi), mi), vi) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                let m_new = *mi + one_minus_beta1 * (gi - *mi);
                let v_new = beta2 * *vi + one_minus_beta2 * gi * gi;
                *mi = m_new;
                *vi = v_new;
                let denom = v_new.sqrt() / bc2_sqrt + eps;
                // torch addcdiv_: p + (value * m) / denom, value = -step_size
                *pi += (neg_step_size * m_new) / denom;
            }
        };
        params
            .par_chunks_mut(rows_per_chunk * stride)
            .zip(grads.par_chunks(rows_per_chunk * stride))
            .zip(state.exp_avg.par_chunks_mut(rows_per_chunk * width))
            .zip(state.exp_avg_sq.par_chunks_mut(rows_per_chunk * width))
            .for_each(|(((p, g), m), v)| {
                if stride == width {
                    update(p, g, m, v);
                    return;
                }
                for ((p_row, g_row), (m_row, v_row)) in p
                    .chunks_exact_mut(stride)
                    .zip(g.chunks_exact(stride))
                    .zip(m.chunks_exact_mut(width).zip(v.chunks_exact_mut(width)))
                {
                    update(
                        &mut p_row[offset..offset + width],
                        &g_row[offset..offset + width],
                        m_row,
                        v_row,
                    );
                }
            });
        Ok(())
    }
}
