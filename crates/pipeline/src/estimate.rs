//! How long each stage of a run will take on this machine: every stage run briefly at the plan's
//! sizes, and the measured costs extrapolated to the plan's schedules ([`estimate`]).
//!
//! - **Geometry.** The geometry stage itself runs from the capture's initial points for its first
//!   tenth (at least ten densification rounds past the start of densification, at most
//!   [`PROBE_SECONDS`]), each step timed, and then a few steps on a scene of `K` times as many
//!   Gaussians, each replaced by `K` copies at `1/sqrt(K)` of its size (so that together they
//!   cover the pixels it covered, as densification's splits do) at the full SH degree. A step's
//!   cost is taken as linear in the number of Gaussians, through these two measurements. The
//!   number: as measured up to the end of the probe; beyond it, growing by a rate per
//!   densification round that falls linearly from its value at the start of the densification
//!   window to zero at its end (the rounds densify fewer Gaussians as the fit improves), the
//!   starting value fitted to the growth over the probe's last half; constant after the window.
//!   At the draft preset this predicts 75k Gaussians where the beer can ends at 72k, and 65k
//!   where lego ends at 44k (its growth slows sooner): the count is the least certain part of
//!   the estimate, and the step cost grows more slowly than the count, so the time errs less.
//! - **Features.** Two feature trainers on two training views and two training paintings, one
//!   on the probe's scene and one on the copied scene: their setup (encoding the views and
//!   paintings) gives the cost of encoding an image, their alignment-only and full steps the
//!   costs of the two kinds of step, each linear in the number of Gaussians and evaluated at the
//!   expected final number.
//! - **Stylize and evaluate.** The two stages on the copied scene's bundle and training
//!   cameras. Stylize with every painting, on one camera and then three: the stage's fixed
//!   cost (the paintings' encoding, the animations, the contact sheet) apart from a frame's,
//!   times the plan's frames. Evaluate with one painting, on three cameras and then eight: a
//!   cost per frame apart from one per compared pair, per row (the colour frames and each
//!   painting's 2D baseline and dsgs frames), times the plan's frames and rows.
//!
//! Stages whose results are already there are not estimated; a finished geometry gives the
//! features and later stages its exact number of Gaussians. Nothing is written outside a
//! scratch folder in the output directory, removed afterwards.

use std::time::Instant;

use base::event::{Quiet, Stage};
use gaussian::dataset::Dataset;
use gaussian::{Camera, FeatureGaussians};
use runtime::SceneBundle;
use train::features::FeatureSetup;
use train::geometry::load_views;
use train::image_folder::collect_images;
use train::{FeatureInputs, FeatureTrainer, GeometryConfig, GeometryTrainer, ImageSet, View};

use crate::error::{Context, Result};
use crate::pretrain_decoder::NetworkFiles;
use crate::run::{
    count, eval_settings, feature_config, features_done, geometry_config, geometry_dir,
    geometry_done, human, stylize_settings, Networks, Plan, RunReport,
};
use crate::Control;

/// The longest the geometry probe runs, in seconds (it stops at the end of the step running
/// then).
pub const PROBE_SECONDS: f64 = 30.0;

/// Timed steps on the copied scene, of each kind.
const TIMED_STEPS: usize = 4;

/// The estimated time of one stage.
#[derive(Clone, Debug, PartialEq)]
pub struct StageEstimate {
    /// The stage's name, as the run's report names it.
    pub stage: &'static str,
    /// Estimated seconds.
    pub seconds: f64,
    /// What the estimate rests on, in a few words.
    pub basis: String,
}

/// The estimated time of a run's stages still to run.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// One per stage still to run, in order.
    pub stages: Vec<StageEstimate>,
    /// The Gaussians the features and later stages are estimated with (expected or known).
    pub gaussians: usize,
    /// Seconds the measurements took.
    pub measured_in: f64,
}

impl Estimate {
    /// The estimate of a stage, if it will run.
    pub fn of(&self, stage: &str) -> Option<f64> {
        self.stages
            .iter()
            .find(|s| s.stage == stage)
            .map(|s| s.seconds)
    }

    /// Each stage's estimated seconds, for [`RunReport::estimated`](crate::run::RunReport).
    pub fn seconds(&self) -> Vec<(&'static str, f64)> {
        self.stages.iter().map(|s| (s.stage, s.seconds)).collect()
    }

