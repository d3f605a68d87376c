//! `dsgs fit-geometry` on a synthetic NeRF-synthetic dataset written by the test (8 RGBA views
//! of 32x32): configuration file plus overriding flags, outputs, exact resume, bad input.

mod common;

use std::path::Path;

#[cfg(unix)]
use common::stop_and_resume;
use common::{dsgs, fails, ok, scratch};

/// Writes `n` views on a circle of radius 3 around the origin (OpenGL camera-to-world poses,
/// world up +z) of a disc whose colour varies with the view, over transparency.
fn write_dataset(dir: &Path, n: usize) {
    std::fs::create_dir_all(dir.join("train")).unwrap();
    let mut frames = Vec::new();
    for i in 0..n {
        let a = i as f64 / n as f64 * std::f64::consts::TAU;
        let eye = [3.0 * a.cos(), 3.0 * a.sin(), 1.0];
        let norm = |v: [f64; 3]| {
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            v.map(|x| x / l)
        };
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let z = norm(eye); // backward: from the target to the eye
        let x = norm(cross([0.0, 0.0, 1.0], z));
        let y = cross(z, x);
        let m: Vec<Vec<f64>> = (0..4)
            .map(|r| {
                if r == 3 {
                    vec![0.0, 0.0, 0.0, 1.0]
                } else {
                    vec![x[r], y[r], z[r], eye[r]]
                }
            })
            .collect();
        frames.push(
            serde_json::json!({"file_path": format!("./train/r_{i}"), "transform_matrix": m}),
        );
        let img = image::RgbaImage::from_fn(32, 32, |px, py| {
            let (dx, dy) = (px as f32 - 15.5, py as f32 - 15.5);
            if dx * dx + dy * dy < 100.0 {
                image::Rgba([
                    (128.0 + 8.0 * dx) as u8,
                    (128.0 + 8.0 * dy) as u8,
                    (40 * (i % 6)) as u8,
                    255,
                ])
            } else {
                image::Rgba([0, 0, 0, 0])
            }
        });
        img.save(dir.join(format!("train/r_{i}.png"))).unwrap();
    }
    let json = serde_json::json!({"camera_angle_x": 0.69, "frames": frames});
    std::fs::write(dir.join("transforms_train.json"), json.to_string()).unwrap();
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn config_flags_outputs_and_exact_resume() {
    let dir = scratch("fit-geometry");
    let data = dir.join("data");
    write_dataset(&data, 8);
    let cfg = dir.join("small.toml");
    std::fs::write(
        &cfg,
        "iterations = 1000\nrandom_init_points = 800\nprogress = false\n[dataset]\neval = true\n",
    )
    .unwrap();
    // Uninterrupted: 20 iterations, checkpoint at 10.
    let full = dir.join("full");
    let out = ok(dsgs()
        .arg("fit-geometry")
        .arg(&data)
        .arg("--config")
        .arg(&cfg)
        .args([
            "--iterations",
            "20",
            "--checkpoint-iterations",
            "10",
            "--white",
            "-o",
        ])
        .arg(&full));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("7 training and 1 test views at 32x32"),
        "{text}"
    );
    assert!(text.contains("iteration 20: held-out PSNR"), "{text}");
    // The start line (on stderr) says what the run trains on before the first iteration.
    let started = String::from_utf8_lossy(&out.stderr);
    assert!(
        started.contains(
            "7 training and 1 held-out views at 32x32; 800 Gaussians at iteration 0 of 20"
        ),
        "{started}"
    );
    let saved = std::fs::read_to_string(full.join("config.toml")).unwrap();
    for key in [
        "iterations = 20",
        "random_init_points = 800",
        "background = [1.0, 1.0, 1.0]",
        "checkpoint_iterations = [10]",
    ] {
        assert!(saved.contains(key), "config.toml lacks `{key}`:\n{saved}");
    }
    let final_ply = std::fs::read(full.join("point_cloud.ply")).unwrap();
    assert_eq!(
        final_ply,
        std::fs::read(full.join("point_cloud/iteration_20/point_cloud.ply")).unwrap()
    );
    assert!(full.join("chkpnt_10.safetensors").is_file());
    // Resumed from iteration 10 into another directory with the saved configuration: the
    // same scene, byte for byte.
    let resumed = dir.join("resumed");
    let out = ok(dsgs()
        .arg("fit-geometry")
        .arg(&data)
        .arg("--config")
        .arg(full.join("config.toml"))
        .arg("--resume")
        .arg(full.join("chkpnt_10.safetensors"))
        .arg("-o")
        .arg(&resumed));
    let started = String::from_utf8_lossy(&out.stderr);
    assert!(started.contains("at iteration 10 of 20"), "{started}");
    assert_eq!(
        std::fs::read(resumed.join("point_cloud.ply")).unwrap(),
        final_ply
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_fit_geometry_input_is_refused_with_a_message() {
    let dir = scratch("fit-geometry-bad");
    let err = fails(
        dsgs()
            .args(["fit-geometry", "no/such/dataset", "-o"])
            .arg(dir.join("o")),
    );
    assert!(err.contains("no/such/dataset"), "{err}");
    let data = dir.join("data");
    write_dataset(&data, 2);
    let cfg = dir.join("typo.toml");
    std::fs::write(&cfg, "iteratons = 5\n").unwrap();
    let err = fails(
        dsgs()
            .arg("fit-geometry")
            .arg(&data)
            .arg("--config")
            .arg(&cfg)
            .arg("-o")
            .arg(dir.join("o")),
    );
    assert!(
        err.contains("typo.toml") && err.contains("`iteratons`"),
        "{err}"
    );
    let err = fails(
        dsgs()
            .arg("fit-geometry")
            .arg(&data)
            .args([
                "--resume",
                "no/such/chkpnt_7.safetensors",
                "--iterations",
                "9",
                "-o",
            ])
            .arg(dir.join("o")),
    );
    assert!(err.contains("chkpnt_7.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_stopped_run_writes_a_checkpoint_that_resumes() {
    use pipeline::fit_geometry::{run, FitSettings, GeometryOverrides};
    use std::sync::atomic::AtomicBool;

    let dir = scratch("fit-geometry-stop");
    let data = dir.join("data");
    write_dataset(&data, 4);
    let cfg = dir.join("small.toml");
    std::fs::write(&cfg, "random_init_points = 300\nprogress = false\n").unwrap();
    let out_dir = dir.join("out");
    let settings = FitSettings {
        dataset: data.clone(),
        out_dir: out_dir.clone(),
        config: Some(cfg),
        resume: None,
        overrides: GeometryOverrides {
            iterations: Some(12),
            ..Default::default()
        },
    };
    // The stop flag is already raised: the run ends before its first iteration.
    let stop = AtomicBool::new(true);
    let control = pipeline::Control {
        sink: &pipeline::Quiet,
        stop: Some(&stop),
    };
    let r = run(&settings, &control).unwrap();
    assert!(r.run.interrupted);
    assert_eq!(r.run.step, 0);
    let ck = out_dir.join("checkpoint.safetensors");
    assert_eq!(r.run.stop_checkpoint.as_deref(), Some(ck.as_path()));
    assert!(ck.is_file() && out_dir.join("point_cloud.ply").is_file());
    // Resuming without --config takes the run's saved config.toml (12 iterations).
    let out = ok(dsgs()
        .arg("fit-geometry")
        .arg(&data)
        .arg("--resume")
        .arg(&ck)
        .arg("-o")
        .arg(&out_dir));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("12 iterations in"), "{text}");
    assert!(out_dir
        .join("point_cloud/iteration_12/point_cloud.ply")
        .is_file());
    std::fs::remove_dir_all(&dir).ok();
}

/// A SIGTERM in the middle of a run: the run stops after its current iteration, writes a
/// checkpoint, says how to resume and exits with status 130; resuming from that checkpoint
/// gives the uninterrupted run's scene, byte for byte.
#[cfg(unix)]
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn sigterm_mid_run_writes_a_checkpoint_that_resumes_exactly() {
    let dir = scratch("fit-geometry-sigterm");
    let data = dir.join("data");
    write_dataset(&data, 4);
    let cfg = dir.join("small.toml");
    std::fs::write(&cfg, "random_init_points = 300\nprogress = false\n").unwrap();
    let (full, cut) = (dir.join("full"), dir.join("cut"));
    // Long enough that the signal lands well before the end.
    let fit = |out: &Path| {
        let mut c = dsgs();
        c.arg("fit-geometry")
            .arg(&data)
            .arg("--config")
            .arg(&cfg)
            .args(["--iterations", "1500", "-o"])
            .arg(out);
        c
    };
    stop_and_resume(1500, &full, &cut, fit, |_, _| {});
    assert_eq!(
        std::fs::read(full.join("point_cloud.ply")).unwrap(),
        std::fs::read(cut.join("point_cloud.ply")).unwrap(),
        "the resumed run differs from the uninterrupted one"
    );
    std::fs::remove_dir_all(&dir).ok();
}
