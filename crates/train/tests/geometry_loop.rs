//! The training loop: exact resume from a checkpoint, determinism, checkpoint validation,
//! configuration from TOML, and the `.ply` output.

mod common;

use common::{render_views, sphere_cameras, synthetic_scene};
use train::checkpoint::GeometryCheckpoint;
use train::density::DensifyConfig;
use train::geometry::{GeometryConfig, GeometryTrainer, View};
use train::init::{gaussians_from_points, random_points_in_box};
use train::model::LearningRates;
use train::Run;

/// A 20-iteration schedule that exercises every event: SH degree increments (every 5),
/// densification (every 4 from 4 to 18) and opacity resets (every 12).
fn busy_config() -> GeometryConfig {
    GeometryConfig {
        iterations: 20,
        seed: 3,
        sh_degree: 1,
        sh_degree_interval: 5,
        learning_rates: LearningRates {
            position_lr_max_steps: 20,
            ..LearningRates::default()
        },
        densify: DensifyConfig {
            densification_interval: 4,
            densify_from_iter: 3,
            densify_until_iter: 18,
            opacity_reset_interval: 12,
            // a low threshold so that clones and splits really happen
            densify_grad_threshold: 1e-6,
            ..DensifyConfig::default()
        },
        test_iterations: vec![],
        save_iterations: vec![],
        ..GeometryConfig::default()
    }
}

fn views() -> Vec<View> {
    let truth = synthetic_scene(60, 2);
    render_views(&truth, &sphere_cameras(6, 4.0, 24, 30.0), [0.0; 3])
}

fn fresh(config: GeometryConfig) -> GeometryTrainer {
    let cloud = random_points_in_box(300, [-1.0; 3], [1.0; 3], 1);
    let initial = gaussians_from_points(&cloud, config.sh_degree).unwrap();
    GeometryTrainer::new(config, initial, views(), vec![]).unwrap()
}