    /// The sum over the stages.
    pub fn total(&self) -> f64 {
        self.stages.iter().map(|s| s.seconds).sum()
    }
}

impl std::fmt::Display for Estimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.stages.is_empty() {
            return writeln!(f, "estimate: every stage's result is already there");
        }
        writeln!(
            f,
            "estimate on this machine (measured in {:.0} s):",
            self.measured_in
        )?;
        for s in &self.stages {
            writeln!(f, "{:>9}: ~{} ({})", s.stage, human(s.seconds), s.basis)?;
        }
        writeln!(f, "{:>9}: ~{}", "total", human(self.total()))
    }
}

/// A predicted count, to two significant figures from 10,000 on (`75k`).
fn rounded(n: f64) -> String {
    if n < 10_000.0 {
        format!("{n:.0}")
    } else {
        format!("{:.0}k", n / 1000.0)
    }
}

/// A cost linear in the number of Gaussians, through two measurements `(gaussians, seconds)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearCost {
    /// Seconds at no Gaussians (not below zero).
    pub fixed: f64,
    /// Seconds per Gaussian (not below zero).
    pub per_gaussian: f64,
}

impl LinearCost {
    /// The line through two measurements, its slope and intercept kept non-negative (timing
    /// noise at nearly equal counts can otherwise make either negative).
    pub fn through(a: (f64, f64), b: (f64, f64)) -> LinearCost {
        let slope = if (b.0 - a.0).abs() > 0.0 {
            ((b.1 - a.1) / (b.0 - a.0)).max(0.0)
        } else {
            0.0
        };
        let fixed = (a.1 - slope * a.0).max(0.0);
        LinearCost {
            fixed,
            per_gaussian: slope,
        }
    }

    /// Seconds at `n` Gaussians.
    pub fn at(&self, n: f64) -> f64 {
        self.fixed + self.per_gaussian * n
    }
}

/// The expected number of Gaussians after each iteration of a geometry schedule, from the
/// probe's measurements (see the module documentation).
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianCount {
    /// The count after each probed iteration (index 0: after iteration 1).
    pub measured: Vec<usize>,
    /// Growth per densification round (natural log) at the start of the densification window.
    pub rate: f64,
    /// The first and last iteration densifying, and the rounds' interval.
    pub window: (u64, u64, u64),
}

impl GaussianCount {
    /// The growth rate at the start of densification, from the probe's growth over the last
    /// half of its densifying iterations (0 when it did not densify or shrank).
    pub fn from_probe(measured: Vec<usize>, config: &GeometryConfig) -> GaussianCount {
        let d = &config.densify;
        let window = (
            d.densify_from_iter,
            d.densify_until_iter,
            d.densification_interval.max(1),
        );
        let mut count = GaussianCount {
            measured,
            rate: 0.0,
            window,
        };
        let end = (count.measured.len() as u64).min(window.1);
        if end > window.0 {
            let start = window.0 + (end - window.0) / 2;
            let (a, b) = (count.at(start.max(1)), count.at(end));
            let share = count.share(start, end);
            if share > 0.0 && a > 0.0 && b > a {
                count.rate = (b / a).ln() / share;
            }
        }
        count
    }

    /// The rounds between iterations `a` and `b`, each weighted by its share of the starting
    /// rate (which falls linearly from 1 at the start of the densification window to 0 at its
    /// end): the log growth between them is `rate` times this.
    fn share(&self, a: u64, b: u64) -> f64 {
        let (from, until, every) = self.window;
        if until <= from {
            return 0.0;
        }
        let rounds = (until - from) as f64 / every as f64;
        let u = |it: u64| (it.clamp(from, until) - from) as f64 / (until - from) as f64;
        let integral = |u: f64| u - u * u / 2.0;
        rounds * (integral(u(b)) - integral(u(a)))
    }

    /// The expected count after iteration `it` (from 1).
    pub fn at(&self, it: u64) -> f64 {
        let probed = self.measured.len() as u64;
        if it <= probed {
            return self.measured[(it.max(1) - 1) as usize] as f64;
        }
        let last = *self.measured.last().unwrap_or(&0) as f64;
        last * (self.rate * self.share(probed, it)).exp()
    }

