//! Learning-rate schedules.
//!
//! [`ExponentialLr`] is the schedule of the 3DGS trainer (`get_expon_lr_func` of the original
//! code): a log-linear interpolation from `lr_init` at step 0 to `lr_final` at `max_steps`, held
//! constant afterwards, optionally multiplied during the first `delay_steps` by a warm-up factor
//! that rises from `delay_mult` to 1 along a quarter sine.

use serde::{Deserialize, Serialize};

/// A log-linear learning-rate decay with an optional sine warm-up.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExponentialLr {
    /// Learning rate at step 0 (before the warm-up factor).
    pub lr_init: f64,
    /// Learning rate from `max_steps` on.
    pub lr_final: f64,
    /// Steps of warm-up; 0 disables it (the 3DGS default).
    pub delay_steps: u64,
    /// Warm-up factor at step 0.
    pub delay_mult: f64,
    /// Step at which `lr_final` is reached.
    pub max_steps: u64,
}

impl ExponentialLr {
    /// The 3DGS position schedule: 1.6e-4 to 1.6e-6 over 30,000 steps, both multiplied by
    /// `spatial_scale` (the scene extent), delay multiplier 0.01 without delay steps.
    pub fn position_3dgs(spatial_scale: f64) -> Self {
        ExponentialLr {
            lr_init: 1.6e-4 * spatial_scale,
            lr_final: 1.6e-6 * spatial_scale,
            delay_steps: 0,
            delay_mult: 0.01,
            max_steps: 30_000,
        }
    }

    /// The learning rate at `step`.
    pub fn at(&self, step: u64) -> f64 {
        if self.lr_init == 0.0 && self.lr_final == 0.0 {
            return 0.0;
        }
        let delay_rate = if self.delay_steps > 0 {
            let s = (step as f64 / self.delay_steps as f64).clamp(0.0, 1.0);
            self.delay_mult + (1.0 - self.delay_mult) * (0.5 * std::f64::consts::PI * s).sin()
        } else {
            1.0
        };
        let t = if self.max_steps == 0 {
            1.0
        } else {
            (step as f64 / self.max_steps as f64).clamp(0.0, 1.0)
        };
        let log_lerp = (self.lr_init.ln() * (1.0 - t) + self.lr_final.ln() * t).exp();
        delay_rate * log_lerp
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn position_schedule_hits_its_end_points_and_is_log_linear() {
        let s = ExponentialLr::position_3dgs(2.0);
        assert!((s.at(0) - 3.2e-4).abs() < 1e-18);
        assert!((s.at(30_000) - 3.2e-6).abs() < 1e-18);
        assert!((s.at(90_000) - 3.2e-6).abs() < 1e-18);
        // halfway in log space: the geometric mean of the end points
        let mid = (3.2e-4f64 * 3.2e-6).sqrt();
        assert!((s.at(15_000) - mid).abs() < 1e-15 * mid.max(1.0));
        // constant ratio per step
        let r1 = s.at(1001) / s.at(1000);
        let r2 = s.at(20_001) / s.at(20_000);
        assert!((r1 - r2).abs() < 1e-12);
        assert!((r1 - (0.01f64).powf(1.0 / 30_000.0)).abs() < 1e-12);
    }

    #[test]
    fn warm_up_rises_from_the_delay_multiplier() {
        let s = ExponentialLr {
            lr_init: 1.0,
            lr_final: 1.0,
            delay_steps: 100,
            delay_mult: 0.01,
            max_steps: 1000,
        };
        assert!((s.at(0) - 0.01).abs() < 1e-15);
        let half = 0.01 + 0.99 * (0.25 * std::f64::consts::PI).sin();
        assert!((s.at(50) - half).abs() < 1e-15);
        assert!((s.at(100) - 1.0).abs() < 1e-15);
        assert!((s.at(500) - 1.0).abs() < 1e-15);
    }
}