#[test]
fn resuming_from_a_checkpoint_reproduces_the_uninterrupted_run() {
    let mut straight = fresh(busy_config());
    let mut densified = 0;
    let mut resets = 0;
    for _ in 0..20 {
        let r = straight.train_step().unwrap();
        densified += r.densified.map_or(0, |d| d.cloned + d.split);
        resets += r.opacity_reset as usize;
    }
    assert!(densified > 0, "the schedule should clone or split");
    assert_eq!(resets, 1);
    assert_eq!(straight.model.active_sh_degree, 1);
    assert_ne!(straight.model.len(), 300);

    let dir = std::env::temp_dir().join(format!("dsgs-train-resume-{}", std::process::id()));
    let path = dir.join("chkpnt_10.safetensors");
    let mut first = fresh(busy_config());
    for _ in 0..10 {
        first.train_step().unwrap();
    }
    first.save_checkpoint(&path).unwrap();
    let ckpt = GeometryCheckpoint::load(&path).unwrap();
    assert_eq!(ckpt, first.checkpoint().unwrap(), "checkpoint round trip");
    // The trainer writes its state without copying it first; the file is the copy's.
    assert!(
        std::fs::read(&path).unwrap() == first.checkpoint().unwrap().to_bytes().unwrap(),
        "the file of save_checkpoint is that of checkpoint().to_bytes()"
    );
    drop(first);
    let mut resumed = GeometryTrainer::resume(busy_config(), ckpt, views(), vec![]).unwrap();
    assert_eq!(resumed.step, 10);
    let summary = resumed.train(&Run::in_memory()).unwrap();
    assert_eq!(summary.run.step, 20);

    assert_eq!(
        resumed.model, straight.model,
        "scene, Adam state and statistics"
    );
    assert_eq!(resumed.running_averages(), straight.running_averages());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn training_is_deterministic_and_lowers_the_loss() {
    let mut a = fresh(busy_config());
    let mut b = fresh(busy_config());
    let views = a.train_views.clone();
    let before = a.evaluate_views(&views).unwrap().unwrap();
    for _ in 0..20 {
        a.train_step().unwrap();
        b.train_step().unwrap();
    }
    assert_eq!(a.model, b.model);
    let after = a.evaluate_views(&views).unwrap().unwrap();
    assert!(
        after.l1 < before.l1 && after.psnr > before.psnr,
        "training views: L1 {} -> {}, PSNR {} -> {}",
        before.l1,
        after.l1,
        before.psnr,
        after.psnr
    );
}

#[test]
fn corrupt_or_foreign_checkpoints_are_clear_errors() {
    let dir = std::env::temp_dir().join(format!("dsgs-train-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let t = fresh(busy_config());
    let good = t.checkpoint().unwrap().to_bytes().unwrap();
    let p = dir.join("x.safetensors");
    for (name, bytes) in [
        ("empty", Vec::new()),
        ("garbage", b"not a checkpoint at all".to_vec()),
        ("truncated", good[..good.len() / 2].to_vec()),
    ] {
        std::fs::write(&p, &bytes).unwrap();
        let e = GeometryCheckpoint::load(&p).unwrap_err().to_string();
        assert!(e.contains("x.safetensors"), "{name}: {e}");
    }
    assert!(GeometryCheckpoint::load(&dir.join("missing.safetensors")).is_err());
    // a view index beyond the views given on resume
    let mut c = t.checkpoint().unwrap();
    c.view_stack = vec![99];
    assert!(GeometryTrainer::resume(busy_config(), c, views(), vec![]).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn config_reads_from_partial_toml_with_3dgs_defaults() {
    let c: GeometryConfig = toml::from_str(
        r#"
        iterations = 7000
        background = [1.0, 1.0, 1.0]
        [densify]
        densify_until_iter = 5000
        [learning_rates]
        opacity_lr = 0.025
        "#,
    )
    .unwrap();
    assert_eq!(c.iterations, 7000);
    assert_eq!(c.background, [1.0; 3]);
    assert_eq!(c.densify.densify_until_iter, 5000);
    assert_eq!(c.densify.densify_from_iter, 500);
    assert_eq!(c.densify.densify_grad_threshold, 0.0002);
    assert_eq!(c.learning_rates.opacity_lr, 0.025);
    assert_eq!(c.learning_rates.position_lr_init, 0.00016);
    assert_eq!(c.learning_rates.feature_lr, 0.0025);
    assert_eq!(c.learning_rates.scaling_lr, 0.005);
    assert_eq!(c.learning_rates.rotation_lr, 0.001);
    assert_eq!(c.adam.eps, 1e-15);
    assert_eq!(c.sh_degree, 3);
    assert_eq!(c.lambda_dssim, 0.2);
    let back: GeometryConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
    assert_eq!(back, c);
}

#[test]
fn final_ply_is_the_official_layout_and_reloads() {
    let mut t = fresh(busy_config());
    for _ in 0..6 {
        t.train_step().unwrap();
    }
    let dir = std::env::temp_dir().join(format!("dsgs-train-ply-{}", std::process::id()));
    let path = train::geometry::ply_path(&dir, 6);
    t.save_ply(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let header = String::from_utf8_lossy(&bytes[..bytes.len().min(2000)]).to_string();
    assert!(header.contains("format binary_little_endian 1.0"));
    // degree 1: x y z nx ny nz f_dc_0..2 f_rest_0..8 opacity scale_0..2 rot_0..3
    assert!(header.contains("property float f_rest_8"));
    assert!(!header.contains("property float f_rest_9"));
    let back = gaussian::ply::load_ply(&path).unwrap();
    assert_eq!(back.len(), t.model.len());
    assert_eq!(back.means, t.model.scene.means);
    assert_eq!(back.sh, t.model.scene.sh);
    assert_eq!(back.opacity_logits, t.model.scene.opacity_logits);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn training_is_bit_identical_for_any_thread_count() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let mut t = fresh(busy_config());
                for _ in 0..20 {
                    t.train_step().unwrap();
                }
                t.model
            })
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(3));
}