    /// The expected count at the end of a schedule of `iterations`.
    pub fn final_count(&self, iterations: u64) -> f64 {
        self.at(iterations)
    }
}

/// `K` copies of every Gaussian at `1/sqrt(K)` of its size, spread about its centre by half its
/// largest scale along fixed directions: a scene covering the same pixels with `K` times the
/// Gaussians, for timing larger scenes.
pub fn split_copies(scene: &FeatureGaussians<f32>, k: usize) -> FeatureGaussians<f32> {
    let k = k.max(1);
    let shrink = 0.5 * (k as f32).ln();
    let coeffs = scene.sh.len() / scene.len().max(1);
    let mut out = FeatureGaussians {
        means: Vec::with_capacity(scene.len() * k),
        log_scales: Vec::with_capacity(scene.len() * k),
        quats: Vec::with_capacity(scene.len() * k),
        opacity_logits: Vec::with_capacity(scene.len() * k),
        sh_degree: scene.sh_degree,
        sh: Vec::with_capacity(scene.sh.len() * k),
        feature_dim: 0,
        features: Vec::new(),
    };
    for i in 0..scene.len() {
        let ls = scene.log_scales[i];
        let reach = 0.5 * ls[0].max(ls[1]).max(ls[2]).exp();
        for c in 0..k {
            // Directions on a golden-angle spiral over the sphere.
            let t = (c as f32 + 0.5) / k as f32;
            let z = 1.0 - 2.0 * t;
            let ring = (1.0 - z * z).max(0.0).sqrt();
            let phi = c as f32 * 2.399_963;
            let d = [ring * phi.cos(), ring * phi.sin(), z];
            let m = scene.means[i];
            out.means.push([
                m[0] + reach * d[0],
                m[1] + reach * d[1],
                m[2] + reach * d[2],
            ]);
            out.log_scales
                .push([ls[0] - shrink, ls[1] - shrink, ls[2] - shrink]);
            out.quats.push(scene.quats[i]);
            out.opacity_logits.push(scene.opacity_logits[i]);
            out.sh
                .extend_from_slice(&scene.sh[i * coeffs..(i + 1) * coeffs]);
        }
    }
    out
}

/// Mean seconds of `n` calls of `step` after one untimed call.
fn time_steps(n: usize, mut step: impl FnMut() -> Result<()>) -> Result<f64> {
    step()?;
    let t = Instant::now();
    for _ in 0..n {
        step()?;
    }
    Ok(t.elapsed().as_secs_f64() / n.max(1) as f64)
}

/// The network files of a plan (its weights file, or the checkpoints it imports).
fn network_files(s: &Plan) -> NetworkFiles {
    match &s.networks {
        Networks::File(w) => NetworkFiles {
            weights: Some(w.clone()),
            encoder: None,
            decoder: s.decoder.clone(),
        },
        Networks::Import { encoder, decoder } => NetworkFiles {
            weights: None,
            encoder: Some(encoder.clone()),
            // No decoder file: the built-in one (`NetworkFiles::load_decoder`).
            decoder: s.decoder.clone().or_else(|| decoder.clone()),
        },
    }
}

/// What the geometry probe measured.
struct GeometryProbe {
    count: GaussianCount,
    step: LinearCost,
    /// Seconds of an evaluation of the held-out views, loading the images and writing the
    /// outputs (measured once).
    overhead: f64,
    /// The probe's scene.
    scene: FeatureGaussians<f32>,
}

