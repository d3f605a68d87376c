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
//!
//! Every layout (a contiguous tensor, a column block of a wider array, several tensors side by
//! side in the rows of one array) applies the element update above with the same operations in
//! the same order. In `f32` the contiguous runs and the side-by-side rows of SH arrays run as
//! vector code (lane arrays, compiled for the instruction set `pulp` picks at run time) that
//! performs exactly those operations per lane, so every path and every thread count gives the
//! same bits.

use std::ops::Range;

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
        let shared = Shared::new(&self.config);
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
        let size = state.begin_step(&self.config);
        let rows_per_chunk = (PAR_CHUNK / stride).max(1);
        params
            .par_chunks_mut(rows_per_chunk * stride)
            .zip(grads.par_chunks(rows_per_chunk * stride))
            .zip(state.exp_avg.par_chunks_mut(rows_per_chunk * width))
            .zip(state.exp_avg_sq.par_chunks_mut(rows_per_chunk * width))
            .for_each(|(((p, g), m), v)| {
                if stride == width {
                    update_run(&shared, size, p, g, m, v);
                    return;
                }
                for ((p_row, g_row), (m_row, v_row)) in p
                    .chunks_exact_mut(stride)
                    .zip(g.chunks_exact(stride))
                    .zip(m.chunks_exact_mut(width).zip(v.chunks_exact_mut(width)))
                {
                    update_run_scalar(
                        &shared,
                        size,
                        &mut p_row[offset..offset + width],
                        &g_row[offset..offset + width],
                        m_row,
                        v_row,
                    );
                }
            });
        Ok(())
    }

    /// One Adam step of several tensors that lie side by side in the rows of one row-major array:
    /// row `r` of `params` (and of `grads`) is row `r` of tensor `indices[0]`, then row `r` of
    /// tensor `indices[1]`, and so on, with nothing in between (e.g. the SH DC and higher-order
    /// groups of an interleaved SH array). Every tensor gets exactly the update (the same bits)
    /// that [`Adam::step_strided`] would give it; one pass reads each row once.
    pub fn step_side_by_side(
        &mut self,
        indices: &[usize],
        params: &mut [T],
        grads: &[T],
    ) -> Result<(), TrainError> {
        let stride = self.side_by_side_stride(indices)?;
        if grads.len() != params.len() {
            return Err(TrainError::Shape(format!(
                "Adam step side by side of groups {indices:?}: params have {} and grads {} \
                 elements",
                params.len(),
                grads.len()
            )));
        }
        let mut no_rows = vec![(); params.len() / stride];
        self.side_by_side(
            indices,
            params,
            &mut no_rows,
            Grads::<T, fn(Range<usize>, &[T], &mut [()], &mut [T])>::Slice(grads),
        )
    }

    /// [`Adam::step_side_by_side`] with the gradients made chunk by chunk, just before the update
    /// of those rows and while they are in cache, instead of read from an array of the whole
    /// tensor: `grads(rows, params_rows, per_row_rows, out)` must overwrite `out`
    /// (`rows.len() * stride` elements, a buffer kept per thread) with the gradients of `rows`,
    /// laid out like `params_rows`, which holds those rows' parameters before the update.
    /// `per_row` has one element per row, handed to the call for the same rows (e.g. an output
    /// the gradients' producer writes alongside). The chunks are fixed, so the result does not
    /// depend on the thread count; it has the bits of [`Adam::step_side_by_side`] with the same
    /// gradients.
    pub fn step_side_by_side_with<U, F>(
        &mut self,
        indices: &[usize],
        params: &mut [T],
        per_row: &mut [U],
        grads: F,
    ) -> Result<(), TrainError>
    where
        U: Send,
        F: Fn(Range<usize>, &[T], &mut [U], &mut [T]) + Sync,
    {
        self.side_by_side(indices, params, per_row, Grads::Fill(grads))
    }

    /// The side-by-side step, with the gradients from either source.
    fn side_by_side<U, F>(
        &mut self,
        indices: &[usize],
        params: &mut [T],
        per_row: &mut [U],
        grads: Grads<'_, T, F>,
    ) -> Result<(), TrainError>
    where
        U: Send,
        F: Fn(Range<usize>, &[T], &mut [U], &mut [T]) + Sync,
    {
        let stride = self.side_by_side_stride(indices)?;
        let shared = Shared::new(&self.config);
        let cfg = self.config;
        let mut slots: Vec<Option<&mut ParamState<T>>> = self.params.iter_mut().map(Some).collect();
        let mut states: Vec<&mut ParamState<T>> = indices
            .iter()
            .map(|&i| {
                slots[i]
                    .take()
                    .expect("checked distinct by side_by_side_stride")
            })
            .collect();
        let rows = states[0].rows();
        if states.iter().any(|s| s.rows() != rows)
            || params.len() != rows * stride
            || per_row.len() != rows
        {
            let shapes: Vec<String> = states
                .iter()
                .map(|s| format!("`{}` {} x {}", s.name, s.rows(), s.width))
                .collect();
            return Err(TrainError::Shape(format!(
                "Adam step side by side of {}: params have {} elements and the per-row outputs \
                 {} rows",
                shapes.join(", "),
                params.len(),
                per_row.len()
            )));
        }
        let widths: Vec<usize> = states.iter().map(|s| s.width).collect();
        let sizes: Vec<StepSize<T>> = states.iter_mut().map(|s| s.begin_step(&cfg)).collect();
        let rows_per_chunk = (PAR_CHUNK / stride).max(1);
        // One work item per chunk of rows: every tensor's moments of those rows.
        let mut items: Vec<Vec<(&mut [T], &mut [T])>> = (0..rows.div_ceil(rows_per_chunk))
            .map(|_| Vec::with_capacity(states.len()))
            .collect();
        for s in states {
            let w = s.width;
            let chunks = s
                .exp_avg
                .chunks_mut(rows_per_chunk * w)
                .zip(s.exp_avg_sq.chunks_mut(rows_per_chunk * w));
            for (item, mv) in items.iter_mut().zip(chunks) {
                item.push(mv);
            }
        }
        params
            .par_chunks_mut(rows_per_chunk * stride)
            .zip(per_row.par_chunks_mut(rows_per_chunk))
            .zip(items.into_par_iter())
            .enumerate()
            .for_each_init(Vec::new, |scratch, (item, ((p, u), mut mv))| {
                let first = item * rows_per_chunk;
                let g: &[T] = match &grads {
                    Grads::Slice(g) => &g[first * stride..first * stride + p.len()],
                    Grads::Fill(fill) => {
                        scratch.resize(p.len(), T::zero());
                        fill(first..first + u.len(), p, u, scratch);
                        scratch
                    }
                };
                if let (Some(p32), Some(g32)) = (T::as_f32_slice_mut(p), T::as_f32_slice(g)) {
                    let sizes32 = StepSize::as_f32(&sizes);
                    let shared32 = shared.as_f32();
                    let mv32 = mv
                        .iter_mut()
                        .map(|(m, v)| T::as_f32_slice_mut(m).zip(T::as_f32_slice_mut(v)))
                        .collect::<Option<Vec<_>>>();
                    if let (Some(sizes32), Some(shared32), Some(mut mv32)) =
                        (sizes32, shared32, mv32)
                    {
                        if fast::side_by_side(&shared32, &sizes32, &widths, p32, g32, &mut mv32) {
                            return;
                        }
                    }
                }
                side_by_side_rows(&shared, &sizes, &widths, p, g, &mut mv);
            });
        Ok(())
    }

    /// The row width of a side-by-side step of `indices`: an error unless they are distinct
    /// existing groups.
    fn side_by_side_stride(&self, indices: &[usize]) -> Result<usize, TrainError> {
        let distinct = indices
            .iter()
            .enumerate()
            .all(|(j, &i)| i < self.params.len() && !indices[..j].contains(&i));
        if indices.is_empty() || !distinct {
            return Err(TrainError::Shape(format!(
                "Adam step side by side of groups {indices:?}: not distinct existing groups"
            )));
        }
        Ok(indices.iter().map(|&i| self.params[i].width).sum())
    }
}

