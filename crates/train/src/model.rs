//! The trainable Gaussian model of the geometry stage: the scene, its Adam state and its
//! densification statistics, kept consistent with each other.
//!
//! The optimiser holds one tensor per parameter group of the 3DGS trainer, with its learning rate:
//!
//! | group      | scene array                       | row width       | default lr            |
//! |------------|-----------------------------------|-----------------|-----------------------|
//! | `xyz`      | `means`                           | 3               | scheduled (see below) |
//! | `f_dc`     | `sh`, coefficient 0               | 3               | 0.0025                |
//! | `f_rest`   | `sh`, coefficients 1..K           | 3 (K - 1)       | 0.0025 / 20           |
//! | `opacity`  | `opacity_logits`                  | 1               | 0.05                  |
//! | `scaling`  | `log_scales`                      | 3               | 0.005                 |
//! | `rotation` | `quats`                           | 4               | 0.001                 |
//!
//! The position learning rate follows [`ExponentialLr`] from 1.6e-4 to 1.6e-6 times the scene
//! extent over 30,000 steps. The opacity rate is 0.05 as in the code released with the paper
//! (later releases lowered it to 0.025). The scene stores SH coefficients up to the maximum degree
//! from the start; the active degree, used for rendering, grows during training, and the
//! coefficients above it receive zero gradients (as in 3DGS, where they are masked out of the
//! rasterizer but stay in the optimiser).

use gaussian::FeatureGaussians;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::adam::{Adam, AdamConfig};
use crate::error::TrainError;
use crate::schedule::ExponentialLr;
use raster::DensificationStats;

/// Name of the position group.
pub const XYZ: &str = "xyz";
/// Name of the SH DC group.
pub const F_DC: &str = "f_dc";
/// Name of the higher-order SH group (absent when the maximum degree is 0).
pub const F_REST: &str = "f_rest";
/// Name of the opacity group.
pub const OPACITY: &str = "opacity";
/// Name of the log-scale group.
pub const SCALING: &str = "scaling";
/// Name of the rotation group.
pub const ROTATION: &str = "rotation";

/// Learning rates of the geometry stage (3DGS `OptimizationParams` defaults of the paper code).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LearningRates {
    /// Initial position rate, before scaling by the scene extent.
    pub position_lr_init: f64,
    /// Final position rate, before scaling by the scene extent.
    pub position_lr_final: f64,
    /// Warm-up multiplier of the position schedule (inactive with 0 delay steps).
    pub position_lr_delay_mult: f64,
    /// Warm-up steps of the position schedule.
    pub position_lr_delay_steps: u64,
    /// Step at which the position rate reaches its final value.
    pub position_lr_max_steps: u64,
    /// SH DC rate; higher SH coefficients use `feature_lr / feature_rest_divisor`.
    pub feature_lr: f64,
    /// Divisor of `feature_lr` for the higher-order SH coefficients (`f_rest`); 3DGS: 20.
    pub feature_rest_divisor: f64,
    /// Rate of the opacity logits: 0.05 as in the paper code (later 3DGS releases: 0.025).
    pub opacity_lr: f64,
    /// Rate of the log-scales; 3DGS: 0.005.
    pub scaling_lr: f64,
    /// Rate of the rotation quaternions; 3DGS: 0.001.
    pub rotation_lr: f64,
}

impl Default for LearningRates {
    fn default() -> Self {
        LearningRates {
            position_lr_init: 0.00016,
            position_lr_final: 0.0000016,
            position_lr_delay_mult: 0.01,
            position_lr_delay_steps: 0,
            position_lr_max_steps: 30_000,
            feature_lr: 0.0025,
            feature_rest_divisor: 20.0,
            opacity_lr: 0.05,
            scaling_lr: 0.005,
            rotation_lr: 0.001,
        }
    }
}