/// Runs the geometry probe (see the module documentation).
fn probe_geometry(s: &Plan, dataset: &Dataset, cfg: &GeometryConfig) -> Result<GeometryProbe> {
    let started = Instant::now();
    let split = dataset.split();
    let train = load_views(dataset, &split.train)?;
    let test = load_views(dataset, &split.test)?;
    let load = started.elapsed().as_secs_f64();
    let mut trainer = GeometryTrainer::from_dataset(cfg.clone(), dataset, true)
        .with_context(|| format!("starting the geometry of {}", s.dataset.display()))?;
    let d = &cfg.densify;
    let wanted = (cfg.iterations / 10)
        .max(d.densify_from_iter + 10 * d.densification_interval.max(1))
        .min(cfg.iterations)
        .max(1);
    let mut counts = Vec::new();
    let mut seconds = Vec::new();
    let probe = Instant::now();
    while (counts.len() as u64) < wanted && probe.elapsed().as_secs_f64() < PROBE_SECONDS {
        let t = Instant::now();
        let r = trainer.train_step()?;
        seconds.push(t.elapsed().as_secs_f64());
        counts.push(r.gaussians);
    }
    let half = counts.len() / 2;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let small = (
        counts[half..].iter().map(|&n| n as f64).sum::<f64>() / (counts.len() - half) as f64,
        mean(&seconds[half..]),
    );
    let count = GaussianCount::from_probe(counts, cfg);
    let expected = count.final_count(cfg.iterations);
    let scene = trainer.model.scene.clone();
    let k = ((expected / scene.len().max(1) as f64).round() as usize).clamp(2, 16);
    let copies = split_copies(&scene, k);
    let n_copies = copies.len() as f64;
    let mut big = GeometryTrainer::new(cfg.clone(), copies, train.clone(), test)?;
    // At the full SH degree, as the schedule's later steps are.
    for _ in 0..cfg.sh_degree {
        big.model.one_up_sh_degree();
    }
    let per_step = time_steps(TIMED_STEPS, || {
        big.train_step()?;
        Ok(())
    })?;
    let t = Instant::now();
    big.evaluate()?;
    let overhead = load + t.elapsed().as_secs_f64();
    Ok(GeometryProbe {
        count,
        step: LinearCost::through(small, (n_copies, per_step)),
        overhead,
        scene,
    })
}

/// What the feature probe measured.
struct FeatureProbe {
    encode_image: f64,
    align: LinearCost,
    full: LinearCost,
    /// The bundles of the probe's scene and of the copied scene, for the stylize and eval
    /// probes.
    bundles: [SceneBundle; 2],
    /// The expected final number of Gaussians.
    expected: f64,
    cameras: Vec<Camera>,
    /// Up to eight training cameras, for the eval probe.
    eval_cameras: Vec<Camera>,
}

/// Runs the feature probe on `scene` and its copies at about `expected` Gaussians.
fn probe_features(
    s: &Plan,
    dataset: &Dataset,
    scene: &FeatureGaussians<f32>,
    expected: f64,
) -> Result<FeatureProbe> {
    let fc = feature_config(s);
    let split = dataset.split();
    let picked: Vec<usize> = split.train.iter().copied().take(3).collect();
    let views: Vec<View> = load_views(dataset, &picked)?;
    let cameras = views.iter().map(|v| v.camera).collect();
    let paintings = collect_images(&s.training_styles, false)?;
    let nets = network_files(s);
    let mut config = fc.features.clone();
    // Step 1 and step 1 + TIMED_STEPS + 1 are untimed warm-ups of each kind.
    config.align_warmup = 1 + TIMED_STEPS as u64;
    config.iterations = 2 * (1 + TIMED_STEPS as u64);
    config.checkpoint_interval = 0;
    let k = ((expected / scene.len().max(1) as f64).round() as usize).clamp(2, 16);
    let mut measured = Vec::new();
    let mut bundles = Vec::new();
    for geometry in [scene.clone(), split_copies(scene, k)] {
        let n = geometry.len() as f64;
        let inputs = FeatureInputs {
            geometry,
            views: views[..2.min(views.len())].to_vec(),
            cameras: Vec::new(),
            styles: ImageSet::from_files(paintings.iter().take(2).cloned().collect())?,
            encoder: nets.load_encoder()?,
            decoder: nets.load_decoder()?,
            background: fc.background,
            provenance: Vec::new(),
        };
        let encoded = (inputs.views.len() + paintings.len().min(2)) as f64;
        let t = Instant::now();
        let mut trainer = FeatureTrainer::new_with(config.clone(), inputs, &FeatureSetup::quiet())
            .context("setting up the feature probe")?;
        let setup = t.elapsed().as_secs_f64() / encoded;
        let align = time_steps(TIMED_STEPS, || {
            trainer.train_step()?;
            Ok(())
        })?;
        let full = time_steps(TIMED_STEPS, || {
            trainer.train_step()?;
            Ok(())
        })?;
        measured.push((n, setup, align, full));
        bundles.push(trainer.bundle());
    }
    let (a, b) = (measured[0], measured[1]);
    Ok(FeatureProbe {
        encode_image: 0.5 * (a.1 + b.1),
        align: LinearCost::through((a.0, a.2), (b.0, b.2)),
        full: LinearCost::through((a.0, a.3), (b.0, b.3)),
        bundles: [bundles.remove(0), bundles.remove(0)],
        expected,
        cameras,
        eval_cameras: split
            .train
            .iter()
            .take(8)
            .map(|&i| dataset.cameras[i])
            .collect(),
    })
}

