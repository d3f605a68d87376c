//! `--shard K/N` and `dsgs assemble` on the tiny bundle: a run split into shards, run in any
//! order, merges into the files of the one-process run byte for byte; a missing, unfinished or
//! changed shard is named and the merge refused until it is rerun.

mod common;

use std::path::{Path, PathBuf};

use common::{assert_same_files_except, dsgs, fails, ok, save_tiny_bundle, scratch};
use dsgs_testkit::shared_path;
use serde_json::Value;

fn styles() -> [PathBuf; 2] {
    [
        shared_path("data/styles/mondrian.jpg"),
        shared_path("data/styles/small-set/3.jpg"),
    ]
}

/// `dsgs stylize` of the tiny bundle with two styles along a 7-frame path, with a GIF.
fn stylize(bundle: &Path, out: &Path, shard: Option<&str>) -> std::process::Command {
    let [a, b] = styles();
    let mut cmd = dsgs();
    cmd.arg("stylize")
        .arg(bundle)
        .arg("--style")
        .arg(a)
        .arg("--style")
        .arg(b)
        .args([
            "--style-size",
            "96",
            "--cameras",
            "path",
            "--frames",
            "7",
            "--sheet-views",
            "3",
            "--gif",
            "--no-progress",
            "-o",
        ])
        .arg(out);
    if let Some(s) = shard {
        cmd.args(["--shard", s]);
    }
    cmd
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn stylize_in_three_shards_assembles_to_the_one_process_output() {
    let dir = scratch("shard-stylize");
    let bundle = save_tiny_bundle(&dir);
    let whole = dir.join("whole");
    ok(&mut stylize(&bundle, &whole, None));

    let out = dir.join("sharded");
    // Shards in any order; each writes only its block of frames and its manifest.
    ok(&mut stylize(&bundle, &out, Some("3/3")));
    ok(&mut stylize(&bundle, &out, Some("1/3")));
    assert!(out.join("mondrian/frame_0000.png").is_file());
    assert!(!out.join("mondrian/frame_0002.png").exists());
    assert!(!out.join("contact_sheet.png").exists() && !out.join("mondrian.gif").exists());
    let err = fails(dsgs().arg("assemble").arg(&out));
    assert!(err.contains("shard 2 of 3 is missing"), "{err}");
    assert!(err.contains("--shard K/3"), "{err}");

    // Shard 2 dies after writing a frame: no manifest, so it is still missing.
    ok(&mut stylize(&bundle, &out, Some("2/3")));
    let manifest = out.join("shards/stylize-2-of-3.json");
    assert!(manifest.is_file());
    std::fs::remove_file(&manifest).unwrap();
    let err = fails(dsgs().arg("assemble").arg(&out));
    assert!(err.contains("shard 2 of 3 is missing"), "{err}");

    // A finished shard's frame changed afterwards: named, refused.
    ok(&mut stylize(&bundle, &out, Some("2/3")));
    let frame = out.join("3/frame_0003.png");
    let good = std::fs::read(&frame).unwrap();
    std::fs::write(&frame, b"not the frame").unwrap();
    let err = fails(dsgs().arg("assemble").arg(&out));
    assert!(
        err.contains("shard 2/3") && err.contains("frame_0003.png"),
        "{err}"
    );
    std::fs::write(&frame, &good).unwrap();

    // Assembled from another working directory: the recorded one is used.
    let out = ok(dsgs().arg("assemble").arg(&out).current_dir(&dir));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("contact_sheet.png"), "{text}");
    assert_same_files_except(&whole, &dir.join("sharded"), &["shards"]);

    // A shard of other settings is refused.
    let mut other = stylize(&bundle, &dir.join("sharded"), Some("1/3"));
    other.args(["--alpha", "0.5"]);
    ok(&mut other);
    let err = fails(dsgs().arg("assemble").arg(dir.join("sharded")));
    assert!(
        err.contains("shard 1/3") && err.contains("fingerprint"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn eval_in_shards_assembles_to_the_one_process_report() {
    let dir = scratch("shard-eval");
    let bundle = save_tiny_bundle(&dir);
    let eval = |report: &Path, shard: Option<&str>| {
        let mut cmd = dsgs();
        cmd.arg("eval")
            .arg(&bundle)
            .arg("--style")
            .arg(shared_path("data/styles/mondrian.jpg"))
            .args([
                "--style-size",
                "64",
                "--cameras",
                "path",
                "--frames",
                "12",
                "--no-progress",
                "-o",
            ])
            .arg(report);
        if let Some(s) = shard {
            cmd.args(["--shard", s]);
        }
        cmd
    };
    let whole = dir.join("whole.json");
    ok(&mut eval(&whole, None));
    // Four shards of 3 views: the long-range pairs (i, i + 7) cross up to three shards.
    let sharded = dir.join("sharded.json");
    for k in [4, 2, 1] {
        ok(&mut eval(&sharded, Some(&format!("{k}/4"))));
    }
    let err = fails(dsgs().arg("assemble").arg(&sharded));
    assert!(err.contains("shard 3 of 4 is missing"), "{err}");
    ok(&mut eval(&sharded, Some("3/4")));
    ok(dsgs().arg("assemble").arg(&sharded));
    let read = |p: &Path| -> Value {
        let mut v: Value = serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap();
        // Measured wall times differ between any two runs.
        v.as_object_mut().unwrap().remove("seconds_per_view");
        v
    };
    let (a, b) = (read(&whole), read(&sharded));
    assert_eq!(a, b);
    // The comparison is not vacuous: both have pairs at both ranges.
    assert_eq!(a["outputs"][1]["long_range"]["pairs"], 5);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn bake_targets_in_shards_fit_to_the_one_process_ply() {
    let dir = scratch("shard-bake");
    let bundle = save_tiny_bundle(&dir);
    let config = dir.join("bake.toml");
    std::fs::write(
        &config,
        "target_views = 4\ninterpolated_per_pair = 1\nheld_out = 2\n",
    )
    .unwrap();
    let bake = |ply: &Path, shard: Option<&str>| {
        let mut cmd = dsgs();
        cmd.arg("bake")
            .arg(&bundle)
            .arg("--style")
            .arg(shared_path("data/styles/mondrian.jpg"))
            .arg("--config")
            .arg(&config)
            .args([
                "--style-size",
                "64",
                "--sh-degree",
                "1",
                "--iterations",
                "6",
                "--no-progress",
                "-o",
            ])
            .arg(ply);
        if let Some(s) = shard {
            cmd.args(["--shard", s]);
        }
        cmd
    };
    let whole = dir.join("whole/baked.ply");
    ok(&mut bake(&whole, None));
    let sharded = dir.join("sharded/baked.ply");
    // Six targets (two held out, four fitted) in four shards: the held-out and training views
    // share shard 2.
    for k in [2, 4, 1] {
        let out = ok(&mut bake(&sharded, Some(&format!("{k}/4"))));
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(text.contains("dsgs assemble"), "{text}");
    }
    assert!(!sharded.exists());
    let err = fails(dsgs().arg("assemble").arg(&sharded));
    assert!(err.contains("shard 3 of 4 is missing"), "{err}");
    ok(&mut bake(&sharded, Some("3/4")));
    let text = ok(dsgs().arg("assemble").arg(&sharded)).stdout;
    let text = String::from_utf8_lossy(&text);
    assert!(
        text.contains("4 training and 2 held-out target views"),
        "{text}"
    );
    assert_eq!(
        std::fs::read(&whole).unwrap(),
        std::fs::read(&sharded).unwrap()
    );
    std::fs::remove_dir_all(&dir).ok();
}
