//! `dsgs demo` at a toy size (32 x 32 lego views, a few dozen iterations): every stage runs
//! and writes its outputs, the evaluation is finite and in range, a rerun skips the finished
//! stages, missing inputs are named with where to get them, and an undecodable style image
//! fails before any stage runs.

mod common;

use common::{dsgs, every_stage_skipped, fails, ok, scratch};
use dsgs_testkit::shared_dir;

fn size_of(p: &std::path::Path) -> (u32, u32) {
    image::image_dimensions(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn a_toy_demo_runs_every_stage_and_a_rerun_skips_them() {
    let dir = scratch("demo");
    let out = dir.join("out");
    let run = || {
        let mut c = dsgs();
        c.arg("demo")
            .arg("--shared")
            .arg(shared_dir())
            .arg("-o")
            .arg(&out)
            .args(["--downscale", "25", "--geometry-iterations", "30"])
            .args(["--align-warmup", "10", "--feature-iterations", "13"])
            .args(["--frames", "4", "--no-progress"]);
        c
    };
    let first = ok(&mut run());
    let text = String::from_utf8_lossy(&first.stdout).into_owned();
    assert!(text.contains("geometry: held-out PSNR"), "{text}");
    assert!(!text.contains("skipped"), "{text}");
    // The summary names the bundle and how to open it.
    let bundle = out.join("features/bundle");
    assert!(
        text.contains(&format!("dsgs view {}", bundle.display())),
        "{text}"
    );

    // Four unseen styles, each with frames and a GIF; the sheet has the colour row and one
    // row per style, the style thumbnail column and the four views.
    for name in [
        "woman_with_hat_matisse",
        "the_resevoir_at_poitiers",
        "en_campo_gris",
        "mondrian",
    ] {
        assert_eq!(
            size_of(&out.join(format!("stylized/{name}/frame_0003.png"))),
            (32, 32)
        );
        assert!(out.join(format!("stylized/{name}.gif")).is_file());
    }
    assert_eq!(
        size_of(&out.join("stylized/contact_sheet.png")),
        (5 * 32, 5 * 32)
    );
    for f in [
        "geometry/config.toml",
        "features/config.toml",
        "features/bundle/bundle.json",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }

    // The report: nine outputs (colour, and per style of four its 2D per-frame baseline and
    // dsgs) with finite metrics in range, and the comparison sheet.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("eval.json")).unwrap()).unwrap();
    let outputs = report["outputs"].as_array().unwrap();
    assert_eq!(outputs.len(), 9);
    assert!(out.join("eval/comparison.png").is_file());
    let mut numbers = 0;
    fn walk(v: &serde_json::Value, n: &mut usize) {
        match v {
            serde_json::Value::Number(x) => {
                let x = x.as_f64().unwrap();
                assert!(x.is_finite() && x >= 0.0, "{x}");
                *n += 1;
            }
            serde_json::Value::Array(a) => a.iter().for_each(|v| walk(v, n)),
            serde_json::Value::Object(o) => o.values().for_each(|v| walk(v, n)),
            _ => {}
        }
    }
    walk(&report["outputs"], &mut numbers);
    assert!(numbers >= 9 * 4, "{report}");

    // A rerun finds every stage done and redoes none.
    every_stage_skipped(&ok(&mut run()));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn missing_shared_files_are_named_with_their_sources() {
    let dir = scratch("demo-missing");
    let err = fails(
        dsgs()
            .arg("demo")
            .arg("--shared")
            .arg(dir.join("nowhere"))
            .arg("-o")
            .arg(dir.join("out")),
    );
    assert!(err.contains("missing input files"), "{err}");
    assert!(err.contains("transforms_train.json"), "{err}");
    // The default networks: the relu4_1 encoder (its decoder is built in).
    assert!(err.contains("4SE.pth"), "{err}");
    assert!(err.contains("nerf_synthetic"), "{err}");
    assert!(
        !dir.join("out").exists(),
        "nothing is written before the inputs are checked"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_undecodable_style_image_fails_before_any_stage_runs() {
    let dir = scratch("demo-bad-style");
    let bad = dir.join("unreadable.txt");
    std::fs::write(&bad, b"not an image, just text\n").unwrap();
    let out = dir.join("out");
    let err = fails(
        dsgs()
            .arg("demo")
            .arg("--shared")
            .arg(shared_dir())
            .arg("-o")
            .arg(&out)
            .args(["--downscale", "25", "--geometry-iterations", "30"])
            .args(["--align-warmup", "10", "--feature-iterations", "13"])
            .args(["--frames", "4", "--no-progress", "--style"])
            .arg(&bad),
    );
    assert!(err.contains("style image"), "{err}");
    assert!(err.contains("unreadable.txt"), "{err}");
    assert!(
        !out.join("geometry").exists() && !out.join("weights.safetensors").exists(),
        "a stage ran before the style image was checked"
    );
    std::fs::remove_dir_all(&dir).ok();
}
