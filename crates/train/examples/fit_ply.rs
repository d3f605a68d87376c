//! Fits 3D Gaussians to a posed dataset with the geometry trainer and writes them as a 3DGS
//! `.ply`, printing the training driver's log lines and the held-out evaluation.
//!
//! ```text
//! fit_ply DATASET OUT.ply ITERATIONS
//! ```
//!
//! DATASET is a COLMAP, NeRF-synthetic or LLFF folder. Images are fitted at most `MAX_SIDE`
//! (128) pixels on their longer side over a black background, every 8th one is held out and
//! evaluated after the last iteration; every other setting is the 3DGS default. This is a
//! demonstration of the library: the `dsgs fit-geometry` command is the full stage
//! (configuration files, checkpoints, resume).

use std::path::Path;

use anyhow::{bail, Context, Result};
use gaussian::{Dataset, LoadOptions};
use train::{Event, GeometryConfig, GeometryTrainer, Run};

/// The longest image side trained on, so that a few hundred iterations take seconds.
const MAX_SIDE: u32 = 128;

const USAGE: &str = "usage: fit_ply DATASET OUT.ply ITERATIONS";

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [dataset_dir, out, iterations] = args.as_slice() else {
        bail!("{USAGE}");
    };
    let Some(iterations) = iterations.parse::<u64>().ok().filter(|&n| n > 0) else {
        bail!("ITERATIONS must be a positive whole number, got `{iterations}`\n{USAGE}");
    };

    let mut dataset = Dataset::load(dataset_dir, &LoadOptions::default())
        .with_context(|| format!("loading the dataset {dataset_dir}"))?;
    for w in &dataset.warnings {
        eprintln!("warning: {w}");
    }
    // Images are decoded lazily at their camera's size: smaller cameras make smaller images.
    for camera in &mut dataset.cameras {
        let k = camera.intrinsics;
        let factor = MAX_SIDE as f64 / k.width.max(k.height) as f64;
        if factor < 1.0 {
            *camera = camera.scaled(factor);
        }
    }

    let config = GeometryConfig {
        iterations,
        test_iterations: vec![iterations],
        save_iterations: vec![],
        log_interval: (iterations / 10).max(1),
        ..GeometryConfig::default().scaled_to(iterations)
    };
    let mut trainer = GeometryTrainer::from_dataset(config, &dataset, true)?;
    let k = trainer.train_views[0].camera.intrinsics;
    let (train, test) = (trainer.train_views.len(), trainer.test_views.len());
    let gaussians = trainer.model.len();
    println!(
        "{train} views ({test} more held out) of {}x{} pixels",
        k.width, k.height
    );
    println!("starting from {gaussians} Gaussians");

    let sink = |event: Event| match event {
        Event::Log { message, .. } => println!("{message}"),
        Event::Evaluation { step, metrics, .. } => {
            let values: Vec<String> = metrics
                .iter()
                .map(|m| match m.value.fract() {
                    0.0 => format!("{} {}", m.name, m.value),
                    _ => format!("{} {:.4}", m.name, m.value),
                })
                .collect();
            println!(
                "held-out views after {step} iterations: {}",
                values.join(", ")
            );
        }
        Event::Warning(message) => eprintln!("warning: {message}"),
        _ => {}
    };
    let summary = trainer.train(&Run {
        sink: &sink,
        ..Run::in_memory()
    })?;

    let out = Path::new(out);
    trainer.save_ply(out)?;
    println!(
        "{} iterations in {:.1} s; wrote {} Gaussians to {}",
        summary.run.step,
        summary.run.seconds,
        summary.gaussians,
        out.display()
    );
    Ok(())
}
