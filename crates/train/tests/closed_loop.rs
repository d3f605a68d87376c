//! Closed loop: ground-truth views of a known scene are rendered with the rasterizer, and the
//! trainer fits a scene to them from random initial points. Success is measured on held-out
//! views (every 8th camera), which the trainer never sees.
//!
//! The schedule is the 3DGS one compressed twentyfold (1,500 iterations instead of 30,000:
//! densification every 50 iterations from 50 to 1,000, opacity reset every 500, position
//! learning rate decayed over 1,500 steps); every other setting is the default. Run with
//! `--release`.

mod common;

use common::{render_views, sphere_cameras, synthetic_scene};
use train::density::DensifyConfig;
use train::geometry::{GeometryConfig, GeometryTrainer, View};
use train::init::{gaussians_from_points, random_points_in_box};
use train::model::LearningRates;
use train::Run;

/// Compresses the 3DGS schedule into `iterations` steps.
pub fn compressed_config(iterations: u64) -> GeometryConfig {
    let f = iterations as f64 / 30_000.0;
    let s = |v: u64| ((v as f64) * f).round() as u64;
    GeometryConfig {
        iterations,
        sh_degree: 0,
        learning_rates: LearningRates {
            position_lr_max_steps: iterations,
            ..LearningRates::default()
        },
        densify: DensifyConfig {
            densification_interval: s(1000).max(1),
            densify_from_iter: s(1000),
            densify_until_iter: s(20_000),
            opacity_reset_interval: s(10_000),
            ..DensifyConfig::default()
        },
        test_iterations: vec![iterations],
        save_iterations: vec![],
        ..GeometryConfig::default()
    }
}

fn split(views: Vec<View>) -> (Vec<View>, Vec<View>) {
    let (test, train): (Vec<_>, Vec<_>) =
        views.into_iter().enumerate().partition(|(i, _)| i % 8 == 0);
    (
        train.into_iter().map(|(_, v)| v).collect(),
        test.into_iter().map(|(_, v)| v).collect(),
    )
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn fits_a_known_scene_to_30_db_on_held_out_views() {
    let truth = synthetic_scene(300, 1);
    let cameras = sphere_cameras(40, 4.0, 64, 80.0);
    let (train_views, test_views) = split(render_views(&truth, &cameras, [0.0; 3]));
    assert_eq!(test_views.len(), 5);

    let config = compressed_config(1500);
    let cloud = random_points_in_box(2000, [-1.0; 3], [1.0; 3], 7);
    let initial = gaussians_from_points(&cloud, config.sh_degree).unwrap();
    let mut trainer = GeometryTrainer::new(config, initial, train_views, test_views).unwrap();
    let before = trainer.evaluate().unwrap().unwrap();
    let summary = trainer.train(&Run::in_memory()).unwrap();
    let after = summary.evaluations.last().copied().unwrap();
    println!(
        "closed loop: held-out PSNR {:.2} dB -> {:.2} dB, SSIM {:.4} -> {:.4}, {} Gaussians, {:.1} s",
        before.psnr, after.psnr, before.ssim, after.ssim, after.gaussians, summary.run.seconds
    );
    assert!(
        after.psnr >= 30.0,
        "held-out PSNR {:.2} dB < 30 dB",
        after.psnr
    );
}