/// Where a side-by-side step takes its gradients from: an array of the whole tensor, or a
/// function that makes each chunk's.
enum Grads<'g, T, F> {
    Slice(&'g [T]),
    Fill(F),
}

/// The constants of a step shared by every tensor, in `T`.
#[derive(Clone, Copy, Debug)]
struct Shared<T> {
    one_minus_beta1: T,
    beta2: T,
    one_minus_beta2: T,
    eps: T,
}

impl<T: Real> Shared<T> {
    fn new(cfg: &AdamConfig) -> Self {
        Shared {
            one_minus_beta1: T::lit(1.0 - cfg.beta1),
            beta2: T::lit(cfg.beta2),
            one_minus_beta2: T::lit(1.0 - cfg.beta2),
            eps: T::lit(cfg.eps),
        }
    }

    fn as_f32(&self) -> Option<Shared<f32>> {
        let v = [
            self.one_minus_beta1,
            self.beta2,
            self.one_minus_beta2,
            self.eps,
        ];
        let [one_minus_beta1, beta2, one_minus_beta2, eps] = *T::as_f32_slice(&v)? else {
            return None;
        };
        Some(Shared {
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            eps,
        })
    }
}

/// The constants of one tensor's step: `sqrt(1 - beta2^t)` and `-lr / (1 - beta1^t)`, in `T`.
#[derive(Clone, Copy, Debug)]
struct StepSize<T> {
    bc2_sqrt: T,
    neg_step_size: T,
}