impl LearningRates {
    /// The position schedule for a scene of the given extent.
    pub fn position_schedule(&self, spatial_lr_scale: f64) -> ExponentialLr {
        ExponentialLr {
            lr_init: self.position_lr_init * spatial_lr_scale,
            lr_final: self.position_lr_final * spatial_lr_scale,
            delay_steps: self.position_lr_delay_steps,
            delay_mult: self.position_lr_delay_mult,
            max_steps: self.position_lr_max_steps,
        }
    }
}

/// Gradients of a loss with respect to the scene parameters, laid out like the scene; `sh` holds
/// `coeffs_per_gaussian` coefficients per Gaussian, which may be fewer than the scene stores (the
/// active degree), in which case the missing ones are zero.
#[derive(Clone, Copy, Debug)]
pub struct GaussianGrads<'a> {
    /// `dL/d(means)`, one `[x, y, z]` per Gaussian (through the projection and the SH view
    /// direction).
    pub means: &'a [[f32; 3]],
    /// `dL/d(quats)`, one `(w, x, y, z)` per Gaussian.
    pub quats: &'a [[f32; 4]],
    /// `dL/d(log_scales)`, one `[x, y, z]` per Gaussian.
    pub log_scales: &'a [[f32; 3]],
    /// `dL/d(opacity_logits)`, one per Gaussian.
    pub opacity_logits: &'a [f32],
    /// `dL/d(sh)`: `coeffs_per_gaussian` RGB coefficients per Gaussian, Gaussian-major.
    pub sh: &'a [[f32; 3]],
    /// SH coefficients per Gaussian in `sh`, `(d + 1)^2` for some degree `d` up to the scene's.
    pub coeffs_per_gaussian: usize,
}

/// The gradients of a colour render before its SH colour backward
/// ([`raster::render_backward_before_sh`]): [`GaussianModel::step_from_colours`] runs that
/// backward inside the SH groups' Adam pass, chunk by chunk, so the coefficient gradients never
/// make a whole array.
#[derive(Clone, Copy, Debug)]
pub struct ColourGrads<'a> {
    /// `dL/d(means)` through the projection only (the view direction's term is added in the
    /// step).
    pub means: &'a [[f32; 3]],
    /// `dL/d(quats)`, one `(w, x, y, z)` per Gaussian.
    pub quats: &'a [[f32; 4]],
    /// `dL/d(log_scales)`, one `[x, y, z]` per Gaussian.
    pub log_scales: &'a [[f32; 3]],
    /// `dL/d(opacity_logits)`, one per Gaussian.
    pub opacity_logits: &'a [f32],
    /// `dL/d(colour)`, one RGB triple per Gaussian.
    pub colours: &'a [[f32; 3]],
    /// The SH degree the colours were evaluated at.
    pub sh_degree: usize,
    /// The centre of the camera the colours were seen from.
    pub camera_center: [f32; 3],
}

/// A scene with its optimiser state and densification statistics.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianModel {
    /// The parameters; SH coefficients are stored up to the maximum degree.
    pub scene: FeatureGaussians<f32>,
    /// The SH degree used for rendering, `<= scene.sh_degree`.
    pub active_sh_degree: usize,
    /// One Adam state per parameter group ([`XYZ`], [`F_DC`], [`F_REST`] when the maximum SH
    /// degree is above 0, [`OPACITY`], [`SCALING`], [`ROTATION`]), with one row per Gaussian.
    pub adam: Adam<f32>,
    /// Densification statistics since the last densification (gradient-norm sums, visibility
    /// counts, largest screen radii), one entry per Gaussian.
    pub stats: DensificationStats,
}

impl GaussianModel {
    /// A model at step 0: fresh Adam state with the given rates, active SH degree 0, zero
    /// statistics. The position rate starts at the schedule's value for step 0.
    pub fn new(
        scene: FeatureGaussians<f32>,
        lrs: &LearningRates,
        adam: AdamConfig,
        spatial_lr_scale: f64,
    ) -> Result<Self, TrainError> {
        check_scene(&scene)?;
        let n = scene.len();
        let k = scene.sh_coeffs_per_gaussian();
        let mut opt = Adam::new(adam);
        for (name, width) in groups(k) {
            let lr = match name {
                XYZ => lrs.position_schedule(spatial_lr_scale).at(0),
                F_DC => lrs.feature_lr,
                F_REST => lrs.feature_lr / lrs.feature_rest_divisor,
                OPACITY => lrs.opacity_lr,
                SCALING => lrs.scaling_lr,
                _ => lrs.rotation_lr,
            };
            opt.add_param(name, lr, n, width);
        }
        Ok(GaussianModel {
            scene,
            active_sh_degree: 0,
            adam: opt,
            stats: DensificationStats::new(n),
        })
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.scene.len()
    }

