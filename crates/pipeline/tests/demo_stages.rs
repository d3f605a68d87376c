//! The demo's stages at a toy size (32 x 32 lego views, a few dozen iterations): a rerun skips
//! every finished stage, stylize and eval included, without rewriting any output; a changed
//! style image reruns stylize and eval only; a bad style image fails before any stage runs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use dsgs_testkit::{scratch_dir, shared_dir};
use pipeline::demo::{run, DemoSettings};
use pipeline::run::RunReport;
use pipeline::weights::Pair;
use pipeline::Control;
use train::Variant;

fn toy(out: &Path, styles: Vec<PathBuf>) -> DemoSettings {
    DemoSettings {
        shared: shared_dir(),
        out_dir: out.to_path_buf(),
        networks: Pair::Relu41,
        weights: None,
        decoder: None,
        variant: Variant::Standard,
        downscale: 25.0,
        geometry_iterations: 30,
        align_warmup: 10,
        feature_iterations: 13,
        styles,
        frames: 4,
    }
}

/// Every file under `dir` with its modification time.
fn files(dir: &Path) -> BTreeMap<PathBuf, SystemTime> {
    let mut out = BTreeMap::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                todo.push(p);
            } else {
                let t = std::fs::metadata(&p).unwrap().modified().unwrap();
                out.insert(p, t);
            }
        }
    }
    out
}

/// The stages that ran (`Some` seconds), by name.
fn ran(r: &RunReport) -> Vec<&'static str> {
    r.seconds
        .iter()
        .filter(|(_, t)| t.is_some())
        .map(|(s, _)| *s)
        .collect()
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn a_rerun_skips_every_finished_stage_and_a_changed_style_reruns_stylize() {
    let dir = scratch_dir("demo-stages", "rerun");
    let out = dir.join("out");
    let style = dir.join("style.jpg");
    let shared = shared_dir();
    std::fs::copy(shared.join("data/styles/mondrian.jpg"), &style).unwrap();
    let settings = toy(&out, vec![style.clone()]);

    let first = run(&settings, &Control::quiet()).unwrap();
    assert_eq!(
        ran(&first),
        ["weights", "geometry", "features", "stylize", "eval"]
    );
    let sheet = first.stylized.contact_sheet.clone().unwrap();
    assert!(sheet.is_file());
    let written = files(&out);

    // Nothing changed: every stage is skipped, the outputs are reported as before and no file
    // is written again.
    let second = run(&settings, &Control::quiet()).unwrap();
    assert!(ran(&second).is_empty(), "{:?}", second.seconds);
    assert_eq!(second.seconds.len(), first.seconds.len());
    assert_eq!(second.stylized.outputs, first.stylized.outputs);
    assert_eq!(second.stylized.gifs, first.stylized.gifs);
    assert_eq!(second.stylized.contact_sheet, Some(sheet));
    assert_eq!(second.eval.outputs.len(), first.eval.outputs.len());
    assert_eq!(
        pipeline::eval::table(&second.eval),
        pipeline::eval::table(&first.eval)
    );
    assert_eq!(files(&out), written, "a skipped stage rewrote its outputs");

    // Another image at the same path: stylize and eval run again, the training stages do not.
    std::fs::copy(shared.join("data/styles/en_campo_gris.jpg"), &style).unwrap();
    let third = run(&settings, &Control::quiet()).unwrap();
    assert_eq!(ran(&third), ["stylize", "eval"]);
    let frame = &third.stylized.outputs[0].1[0];
    assert_ne!(
        files(&out)[frame],
        written[frame],
        "the frames were not redone"
    );

    // A missing output reruns its stage.
    std::fs::remove_file(third.stylized.gifs[0].clone()).unwrap();
    let fourth = run(&settings, &Control::quiet()).unwrap();
    assert_eq!(ran(&fourth), ["stylize"]);
    assert!(fourth.stylized.gifs[0].is_file());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_undecodable_style_image_fails_before_any_stage() {
    let dir = scratch_dir("demo-stages", "bad-style");
    let out = dir.join("out");
    let bad = dir.join("unreadable.txt");
    std::fs::write(&bad, b"this is not an image\n").unwrap();
    let good = shared_dir().join("data/styles/mondrian.jpg");
    let err = run(&toy(&out, vec![good, bad.clone()]), &Control::quiet())
        .unwrap_err()
        .to_string();
    assert!(err.contains("style image"), "{err}");
    assert!(err.contains(&bad.display().to_string()), "{err}");
    assert!(!out.exists(), "a stage ran before the inputs were checked");
    std::fs::remove_dir_all(&dir).ok();
}
