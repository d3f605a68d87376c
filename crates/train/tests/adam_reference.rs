//! Adam against a straightforward f64 transcription of the algorithm as the PyTorch
//! documentation states it (`torch.optim.Adam`, amsgrad off, no weight decay):
//!
//! ```text
//! m_t = b1 m_{t-1} + (1 - b1) g_t
//! v_t = b2 v_{t-1} + (1 - b2) g_t^2
//! m_hat = m_t / (1 - b1^t),  v_hat = v_t / (1 - b2^t)
//! theta_t = theta_{t-1} - lr m_hat / (sqrt(v_hat) + eps)
//! ```
//!
//! The optimiser rearranges these formulas the way PyTorch's implementation does (lerp for `m`,
//! `sqrt(v) / sqrt(1 - b2^t)`), so the two agree to rounding, not bit for bit. Tolerance: 1e-12
//! relative (infinity norm), a few hundred ulps of f64 after several steps of a handful of
//! operations each; an error in any formula (a missing bias correction, eps inside the square
//! root) shows up at 1e-3 or more.

use dsgs_testkit::assert_close;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use train::{Adam, AdamConfig};

const TOL: f64 = 1e-12;

/// The textbook algorithm for one tensor.
struct Reference {
    lr: f64,
    b1: f64,
    b2: f64,
    eps: f64,
    t: i32,
    m: Vec<f64>,
    v: Vec<f64>,
}