impl<T: Real> StepSize<T> {
    fn as_f32(sizes: &[StepSize<T>]) -> Option<Vec<StepSize<f32>>> {
        sizes
            .iter()
            .map(|s| {
                let v = [s.bc2_sqrt, s.neg_step_size];
                let [bc2_sqrt, neg_step_size] = *T::as_f32_slice(&v)? else {
                    return None;
                };
                Some(StepSize {
                    bc2_sqrt,
                    neg_step_size,
                })
            })
            .collect()
    }
}

impl<T: Real> ParamState<T> {
    /// Counts a step and returns its constants. The bias corrections and the step size are
    /// computed in `f64`, as PyTorch computes them in Python floats.
    fn begin_step(&mut self, cfg: &AdamConfig) -> StepSize<T> {
        self.step += 1;
        let t = self.step as i32;
        let bias_correction1 = 1.0 - cfg.beta1.powi(t);
        let bias_correction2_sqrt = (1.0 - cfg.beta2.powi(t)).sqrt();
        StepSize {
            bc2_sqrt: T::lit(bias_correction2_sqrt),
            neg_step_size: T::lit(-(self.lr / bias_correction1)),
        }
    }
}

/// One element's update. Every path (flat runs, strided rows, side-by-side rows, the `f32`
/// vector code) applies exactly these operations in this order, so all give the same bits.
#[inline(always)]
fn update_one<T: Real>(
    c: &Shared<T>,
    bc2_sqrt: T,
    neg_step_size: T,
    p: &mut T,
    g: T,
    m: &mut T,
    v: &mut T,
) {
    let m_new = *m + c.one_minus_beta1 * (g - *m);
    let v_new = c.beta2 * *v + c.one_minus_beta2 * g * g;
    *m = m_new;
    *v = v_new;
    let denom = v_new.sqrt() / bc2_sqrt + c.eps;
    // torch addcdiv_: p + (value * m) / denom, value = -step_size
    *p += (neg_step_size * m_new) / denom;
}