    /// Whether the model has no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.scene.is_empty()
    }

    /// Index of an optimiser group by name.
    pub fn group(&self, name: &str) -> Result<usize, TrainError> {
        self.adam
            .index_of(name)
            .ok_or_else(|| TrainError::Shape(format!("the optimiser has no group `{name}`")))
    }

    /// Sets the position learning rate.
    pub fn set_position_lr(&mut self, lr: f64) -> Result<(), TrainError> {
        let g = self.group(XYZ)?;
        self.adam.set_lr(g, lr);
        Ok(())
    }

    /// Raises the active SH degree by one, up to the stored maximum.
    pub fn one_up_sh_degree(&mut self) {
        if self.active_sh_degree < self.scene.sh_degree {
            self.active_sh_degree += 1;
        }
    }

    /// One Adam step of every group from the gradients of the loss.
    pub fn step(&mut self, grads: &GaussianGrads<'_>) -> Result<(), TrainError> {
        self.step_except(grads, &[])
    }

    /// One Adam step of every group except those named in `skip` (whose parameters and state
    /// stay untouched, as for a PyTorch parameter without gradient).
    pub fn step_except(
        &mut self,
        grads: &GaussianGrads<'_>,
        skip: &[&str],
    ) -> Result<(), TrainError> {
        let n = self.len();
        let k_all = self.scene.sh_coeffs_per_gaussian();
        let kg = grads.coeffs_per_gaussian;
        let lens = [
            ("means", grads.means.len(), n),
            ("quats", grads.quats.len(), n),
            ("log_scales", grads.log_scales.len(), n),
            ("opacity_logits", grads.opacity_logits.len(), n),
            ("sh", grads.sh.len(), n * kg),
        ];
        for (what, got, want) in lens {
            if got != want {
                return Err(TrainError::Shape(format!(
                    "gradient of `{what}` has {got} rows, the model has {want}"
                )));
            }
        }
        if kg == 0 || kg > k_all {
            return Err(TrainError::Shape(format!(
                "gradient has {kg} SH coefficients per Gaussian, the model stores {k_all}"
            )));
        }
        self.step_sh(grads.sh, kg, skip)?;
        self.step_except_sh(
            grads.means,
            grads.quats,
            grads.log_scales,
            grads.opacity_logits,
            skip,
        )
    }

    /// The Adam steps of the SH groups not in `skip`, from coefficient gradients with `kg`
    /// coefficients per Gaussian (checked by the caller).
    fn step_sh(&mut self, sh: &[[f32; 3]], kg: usize, skip: &[&str]) -> Result<(), TrainError> {
        let n = self.len();
        let k_all = self.scene.sh_coeffs_per_gaussian();
        let run = |name: &str| !skip.contains(&name);
        // SH gradients at the stored width (zeros above the active degree)
        let padded;
        let sh_grad: &[[f32; 3]] = if kg == k_all {
            sh
        } else {
            let mut p = vec![[0.0f32; 3]; n * k_all];
            for (dst, src) in p.chunks_exact_mut(k_all).zip(sh.chunks_exact(kg)) {
                dst[..kg].copy_from_slice(src);
            }
            padded = p;
            &padded
        };
        let stride = 3 * k_all;
        if k_all > 1 && run(F_DC) && run(F_REST) {
            // Both SH groups in one pass over the interleaved array (the same bits as one
            // strided step per group).
            let groups = [self.group(F_DC)?, self.group(F_REST)?];
            self.adam.step_side_by_side(
                &groups,
                self.scene.sh.as_flattened_mut(),
                sh_grad.as_flattened(),
            )?;
        } else {
            if run(F_DC) {
                let g = self.group(F_DC)?;
                self.adam.step_strided(
                    g,
                    self.scene.sh.as_flattened_mut(),
                    sh_grad.as_flattened(),
                    stride,
                    0,
                )?;
            }
            if k_all > 1 && run(F_REST) {
                let g = self.group(F_REST)?;
                self.adam.step_strided(
                    g,
                    self.scene.sh.as_flattened_mut(),
                    sh_grad.as_flattened(),
                    stride,
                    3,
                )?;
            }
        }
        Ok(())
    }

    /// The Adam steps of the groups other than SH that are not in `skip`, from gradients of
    /// the model's length (checked by the caller).
    fn step_except_sh(
        &mut self,
        means: &[[f32; 3]],
        quats: &[[f32; 4]],
        log_scales: &[[f32; 3]],
        opacity_logits: &[f32],
        skip: &[&str],
    ) -> Result<(), TrainError> {
        let run = |name: &str| !skip.contains(&name);
        if run(XYZ) {
            let g = self.group(XYZ)?;
            self.adam
                .step(g, self.scene.means.as_flattened_mut(), means.as_flattened())?;
        }
        if run(OPACITY) {
            let g = self.group(OPACITY)?;
            self.adam
                .step(g, &mut self.scene.opacity_logits, opacity_logits)?;
        }
        if run(SCALING) {
            let g = self.group(SCALING)?;
            self.adam.step(
                g,
                self.scene.log_scales.as_flattened_mut(),
                log_scales.as_flattened(),
            )?;
        }
        if run(ROTATION) {
            let g = self.group(ROTATION)?;
            self.adam
                .step(g, self.scene.quats.as_flattened_mut(), quats.as_flattened())?;
        }
        Ok(())
    }

    /// The step of [`GaussianModel::step_except`] from the gradients of a colour render before
    /// its SH colour backward: with both SH groups stepped, that backward runs chunk by chunk
    /// inside their Adam pass (`gaussian::sh_colors_backward_rows` into a per-thread buffer,
    /// updated at once), so the coefficient gradients are written and read in cache instead of
    /// through an array of every Gaussian's; its view-direction term joins `grads.means` before
    /// the position step. The result has the bits of [`raster::render_backward`] followed by
    /// [`GaussianModel::step_except`]. If an SH group is skipped, the coefficient gradients are
    /// made first, as [`raster::render_backward`] makes them.
    pub fn step_from_colours(
        &mut self,
        grads: &ColourGrads<'_>,
        skip: &[&str],
    ) -> Result<(), TrainError> {
        let n = self.len();
        let k = self.scene.sh_coeffs_per_gaussian();
        let lens = [
            ("means", grads.means.len()),
            ("quats", grads.quats.len()),
            ("log_scales", grads.log_scales.len()),
            ("opacity_logits", grads.opacity_logits.len()),
            ("colours", grads.colours.len()),
        ];
        for (what, got) in lens {
            if got != n {
                return Err(TrainError::Shape(format!(
                    "gradient of `{what}` has {got} rows, the model has {n}"
                )));
            }
        }
        let degree = grads.sh_degree;
        if degree > 3 || (degree + 1) * (degree + 1) > k {
            return Err(TrainError::Shape(format!(
                "colours at SH degree {degree}, the model stores {k} coefficients per Gaussian"
            )));
        }
        // Written by the threads of the pool: a copy on one core would keep the other idle.
        let mut means = Vec::with_capacity(n);
        means.par_extend(grads.means.par_iter().copied());
        if k > 1 && !skip.contains(&F_DC) && !skip.contains(&F_REST) {
            let groups = [self.group(F_DC)?, self.group(F_REST)?];
            let scene_means = &self.scene.means;
            let (colours, center) = (grads.colours, grads.camera_center);
            // Each chunk's view-direction term joins its rows of `means` while in cache
            // (`raster::add_view_direction_term` on those rows).
            self.adam.step_side_by_side_with(
                &groups,
                self.scene.sh.as_flattened_mut(),
                &mut means,
                |rows, sh, means, out| {
                    let mut d_means = vec![[0.0f32; 3]; rows.len()];
                    gaussian::sh_colors_backward_rows(
                        degree,
                        k,
                        sh.as_chunks::<3>().0,
                        &scene_means[rows.clone()],
                        center,
                        &colours[rows],
                        out.as_chunks_mut::<3>().0,
                        &mut d_means,
                    );
                    raster::add_view_direction_term(means, &d_means);
                },
            )?;
        } else {
            let (d_sh, d_means) = gaussian::sh_colors_backward(
                degree,
                k,
                &self.scene.sh,
                &self.scene.means,
                grads.camera_center,
                grads.colours,
            );
            raster::add_view_direction_term(&mut means, &d_means);
            self.step_sh(&d_sh, k, skip)?;
        }
        self.step_except_sh(
            &means,
            grads.quats,
            grads.log_scales,
            grads.opacity_logits,
            skip,
        )
    }

    /// Checks that scene, optimiser state and statistics agree on the number of Gaussians.
    pub fn check_consistency(&self) -> Result<(), TrainError> {
        check_scene(&self.scene)?;
        let n = self.len();
        let expected = groups(self.scene.sh_coeffs_per_gaussian());
        let found: Vec<(&str, usize)> = self
            .adam
            .params()
            .iter()
            .map(|p| (p.name.as_str(), p.width()))
            .collect();
        if found != expected {
            let list = |g: &[(&str, usize)]| {
                g.iter()
                    .map(|(name, w)| format!("{name} ({w})"))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            return Err(TrainError::Shape(format!(
                "the optimiser groups are {}; a scene of SH degree {} needs {}",
                list(&found),
                self.scene.sh_degree,
                list(&expected)
            )));
        }
        for p in self.adam.params() {
            if p.rows() != n {
                return Err(TrainError::Shape(format!(
                    "optimiser group `{}` has {} rows for {n} Gaussians",
                    p.name,
                    p.rows()
                )));
            }
        }
        if !self.stats.is_consistent(n) {
            return Err(TrainError::Shape(format!(
                "densification statistics track {} Gaussians, the model has {n}",
                self.stats.len()
            )));
        }
        if self.active_sh_degree > self.scene.sh_degree {
            return Err(TrainError::Shape(format!(
                "active SH degree {} exceeds the stored degree {}",
                self.active_sh_degree, self.scene.sh_degree
            )));
        }
        Ok(())
    }
}