impl Reference {
    fn new(lr: f64, cfg: AdamConfig, n: usize) -> Self {
        Reference {
            lr,
            b1: cfg.beta1,
            b2: cfg.beta2,
            eps: cfg.eps,
            t: 0,
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }

    fn step(&mut self, theta: &mut [f64], g: &[f64]) {
        self.t += 1;
        for i in 0..theta.len() {
            self.m[i] = self.b1 * self.m[i] + (1.0 - self.b1) * g[i];
            self.v[i] = self.b2 * self.v[i] + (1.0 - self.b2) * g[i] * g[i];
            let m_hat = self.m[i] / (1.0 - self.b1.powi(self.t));
            let v_hat = self.v[i] / (1.0 - self.b2.powi(self.t));
            theta[i] -= self.lr * m_hat / (v_hat.sqrt() + self.eps);
        }
    }
}

fn random_vec(rng: &mut StdRng, n: usize, scale: f64) -> Vec<f64> {
    (0..n).map(|_| rng.random_range(-scale..scale)).collect()
}

#[test]
fn adam_matches_the_documented_algorithm_over_many_steps() {
    let mut rng = StdRng::seed_from_u64(7);
    for (cfg, lr) in [
        (AdamConfig::default(), 1e-4),
        (
            AdamConfig {
                beta1: 0.8,
                beta2: 0.99,
                eps: 1e-15,
            },
            0.05,
        ),
    ] {
        let n = 1000;
        let mut theta = random_vec(&mut rng, n, 1.0);
        let mut theta_ref = theta.clone();
        let mut adam = Adam::<f64>::new(cfg);
        let id = adam.add_param("w", lr, n, 1);
        let mut reference = Reference::new(lr, cfg, n);
        for step in 0..25 {
            // gradients of widely varying magnitude, some exactly zero
            let scale = 10f64.powi(step % 7 - 3);
            let mut g = random_vec(&mut rng, n, scale);
            g[3] = 0.0;
            adam.step(id, &mut theta, &g).unwrap();
            reference.step(&mut theta_ref, &g);
            assert_close("theta", &theta, &theta_ref, TOL);
        }
        assert_close("exp_avg", adam.params()[0].exp_avg(), &reference.m, TOL);
        assert_close(
            "exp_avg_sq",
            adam.params()[0].exp_avg_sq(),
            &reference.v,
            TOL,
        );
        assert_eq!(adam.params()[0].step_count(), 25);
    }
}

#[test]
fn the_first_step_moves_every_element_by_the_learning_rate() {
    // With zero moments, the bias-corrected first step is lr * g / (|g| + eps): a sign step.
    let cfg = AdamConfig {
        eps: 1e-15,
        ..AdamConfig::default()
    };
    let mut adam = Adam::<f64>::new(cfg);
    let id = adam.add_param("w", 0.01, 4, 1);
    let mut theta = vec![1.0, 1.0, 1.0, 1.0];
    adam.step(id, &mut theta, &[3.0, -1e-3, 0.0, 250.0])
        .unwrap();
    let expected = [0.99, 1.01, 1.0, 0.99];
    assert_close("first step", &theta, &expected, 1e-12);
}

#[test]
fn per_tensor_learning_rates_and_strided_columns_act_independently() {
    let cfg = AdamConfig::default();
    let mut rng = StdRng::seed_from_u64(11);
    let rows = 37;
    // an interleaved array of width 8 whose first 3 columns and last 5 columns are two tensors
    let mut packed = random_vec(&mut rng, rows * 8, 1.0);
    let mut dc: Vec<f64> = (0..rows)
        .flat_map(|r| packed[r * 8..r * 8 + 3].to_vec())
        .collect();
    let mut rest: Vec<f64> = (0..rows)
        .flat_map(|r| packed[r * 8 + 3..r * 8 + 8].to_vec())
        .collect();
    let mut adam = Adam::<f64>::new(cfg);
    let a = adam.add_param("dc", 2.5e-3, rows, 3);
    let b = adam.add_param("rest", 2.5e-3 / 20.0, rows, 5);
    let mut ref_a = Reference::new(2.5e-3, cfg, rows * 3);
    let mut ref_b = Reference::new(2.5e-3 / 20.0, cfg, rows * 5);
    for _ in 0..5 {
        let g = random_vec(&mut rng, rows * 8, 1.0);
        let g_dc: Vec<f64> = (0..rows)
            .flat_map(|r| g[r * 8..r * 8 + 3].to_vec())
            .collect();
        let g_rest: Vec<f64> = (0..rows)
            .flat_map(|r| g[r * 8 + 3..r * 8 + 8].to_vec())
            .collect();
        adam.step_strided(a, &mut packed, &g, 8, 0).unwrap();
        adam.step_strided(b, &mut packed, &g, 8, 3).unwrap();
        ref_a.step(&mut dc, &g_dc);
        ref_b.step(&mut rest, &g_rest);
    }
    let got_dc: Vec<f64> = (0..rows)
        .flat_map(|r| packed[r * 8..r * 8 + 3].to_vec())
        .collect();
    let got_rest: Vec<f64> = (0..rows)
        .flat_map(|r| packed[r * 8 + 3..r * 8 + 8].to_vec())
        .collect();
    assert_close("dc", &got_dc, &dc, TOL);
    assert_close("rest", &got_rest, &rest, TOL);
}

#[test]
fn row_surgery_keeps_state_aligned_with_the_surviving_rows() {
    // Prune some rows and append new ones mid-training, as density control does. Surviving rows
    // must continue exactly as if nothing happened; new rows start from zero moments but share the
    // tensor's step count (3DGS concatenates zeros to exp_avg / exp_avg_sq and keeps 'step').
    let cfg = AdamConfig::default();
    let mut rng = StdRng::seed_from_u64(3);
    let (rows, width) = (20, 3);
    let mut theta = random_vec(&mut rng, rows * width, 1.0);
    let mut adam = Adam::<f64>::new(cfg);
    let id = adam.add_param("xyz", 1e-3, rows, width);
    let mut reference = Reference::new(1e-3, cfg, rows * width);
    let mut theta_ref = theta.clone();
    for _ in 0..4 {
        let g = random_vec(&mut rng, rows * width, 1.0);
        adam.step(id, &mut theta, &g).unwrap();
        reference.step(&mut theta_ref, &g);
    }
    let keep: Vec<bool> = (0..rows).map(|r| r % 3 != 1).collect();
    adam.param_mut(id).retain_rows(&keep).unwrap();
    let filter = |v: &[f64]| -> Vec<f64> {
        v.chunks(width)
            .zip(&keep)
            .filter(|(_, &k)| k)
            .flat_map(|(c, _)| c.to_vec())
            .collect()
    };
    theta = filter(&theta);
    theta_ref = filter(&theta_ref);
    reference.m = filter(&reference.m);
    reference.v = filter(&reference.v);
    let added = 5;
    adam.param_mut(id).extend_rows(added);
    let new_rows = random_vec(&mut rng, added * width, 1.0);
    theta.extend_from_slice(&new_rows);
    theta_ref.extend_from_slice(&new_rows);
    reference.m.extend(std::iter::repeat_n(0.0, added * width));
    reference.v.extend(std::iter::repeat_n(0.0, added * width));
    let kept = keep.iter().filter(|&&k| k).count();
    assert_eq!(adam.params()[id].rows(), kept + added);
    assert!(adam.params()[id].exp_avg()[kept * width..]
        .iter()
        .all(|&m| m == 0.0));
    for _ in 0..3 {
        let g = random_vec(&mut rng, (kept + added) * width, 1.0);
        adam.step(id, &mut theta, &g).unwrap();
        reference.step(&mut theta_ref, &g);
    }
    assert_close("theta after surgery", &theta, &theta_ref, TOL);
    assert_close(
        "exp_avg after surgery",
        adam.params()[id].exp_avg(),
        &reference.m,
        TOL,
    );
    assert_eq!(adam.params()[id].step_count(), 7);

    // zero_moments (opacity reset): moments vanish, the step count stays
    adam.param_mut(id).zero_moments();
    assert!(adam.params()[id].exp_avg_sq().iter().all(|&v| v == 0.0));
    assert_eq!(adam.params()[id].step_count(), 7);
}

#[test]
fn mismatched_lengths_are_errors_not_panics() {
    let mut adam = Adam::<f32>::new(AdamConfig::default());
    let id = adam.add_param("w", 1e-3, 4, 3);
    let mut p = vec![0.0f32; 12];
    assert!(adam.step(id, &mut p, &[0.0; 11]).is_err());
    assert!(adam.step(id, &mut p[..9], &[0.0; 9]).is_err());
    assert!(adam.step_strided(id, &mut p, &[0.0; 12], 3, 1).is_err());
    assert!(adam.param_mut(id).retain_rows(&[true; 3]).is_err());
    let err = adam.step(id, &mut p, &[0.0; 11]).unwrap_err().to_string();
    assert!(err.contains("`w`"), "{err}");
}
