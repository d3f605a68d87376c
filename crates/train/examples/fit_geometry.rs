//! Fits a 3DGS scene to a dataset with the geometry stage and reports held-out quality.
//!
//! ```text
//! cargo run --release -p train --example fit_geometry -- DATASET_DIR OUT_DIR \
//!     [--downscale F] [--iterations N] [--white] [--no-eval] [--config FILE.toml]
//!     [--test-iterations a,b,..] [--checkpoint-iterations a,b,..] [--resume CHECKPOINT]
//!     [--log-every N]
//! ```
//!
//! Without `--no-eval`, every 8th image is held out and evaluated at the test iterations. The
//! scene is written to `OUT_DIR/point_cloud/iteration_N/point_cloud.ply` at the save iterations
//! (by default the test iterations). The effective configuration is written to
//! `OUT_DIR/config.toml`.

use std::path::PathBuf;
use std::process::ExitCode;

use gaussian::dataset::{Dataset, LoadOptions, Resolution};
use train::checkpoint::GeometryCheckpoint;
use train::geometry::load_views;
use train::{GeometryConfig, GeometryTrainer};

fn list(s: &str) -> Result<Vec<u64>, String> {
    s.split(',')
        .map(|v| {
            v.trim()
                .parse()
                .map_err(|_| format!("not an iteration: {v}"))
        })
        .collect()
}

fn run() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let (mut dataset_dir, mut out_dir) = (None, None);
    let mut downscale = 1.0f64;
    let mut config = GeometryConfig::default();
    let mut iterations = None;
    let mut eval = true;
    let mut tests = None;
    let mut checkpoints = None;
    let mut resume = None;
    while let Some(a) = args.next() {
        let mut val = || args.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--downscale" => downscale = val()?.parse().map_err(|e| format!("{e}"))?,
            "--iterations" => iterations = Some(val()?.parse().map_err(|e| format!("{e}"))?),
            "--white" => config.background = [1.0; 3],
            "--no-eval" => eval = false,
            "--log-every" => config.log_interval = val()?.parse().map_err(|e| format!("{e}"))?,
            "--config" => {
                let p = val()?;
                let text = std::fs::read_to_string(&p).map_err(|e| format!("{p}: {e}"))?;
                config = toml::from_str(&text).map_err(|e| format!("{p}: {e}"))?;
            }
            "--test-iterations" => tests = Some(list(&val()?)?),
            "--checkpoint-iterations" => checkpoints = Some(list(&val()?)?),
            "--resume" => resume = Some(PathBuf::from(val()?)),
            _ if dataset_dir.is_none() => dataset_dir = Some(PathBuf::from(a)),
            _ if out_dir.is_none() => out_dir = Some(PathBuf::from(a)),
            _ => return Err(format!("unexpected argument {a}")),
        }
    }
    let dataset_dir = dataset_dir.ok_or("missing DATASET_DIR")?;
    let out_dir = out_dir.ok_or("missing OUT_DIR")?;
    if let Some(n) = iterations {
        config.iterations = n;
        config.test_iterations.retain(|&t| t <= n);
        config.save_iterations.retain(|&t| t <= n);
        if !config.test_iterations.contains(&n) {
            config.test_iterations.push(n);
        }
        if !config.save_iterations.contains(&n) {
            config.save_iterations.push(n);
        }
    }
    if let Some(t) = tests {
        config.save_iterations = t.clone();
        config.test_iterations = t;
    }
    if let Some(c) = checkpoints {
        config.checkpoint_iterations = c;
    }
    let options = LoadOptions {
        resolution: if downscale == 1.0 {
            Resolution::Full
        } else {
            Resolution::Downscale(downscale)
        },
        background: config.background,
        ..LoadOptions::default()
    };
    let dataset = Dataset::load(&dataset_dir, &options).map_err(|e| e.to_string())?;
    for w in &dataset.warnings {
        eprintln!("warning: {w}");
    }
    std::fs::create_dir_all(&out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;
    let cfg_text = toml::to_string(&config).map_err(|e| e.to_string())?;
    std::fs::write(out_dir.join("config.toml"), cfg_text).map_err(|e| e.to_string())?;

    let load_start = std::time::Instant::now();
    let mut trainer = match resume {
        None => GeometryTrainer::from_dataset(config, &dataset, eval).map_err(|e| e.to_string())?,
        Some(p) => {
            let split = dataset.split();
            let (train_idx, test_idx) = if eval {
                (split.train, split.test)
            } else {
                ((0..dataset.len()).collect(), Vec::new())
            };
            let ck = GeometryCheckpoint::load(&p).map_err(|e| e.to_string())?;
            GeometryTrainer::resume(
                config,
                ck,
                load_views(&dataset, &train_idx).map_err(|e| e.to_string())?,
                load_views(&dataset, &test_idx).map_err(|e| e.to_string())?,
            )
            .map_err(|e| e.to_string())?
        }
    };
    let k = trainer.train_views[0].camera.intrinsics;
    println!(
        "{} training and {} test views at {}x{}, {} initial Gaussians, extent {:.3} (loaded in {:.1} s)",
        trainer.train_views.len(),
        trainer.test_views.len(),
        k.width,
        k.height,
        trainer.model.len(),
        trainer.extent,
        load_start.elapsed().as_secs_f64()
    );
    let first = trainer.step;
    let summary = trainer
        .train(Some(&out_dir), None)
        .map_err(|e| e.to_string())?;
    for e in &summary.evaluations {
        println!(
            "iteration {}: held-out PSNR {:.3} dB, SSIM {:.4}, L1 {:.5}, {} Gaussians",
            e.step, e.psnr, e.ssim, e.l1, e.gaussians
        );
    }
    println!(
        "{} iterations in {:.1} s ({:.2} it/s), {} Gaussians",
        summary.step - first,
        summary.seconds,
        (summary.step - first) as f64 / summary.seconds,
        summary.gaussians
    );
    Ok(())
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