/// The update of a run of elements of one tensor: the `f32` vector code when `T` is `f32`.
fn update_run<T: Real>(
    c: &Shared<T>,
    s: StepSize<T>,
    p: &mut [T],
    g: &[T],
    m: &mut [T],
    v: &mut [T],
) {
    if let (Some(p32), Some(g32), Some(m32), Some(v32)) = (
        T::as_f32_slice_mut(p),
        T::as_f32_slice(g),
        T::as_f32_slice_mut(m),
        T::as_f32_slice_mut(v),
    ) {
        if let (Some(c32), Some(s32)) = (c.as_f32(), StepSize::as_f32(&[s])) {
            fast::run(&c32, s32[0], p32, g32, m32, v32);
            return;
        }
    }
    update_run_scalar(c, s, p, g, m, v);
}

/// [`update_run`] one element after the other (the reference, and the only path in `f64`).
#[inline(always)]
fn update_run_scalar<T: Real>(
    c: &Shared<T>,
    s: StepSize<T>,
    p: &mut [T],
    g: &[T],
    m: &mut [T],
    v: &mut [T],
) {
    for (((pi, &gi), mi), vi) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
        update_one(c, s.bc2_sqrt, s.neg_step_size, pi, gi, mi, vi);
    }
}

/// The rows of one work item of [`Adam::step_side_by_side`], tensor by tensor within each row
/// (the reference path): `mv[k]` holds tensor `k`'s moments of these rows.
fn side_by_side_rows<T: Real>(
    c: &Shared<T>,
    sizes: &[StepSize<T>],
    widths: &[usize],
    p: &mut [T],
    g: &[T],
    mv: &mut [(&mut [T], &mut [T])],
) {
    let stride: usize = widths.iter().sum();
    for (r, (p_row, g_row)) in p
        .chunks_exact_mut(stride)
        .zip(g.chunks_exact(stride))
        .enumerate()
    {
        let mut col = 0;
        for ((&w, s), (m, v)) in widths.iter().zip(sizes).zip(mv.iter_mut()) {
            update_run_scalar(
                c,
                *s,
                &mut p_row[col..col + w],
                &g_row[col..col + w],
                &mut m[r * w..(r + 1) * w],
                &mut v[r * w..(r + 1) * w],
            );
            col += w;
        }
    }
}

/// The `f32` vector code, compiled for the instruction set `pulp` picks at run time (AVX-512,
/// AVX2 or the baseline): fixed-size lane arrays that the compiler vectorises, each lane
/// running [`update_one`] unchanged.
mod fast {
    use super::{update_one, update_run_scalar, Shared, StepSize};

    /// Elements per vector step.
    const LANES: usize = 16;

    /// Elements ahead of a flat run's step whose parameters, gradients and moments are
    /// prefetched.
    const AHEAD: usize = 16 * LANES;

    /// Rows ahead of a side-by-side step whose moments are prefetched.
    const AHEAD_ROWS: usize = 4;

    /// A flat run of one tensor.
    pub(super) fn run(
        c: &Shared<f32>,
        s: StepSize<f32>,
        p: &mut [f32],
        g: &[f32],
        m: &mut [f32],
        v: &mut [f32],
    ) {
        base::isa::dispatch(Run { c, s, p, g, m, v });
    }