/// Measures the stages of `s` still to run (see the module documentation).
pub fn estimate(s: &Plan) -> Result<Estimate> {
    let started = Instant::now();
    let mut stages = Vec::new();
    let gcfg = geometry_config(s);
    let dataset = Dataset::load(&s.dataset, &gcfg.load_options()?)
        .with_context(|| format!("loading the dataset {}", s.dataset.display()))?;
    let geometry_ply = geometry_dir(s).join("point_cloud.ply");
    let (scene, expected) = if geometry_done(s) {
        let scene = gaussian::ply::load_ply(&geometry_ply)
            .with_context(|| format!("reading the geometry {}", geometry_ply.display()))?;
        let n = scene.len() as f64;
        (scene, n)
    } else {
        let g = &gcfg.geometry;
        let probe = probe_geometry(s, &dataset, g)?;
        let resumed_at = crate::run::geometry_progress(s);
        let steps: f64 = (resumed_at + 1..=g.iterations)
            .map(|it| probe.step.at(probe.count.at(it)))
            .sum();
        let expected = probe.count.final_count(g.iterations);
        stages.push(StageEstimate {
            stage: "geometry",
            seconds: steps + probe.overhead,
            basis: format!(
                "{} iterations from {} to about {} Gaussians",
                g.iterations - resumed_at.min(g.iterations),
                probe.count.measured.first().copied().unwrap_or(0),
                rounded(expected)
            ),
        });
        (probe.scene, expected)
    };
    if !features_done(s) || !crate::run::outputs_done(s) {
        let probe = probe_features(s, &dataset, &scene, expected)?;
        if !features_done(s) {
            let views = dataset.split().train.len();
            let paintings = collect_images(&s.training_styles, false)?.len();
            let warm = s.align_warmup.min(s.feature_iterations) as f64;
            let full = s.feature_iterations as f64 - warm;
            let seconds = probe.encode_image * (views + paintings) as f64
                + warm * probe.align.at(expected)
                + full * probe.full.at(expected);
            stages.push(StageEstimate {
                stage: "features",
                seconds,
                basis: format!(
                    "{} and {} encoded, {} + {} iterations",
                    count(views, "view"),
                    count(paintings, "painting"),
                    warm,
                    full
                ),
            });
        }
        stages.extend(probe_outputs(s, &probe)?);
    }
    Ok(Estimate {
        stages,
        gaussians: expected as usize,
        measured_in: started.elapsed().as_secs_f64(),
    })
}

/// Runs the plan as [`execute`](crate::run::execute) does, after reporting to the control's
/// sink (as log lines) that the stages are being timed and then their [`estimate`]; the report
/// carries the estimate beside the stages' times.
pub fn execute_estimated(s: &Plan, control: &Control) -> Result<RunReport> {
    crate::run::check_inputs(s)?;
    control.log(
        Stage::Prepare,
        "timing a few steps of each stage on this machine (--no-estimate skips this)",
    );
    let e = estimate(s)?;
    control.log(Stage::Prepare, e.to_string().trim_end());
    let mut report = crate::run::execute(s, control)?;
    report.estimated = e.seconds();
    Ok(report)
}