/// The optimiser groups of a scene with `k` SH coefficients per colour channel, in order, with
/// their widths: the layout [`GaussianModel::new`] builds and [`GaussianModel::check_consistency`]
/// requires (`f_rest` only when `k > 1`).
fn groups(k: usize) -> Vec<(&'static str, usize)> {
    let mut g = vec![(XYZ, 3), (F_DC, 3)];
    if k > 1 {
        g.push((F_REST, 3 * (k - 1)));
    }
    g.extend([(OPACITY, 1), (SCALING, 3), (ROTATION, 4)]);
    g
}

/// Array lengths of a scene without features, as the geometry stage trains it.
pub(crate) fn check_scene(scene: &FeatureGaussians<f32>) -> Result<(), TrainError> {
    let n = scene.len();
    let k = scene.sh_coeffs_per_gaussian();
    if scene.sh_degree > 3
        || scene.log_scales.len() != n
        || scene.quats.len() != n
        || scene.opacity_logits.len() != n
        || scene.sh.len() != n * k
        || scene.features.len() != n * scene.feature_dim
    {
        return Err(TrainError::Shape(format!(
            "inconsistent scene: {n} means, {} log-scales, {} quaternions, {} opacities, {} SH \
             rows for degree {}",
            scene.log_scales.len(),
            scene.quats.len(),
            scene.opacity_logits.len(),
            scene.sh.len(),
            scene.sh_degree
        )));
    }
    Ok(())
}