    struct Run<'a> {
        c: &'a Shared<f32>,
        s: StepSize<f32>,
        p: &'a mut [f32],
        g: &'a [f32],
        m: &'a mut [f32],
        v: &'a mut [f32],
    }

    impl pulp::WithSimd for Run<'_> {
        type Output = ();

        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) {
            let Run { c, s, p, g, m, v } = self;
            let n = p.len().min(g.len()).min(m.len()).min(v.len());
            let body = n - n % LANES;
            let (p, p_tail) = p[..n].split_at_mut(body);
            let (g, g_tail) = g[..n].split_at(body);
            let (m, m_tail) = m[..n].split_at_mut(body);
            let (v, v_tail) = v[..n].split_at_mut(body);
            for at in (0..body).step_by(LANES) {
                let (ahead, end) = ((at + AHEAD).min(body), (at + AHEAD + LANES).min(body));
                base::memory::prefetch(&p[ahead..end]);
                base::memory::prefetch(&g[ahead..end]);
                base::memory::prefetch(&m[ahead..end]);
                base::memory::prefetch(&v[ahead..end]);
                let (p, g) = (&mut p[at..at + LANES], &g[at..at + LANES]);
                let (m, v) = (&mut m[at..at + LANES], &mut v[at..at + LANES]);
                for l in 0..LANES {
                    update_one(
                        c,
                        s.bc2_sqrt,
                        s.neg_step_size,
                        &mut p[l],
                        g[l],
                        &mut m[l],
                        &mut v[l],
                    );
                }
            }
            update_run_scalar(c, s, p_tail, g_tail, m_tail, v_tail);
        }
    }

    /// The rows of one work item of `step_side_by_side` in the layouts worth a vector path:
    /// two tensors of widths 3 and `W - 3` with `W` = 12, 27 or 48 (SH degree 1, 2 or 3: DC
    /// then the rest). Returns `false`, having done nothing, for any other layout.
    pub(super) fn side_by_side<'b>(
        c: &Shared<f32>,
        sizes: &[StepSize<f32>],
        widths: &[usize],
        p: &mut [f32],
        g: &[f32],
        mv: &mut [(&'b mut [f32], &'b mut [f32])],
    ) -> bool {
        let ([s_a, s_b], [(m_a, v_a), (m_b, v_b)]) = (sizes, mv) else {
            return false;
        };
        let (sizes, mv) = (
            [*s_a, *s_b],
            [(&mut **m_a, &mut **v_a), (&mut **m_b, &mut **v_b)],
        );
        let arch = base::isa::arch();
        match widths {
            [3, 45] => arch.dispatch(Rows::<48, 3> { c, sizes, p, g, mv }),
            [3, 24] => arch.dispatch(Rows::<27, 3> { c, sizes, p, g, mv }),
            [3, 9] => arch.dispatch(Rows::<12, 3> { c, sizes, p, g, mv }),
            _ => return false,
        }
        true
    }

    /// Rows of `W` columns, the first `A` of one tensor and the rest of another: each row's
    /// moments are gathered from the two tensors into `W`-lane arrays (fixed-size copies),
    /// updated with per-column constants, and scattered back.
    struct Rows<'a, 'b, const W: usize, const A: usize> {
        c: &'a Shared<f32>,
        sizes: [StepSize<f32>; 2],
        p: &'a mut [f32],
        g: &'a [f32],
        mv: [(&'b mut [f32], &'b mut [f32]); 2],
    }

    impl<const W: usize, const A: usize> pulp::WithSimd for Rows<'_, '_, W, A> {
        type Output = ();

        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) {
            let Rows {
                c,
                sizes,
                p,
                g,
                mv: [(m_a, v_a), (m_b, v_b)],
            } = self;
            let mut bc2 = [0.0f32; W];
            let mut nss = [0.0f32; W];
            bc2[..A].fill(sizes[0].bc2_sqrt);
            nss[..A].fill(sizes[0].neg_step_size);
            bc2[A..].fill(sizes[1].bc2_sqrt);
            nss[A..].fill(sizes[1].neg_step_size);
            let rows = p.len() / W;
            let (p, g) = (p.as_chunks_mut::<W>().0, g.as_chunks::<W>().0);
            let (m_a, v_a) = (
                &mut m_a.as_chunks_mut::<A>().0[..rows],
                &mut v_a.as_chunks_mut::<A>().0[..rows],
            );
            let (m_b, v_b) = (&mut m_b[..rows * (W - A)], &mut v_b[..rows * (W - A)]);
            for r in 0..rows {
                let ahead = (r + AHEAD_ROWS).min(rows - 1);
                base::memory::prefetch(&m_a[ahead]);
                base::memory::prefetch(&v_a[ahead]);
                base::memory::prefetch(&m_b[ahead * (W - A)..(ahead + 1) * (W - A)]);
                base::memory::prefetch(&v_b[ahead * (W - A)..(ahead + 1) * (W - A)]);
                let (p, g) = (&mut p[r], &g[r]);
                let mb = &mut m_b[r * (W - A)..(r + 1) * (W - A)];
                let vb = &mut v_b[r * (W - A)..(r + 1) * (W - A)];
                let mut m = [0.0f32; W];
                let mut v = [0.0f32; W];
                m[..A].copy_from_slice(&m_a[r]);
                v[..A].copy_from_slice(&v_a[r]);
                m[A..].copy_from_slice(mb);
                v[A..].copy_from_slice(vb);
                for l in 0..W {
                    update_one(c, bc2[l], nss[l], &mut p[l], g[l], &mut m[l], &mut v[l]);
                }
                m_a[r].copy_from_slice(&m[..A]);
                v_a[r].copy_from_slice(&v[..A]);
                mb.copy_from_slice(&m[A..]);
                vb.copy_from_slice(&v[A..]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn random(rng: &mut StdRng, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-scale..scale)).collect()
    }

    /// An optimiser with the given group widths over `rows` rows, moments filled by a few
    /// steps on random gradients so that they are not zero. Group `k` takes `3 + k` steps and
    /// has its own learning rate, so no two groups share a step size.
    fn warmed_up(widths: &[usize], rows: usize, seed: u64) -> (Adam<f32>, Vec<f32>) {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut adam = Adam::new(AdamConfig::default());
        for (k, &w) in widths.iter().enumerate() {
            adam.add_param(&format!("g{k}"), 0.01 * (k + 1) as f64, rows, w);
        }
        let stride: usize = widths.iter().sum();
        let mut params = random(&mut rng, rows * stride, 1.0);
        for step in 0..3 + widths.len() {
            let grads = random(&mut rng, rows * stride, 0.1);
            let mut offset = 0;
            for (k, &w) in widths.iter().enumerate() {
                if step < 3 + k {
                    adam.step_strided(k, &mut params, &grads, stride, offset)
                        .unwrap();
                }
                offset += w;
            }
        }
        (adam, params)
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn vector_runs_give_the_bits_of_the_scalar_reference() {
        let mut rng = StdRng::seed_from_u64(7);
        // lengths below, at and above the lane count, with tails
        for n in [0, 1, 15, 16, 17, 100, 1000] {
            let c = Shared::<f32>::new(&AdamConfig {
                eps: 1e-15,
                ..AdamConfig::default()
            });
            let s = StepSize {
                bc2_sqrt: 0.05f32,
                neg_step_size: -0.02f32,
            };
            let g = random(&mut rng, n, 0.1);
            let (p0, m0) = (random(&mut rng, n, 1.0), random(&mut rng, n, 0.01));
            let v0: Vec<f32> = random(&mut rng, n, 1e-4).iter().map(|x| x.abs()).collect();
            let (mut p1, mut m1, mut v1) = (p0.clone(), m0.clone(), v0.clone());
            let (mut p2, mut m2, mut v2) = (p0, m0, v0);
            update_run(&c, s, &mut p1, &g, &mut m1, &mut v1);
            update_run_scalar(&c, s, &mut p2, &g, &mut m2, &mut v2);
            assert_eq!(bits(&p1), bits(&p2), "params, n = {n}");
            assert_eq!(bits(&m1), bits(&m2), "exp_avg, n = {n}");
            assert_eq!(bits(&v1), bits(&v2), "exp_avg_sq, n = {n}");
        }
    }

    #[test]
    fn side_by_side_gives_the_bits_of_one_strided_step_per_tensor() {
        // SH layouts of degree 1..3 (the vector path) and an odd one (the row-by-row path);
        // row counts that leave a partial parallel chunk
        for widths in [vec![3, 9], vec![3, 24], vec![3, 45], vec![2, 5, 1]] {
            let rows = 700;
            let stride: usize = widths.iter().sum();
            let (mut a, mut pa) = warmed_up(&widths, rows, 3);
            let (mut b, mut pb) = (a.clone(), pa.clone());
            let grads = random(&mut StdRng::seed_from_u64(11), rows * stride, 0.1);
            let all: Vec<usize> = (0..widths.len()).collect();
            a.step_side_by_side(&all, &mut pa, &grads).unwrap();
            let mut offset = 0;
            for (k, &w) in widths.iter().enumerate() {
                b.step_strided(k, &mut pb, &grads, stride, offset).unwrap();
                offset += w;
            }
            assert_eq!(bits(&pa), bits(&pb), "params, widths {widths:?}");
            for (x, y) in a.params().iter().zip(b.params()) {
                assert_eq!(x.step_count(), y.step_count());
                assert_eq!(bits(x.exp_avg()), bits(y.exp_avg()), "{}", x.name);
                assert_eq!(bits(x.exp_avg_sq()), bits(y.exp_avg_sq()), "{}", x.name);
            }
        }
    }

    #[test]
    fn gradients_made_per_chunk_give_the_bits_of_a_gradient_array() {
        // The producer sees each chunk's rows before the update and writes its per-row output;
        // rows that leave a partial parallel chunk, on one thread and on the default pool.
        for threads in [1, 3] {
            let widths = [3, 45];
            let (rows, stride) = (700, 48);
            let (mut a, mut pa) = warmed_up(&widths, rows, 5);
            let (mut b, mut pb) = (a.clone(), pa.clone());
            let grads = random(&mut StdRng::seed_from_u64(13), rows * stride, 0.1);
            let before = pa.clone();
            a.step_side_by_side(&[0, 1], &mut pa, &grads).unwrap();
            let mut seen = vec![0.0f32; rows];
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                b.step_side_by_side_with(&[0, 1], &mut pb, &mut seen, |r, p, seen, out| {
                    assert_eq!(p, &before[r.start * stride..r.end * stride]);
                    out.copy_from_slice(&grads[r.start * stride..r.end * stride]);
                    for (s, row) in seen.iter_mut().zip(p.chunks_exact(stride)) {
                        *s = row[0];
                    }
                })
                .unwrap()
            });
            assert_eq!(bits(&pa), bits(&pb), "params, {threads} threads");
            let first: Vec<f32> = before.chunks_exact(stride).map(|row| row[0]).collect();
            assert_eq!(bits(&seen), bits(&first));
            assert_eq!(a, b, "states, {threads} threads");
        }
    }

    #[test]
    fn side_by_side_in_f64_matches_strided_steps() {
        let widths = [3, 45];
        let rows = 10;
        let mut a = Adam::<f64>::new(AdamConfig::default());
        for (k, &w) in widths.iter().enumerate() {
            a.add_param(&format!("g{k}"), 0.1, rows, w);
        }
        let mut b = a.clone();
        let mut pa: Vec<f64> = (0..rows * 48).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut pb = pa.clone();
        let g: Vec<f64> = (0..rows * 48).map(|i| (i as f64 * 0.11).cos()).collect();
        a.step_side_by_side(&[0, 1], &mut pa, &g).unwrap();
        b.step_strided(0, &mut pb, &g, 48, 0).unwrap();
        b.step_strided(1, &mut pb, &g, 48, 3).unwrap();
        assert_eq!(pa, pb);
        assert_eq!(a, b);
    }

    #[test]
    fn side_by_side_refuses_repeated_groups_and_wrong_lengths() {
        let (mut a, mut p) = warmed_up(&[3, 45], 4, 1);
        let g = vec![0.0; p.len()];
        assert!(a.step_side_by_side(&[0, 0], &mut p, &g).is_err());
        assert!(a.step_side_by_side(&[0, 5], &mut p, &g).is_err());
        assert!(a.step_side_by_side(&[], &mut p, &g).is_err());
        assert!(a.step_side_by_side(&[0], &mut p, &g).is_err());
        let steps: Vec<u64> = a.params().iter().map(|s| s.step_count()).collect();
        assert_eq!(steps, [3, 4], "a refused step counts nothing");
    }
}