/// Times the stylize and eval stages for a painting and the probe's cameras, scaled to the
/// plan's frames and paintings.
fn probe_outputs(s: &Plan, probe: &FeatureProbe) -> Result<Vec<StageEstimate>> {
    let scratch = s.out_dir.join(".estimate");
    let result = (|| -> Result<Vec<StageEstimate>> {
        let bundle = &probe.bundles[1];
        // The stage as it runs, with every painting: a frame is rasterized once and decoded
        // once per painting, and the paintings share the contact sheet's colour row.
        let every = stylize_settings(s, scratch.clone());
        let frames = probe.cameras.len() as f64;
        let outputs = s.styles.len() as f64;
        // One camera, then all: the difference is the cost of the other frames, the rest the
        // stage's fixed cost (encoding the paintings, the animations, the contact sheet). Each
        // the faster of two runs, after a first, untimed one (the first use of the buffers):
        // the runs are short, and a busy machine's pauses would otherwise swamp them.
        crate::stylize::run(bundle, &probe.cameras[..1], &every, &Quiet)?;
        let stylize_time = |cameras: &[Camera]| -> Result<f64> {
            let mut best = f64::INFINITY;
            for _ in 0..2 {
                let t = Instant::now();
                crate::stylize::run(bundle, cameras, &every, &Quiet)?;
                best = best.min(t.elapsed().as_secs_f64());
            }
            Ok(best)
        };
        let one = stylize_time(&probe.cameras[..1])?;
        let all = stylize_time(&probe.cameras)?;
        let (per_frame, fixed) = if frames > 1.0 {
            let per_frame = ((all - one) / (frames - 1.0)).max(0.0);
            (per_frame, (one - per_frame).max(0.0))
        } else {
            (one, 0.0)
        };
        // A frame's feature raster, measured on the copies, costs what it costs at the
        // expected number of Gaussians: linear through the probe's scene and the copies.
        let raster = |b: &SceneBundle| -> Result<f64> {
            let mut best = f64::INFINITY;
            for _ in 0..2 {
                let mut sum = 0.0;
                for c in &probe.cameras {
                    sum += b.feature_view(c)?.raster_seconds;
                }
                best = best.min(sum / frames);
            }
            Ok(best)
        };
        let [scene, copies] = &probe.bundles;
        let on_copies = raster(copies)?;
        let expected = LinearCost::through(
            (scene.scene.len() as f64, raster(scene)?),
            (copies.scene.len() as f64, on_copies),
        )
        .at(probe.expected);
        let per_frame = (per_frame - on_copies).max(0.0) + expected;
        // Three cameras (2 short-range pairs, no long-range one), then eight (7 and 1), with
        // one painting: per row (colour, the painting's 2D baseline, dsgs), a cost per frame
        // and one per pair.
        let mut one_painting = every.clone();
        one_painting.styles.truncate(1);
        let eval_time = |cameras: &[Camera]| -> Result<f64> {
            let t = Instant::now();
            crate::eval::evaluate_bundle(
                bundle,
                "estimate",
                cameras,
                &eval_settings(&one_painting, scratch.join("eval")),
                &Quiet,
            )?;
            Ok(t.elapsed().as_secs_f64() / 3.0)
        };
        let few = eval_time(&probe.eval_cameras[..3.min(probe.eval_cameras.len())])?;
        let many = eval_time(&probe.eval_cameras)?;
        let (per_frame_row, per_pair_row) = if probe.eval_cameras.len() == 8 {
            // few = 3 f + 2 p, many = 8 f + 8 p.
            let f = few - many / 4.0;
            let p = many / 8.0 - f;
            match (f >= 0.0, p >= 0.0) {
                (true, true) => (f, p),
                (false, _) => (0.0, many / 8.0),
                (_, false) => (many / 8.0, 0.0),
            }
        } else {
            (many / probe.eval_cameras.len() as f64, 0.0)
        };
        let pairs = |frames: usize, gap: usize| frames.saturating_sub(gap) as f64;
        let rows = 2.0 * outputs + 1.0;
        let eval_seconds = rows
            * (per_frame_row * s.frames as f64
                + per_pair_row * (pairs(s.frames, 1) + pairs(s.frames, 7)));
        let n = s.frames as f64;
        Ok(vec![
            StageEstimate {
                stage: "stylize",
                seconds: fixed + per_frame * n,
                basis: format!(
                    "{} x {}",
                    count(s.frames, "frame"),
                    count(s.styles.len(), "painting")
                ),
            },
            StageEstimate {
                stage: "eval",
                seconds: eval_seconds,
                basis: format!(
                    "{} x colour, and 2D and dsgs for {}",
                    count(s.frames, "frame"),
                    count(s.styles.len(), "painting")
                ),
            },
        ])
    })();
    let _ = std::fs::remove_dir_all(&scratch);
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_through_two_measurements_passes_through_both() {
        let c = LinearCost::through((1000.0, 0.012), (9000.0, 0.044));
        assert!((c.at(1000.0) - 0.012).abs() < 1e-15);
        assert!((c.at(9000.0) - 0.044).abs() < 1e-15);
        // Noise making the larger scene faster gives a flat cost, never a negative slope.
        let flat = LinearCost::through((1000.0, 0.02), (9000.0, 0.019));
        assert_eq!(flat.per_gaussian, 0.0);
        assert!((flat.at(5e6) - 0.02).abs() < 1e-15);
    }

    fn config(from: u64, until: u64, every: u64) -> GeometryConfig {
        let mut c = GeometryConfig::default();
        c.densify.densify_from_iter = from;
        c.densify.densify_until_iter = until;
        c.densify.densification_interval = every;
        c
    }

    #[test]
    fn counts_grow_at_a_rate_falling_linearly_over_the_densification_window() {
        // A count following the model exactly: 20 rounds of 10 iterations from iteration 50 to
        // 250, the log growth rate r0 (1 - u) per round at the fraction u of the window, so
        // ln N(u) = ln N0 + 20 r0 (u - u^2 / 2). The probe sees its first 120 iterations.
        let (n0, r0) = (1.0e6, 0.05);
        let cfg = config(50, 250, 10);
        let truth = |it: u64| {
            let u = (it.clamp(50, 250) - 50) as f64 / 200.0;
            n0 * (20.0 * r0 * (u - u * u / 2.0)).exp()
        };
        let measured: Vec<usize> = (1..=120u64).map(|it| truth(it).round() as usize).collect();
        let c = GaussianCount::from_probe(measured.clone(), &cfg);
        assert!((c.rate - r0).abs() < 1e-5, "{}", c.rate);
        assert_eq!(c.at(40), measured[39] as f64);
        // Half the window's full growth, 20 r0 / 2, is reached at its end; nothing after.
        let end = n0 * (10.0 * r0).exp();
        assert!((c.at(250) - end).abs() < 1e-5 * end, "{} {end}", c.at(250));
        assert_eq!(c.at(400), c.at(250));
        assert!((121..250).all(|it| c.at(it) <= c.at(it + 1)));
    }

    #[test]
    fn a_shrinking_or_undensified_probe_predicts_no_growth() {
        let cfg = config(50, 250, 10);
        let shrinking: Vec<usize> = (0..100).map(|i| 5000 - 10 * i).collect();
        let c = GaussianCount::from_probe(shrinking, &cfg);
        assert_eq!(c.rate, 0.0);
        assert_eq!(c.final_count(1000), 5000.0 - 990.0);
        let early = GaussianCount::from_probe(vec![7; 30], &cfg);
        assert_eq!(early.final_count(1000), 7.0);
    }

    #[test]
    fn copies_multiply_the_count_and_shrink_the_scales() {
        let mut scene = FeatureGaussians::<f32> {
            sh_degree: 1,
            ..Default::default()
        };
        for i in 0..3 {
            scene.means.push([i as f32, 0.0, 0.0]);
            scene.log_scales.push([-2.0, -3.0, -1.0]);
            scene.quats.push([1.0, 0.0, 0.0, 0.0]);
            scene.opacity_logits.push(0.5);
            for c in 0..4 {
                scene.sh.push([i as f32, c as f32, 0.0]);
            }
        }
        let copies = split_copies(&scene, 4);
        assert_eq!(copies.len(), 12);
        assert_eq!(copies.sh.len(), 48);
        let shrink = 0.5 * 4f32.ln();
        assert!((copies.log_scales[5][2] - (-1.0 - shrink)).abs() < 1e-6);
        // Each copy keeps its original's colour and stays within its largest scale.
        assert_eq!(copies.sh[5 * 4 + 3], [1.0, 3.0, 0.0]);
        let reach = (-1.0f32).exp();
        for (j, m) in copies.means.iter().enumerate() {
            let o = (j / 4) as f32;
            let d = ((m[0] - o).powi(2) + m[1].powi(2) + m[2].powi(2)).sqrt();
            assert!(d <= reach, "{d}");
        }
    }
}
