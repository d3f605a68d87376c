//! `dsgs run` on a capture at a toy size (32 x 32 lego views, short schedules): the bundle, the
//! frames along the smooth tour, the contact sheet and the report are written; a run stopped by
//! SIGTERM during the geometry stage continues from its checkpoint when given the same command;
//! a finished run reruns without redoing anything; the time estimate is printed before the
//! stages and beside their times; a missing capture is named.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{dsgs, every_stage_skipped, fails, ok, scratch};
use dsgs_testkit::{shared_dir, shared_path};

fn size_of(p: &Path) -> (u32, u32) {
    image::image_dimensions(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// `dsgs run` of lego at 32 x 32 with two paintings, `geometry` iterations of geometry.
fn run(out: &Path, geometry: u64) -> Command {
    let mut c = dsgs();
    c.arg("run")
        .arg(shared_path("data/scenes/lego"))
        .arg("--style")
        .arg(shared_path("data/styles/mondrian.jpg"))
        .arg("--style")
        .arg(shared_path("data/styles/sketch.png"))
        .arg("--shared")
        .arg(shared_dir())
        .args(["--quality", "draft", "--downscale", "25"])
        .args(["--geometry-iterations", &geometry.to_string()])
        .args(["--align-warmup", "10", "--feature-iterations", "13"])
        .args(["--frames", "4", "--no-progress", "-o"])
        .arg(out);
    c
}

fn modified(p: &Path) -> std::time::SystemTime {
    std::fs::metadata(p)
        .and_then(|m| m.modified())
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
#[cfg(unix)]
fn a_toy_run_writes_everything_and_continues_after_a_stop() {
    let dir = scratch("run");
    let out = dir.join("out");
    let geometry = 600;

    // Stopped by SIGTERM once the geometry stage has kept its half-way checkpoint.
    let mut child = run(&out, geometry)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the dsgs binary runs");
    let half = out.join(format!("geometry/chkpnt_{}.safetensors", geometry / 2));
    let started = Instant::now();
    while !half.is_file() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before its half-way checkpoint"
        );
        assert!(
            started.elapsed() < Duration::from_secs(1200),
            "no checkpoint"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let output = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{log}");
    assert!(log.contains("run the same command again"), "{log}");
    let kept = modified(&half);

    // The same command continues: the half-way checkpoint is not written again.
    let first = ok(&mut run(&out, geometry));
    let text = String::from_utf8_lossy(&first.stdout).into_owned();
    assert_eq!(modified(&half), kept, "the geometry stage started over");
    assert!(
        text.contains("1/25.000") && text.contains("4 frames along path"),
        "{text}"
    );
    // The estimate is logged before the stages and set beside each stage's time; the geometry
    // stage resumes from its checkpoint (half-way or a little after), so its estimate counts
    // the iterations left.
    let log = String::from_utf8_lossy(&first.stderr);
    assert!(log.contains("estimate on this machine"), "{log}");
    let left: u64 = log
        .lines()
        .find_map(|l| {
            l.split_once("geometry: ~")?
                .1
                .split_once(" (")?
                .1
                .split_once(' ')
        })
        .and_then(|(n, rest)| {
            rest.starts_with("iterations from")
                .then(|| n.parse().ok())?
        })
        .unwrap_or_else(|| panic!("no geometry estimate: {log}"));
    assert!(
        left > 0 && left <= geometry / 2,
        "{left} iterations left: {log}"
    );
    for stage in ["geometry", "features", "stylize", "eval"] {
        let timed = |l: &&str| {
            l.trim_start().starts_with(&format!("{stage}: ")) && l.contains("(estimated ")
        };
        assert!(
            text.lines().any(|l| timed(&l)),
            "no estimate of {stage}: {text}"
        );
    }
    let bundle = out.join("features/bundle");
    assert!(bundle.join("bundle.json").is_file());
    assert!(
        text.contains(&format!("dsgs view {}", bundle.display())),
        "{text}"
    );
    for name in ["mondrian", "sketch"] {
        for i in 0..4 {
            let frame = out.join(format!("stylized/{name}/frame_{i:04}.png"));
            assert_eq!(size_of(&frame), (32, 32));
        }
        assert!(out.join(format!("stylized/{name}.gif")).is_file());
    }
    // The colour row and one row per painting; the painting column and the four views.
    assert_eq!(
        size_of(&out.join("stylized/contact_sheet.png")),
        (5 * 32, 3 * 32)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    let outputs = report["outputs"].as_array().unwrap();
    // The colour render, then per painting its per-frame 2D baseline and dsgs.
    let names: Vec<&str> = outputs
        .iter()
        .map(|o| o["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        ["colour", "2d:mondrian", "mondrian", "2d:sketch", "sketch"],
        "{report}"
    );
    // Their frames, and the comparison sheet of four views: a painting column and a row each.
    assert!(out.join("eval/2d_sketch/frame_0003.png").is_file());
    assert_eq!(size_of(&out.join("eval/comparison.png")), (5 * 32, 5 * 32));
    assert!(
        text.contains("comparison.png (colour | 2D per-frame | dsgs)"),
        "{text}"
    );
    for o in &outputs[1..] {
        for key in ["style_loss", "texture_distance", "content_loss"] {
            let x = o[key].as_f64().unwrap_or(f64::NAN);
            assert!(x.is_finite() && x > 0.0, "{key}: {o}");
        }
    }

    // A rerun finds every stage done, and has nothing to estimate.
    let again = ok(&mut run(&out, geometry));
    every_stage_skipped(&again);
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("every stage's result is already there")
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_missing_capture_is_named() {
    let dir = scratch("run-missing");
    let err = fails(
        dsgs()
            .arg("run")
            .arg(dir.join("no-such-capture"))
            .arg("--style")
            .arg(shared_path("data/styles/mondrian.jpg"))
            .arg("-o")
            .arg(dir.join("out")),
    );
    assert!(err.contains("no-such-capture"), "{err}");
    assert!(
        !dir.join("out").exists(),
        "nothing is written for a missing capture"
    );
    std::fs::remove_dir_all(&dir).ok();
}
