//! `dsgs render`: colour, depth and alpha images of the trained 3DGS scene along an orbit, and
//! bad input.

mod common;

use common::{dsgs, fails, ok, scratch, size_of};
use dsgs_testkit::shared_path;

#[test]
fn orbit_renders_have_the_requested_size() {
    let dir = scratch("render-orbit");
    let ply = shared_path("data/gaussians/trained_9080.ply");
    for what in ["color", "depth", "alpha"] {
        let out = dir.join(what);
        ok(dsgs()
            .args(["render", "--scene"])
            .arg(&ply)
            .args([
                "--cameras",
                "orbit",
                "--frames",
                "3",
                "--width",
                "64",
                "--height",
                "48",
            ])
            .args(["--what", what, "-o"])
            .arg(&out));
        let mut files: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        files.sort();
        assert_eq!(
            files,
            ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
        );
        for f in &files {
            assert_eq!(size_of(&out.join(f)), (64, 48), "{what}/{f}");
        }
        // Something of the scene is visible: the frame is not uniformly black.
        let img = image::open(out.join("frame_0000.png")).unwrap().to_rgb8();
        assert!(
            img.pixels().any(|p| p.0 != [0, 0, 0]),
            "{what} frame is empty"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn feature_pca_of_a_bundle_is_consistent_across_views() {
    let dir = scratch("render-pca");
    let bundle = common::save_tiny_bundle(&dir);
    let out = dir.join("pca");
    ok(dsgs()
        .args(["render", "--scene"])
        .arg(&bundle)
        .args([
            "--cameras",
            "dataset",
            "--frames",
            "2",
            "--what",
            "features-pca",
            "-o",
        ])
        .arg(&out));
    assert_eq!(size_of(&out.join("frame_0001.png")), (64, 64));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_render_input_is_refused_with_a_message() {
    let ply = shared_path("data/gaussians/trained_9080.ply");
    let dir = scratch("render-bad");
    // A .ply carries no cameras.
    let err = fails(
        dsgs()
            .args(["render", "--scene"])
            .arg(&ply)
            .args(["--cameras", "dataset", "-o"])
            .arg(dir.join("x")),
    );
    assert!(
        err.contains("trained_9080.ply") && err.contains("no cameras"),
        "{err}"
    );
    // No features to project.
    let err = fails(
        dsgs()
            .args(["render", "--scene"])
            .arg(&ply)
            .args(["--what", "features-pca", "--frames", "1", "-o"])
            .arg(dir.join("y")),
    );
    assert!(err.contains("no per-Gaussian features"), "{err}");
    // A missing scene.
    let err = fails(
        dsgs()
            .args(["render", "--scene", "no/such/scene.ply", "-o"])
            .arg(dir.join("z")),
    );
    assert!(err.contains("no/such/scene.ply"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_huge_image_size_is_refused_quickly_naming_the_limit() {
    let ply = shared_path("data/gaussians/trained_9080.ply");
    let dir = scratch("render-huge");
    let limit = gaussian::camera::MAX_IMAGE_SIDE.to_string();
    // A width far beyond the limit (it once aborted on a 300 GB allocation), and a scale factor
    // that makes the orbit's cameras as large.
    for (flag, value) in [("--width", "100000000"), ("--scale", "100000")] {
        let out = dir.join(&flag[2..]);
        let started = std::time::Instant::now();
        let err = fails(
            dsgs()
                .args(["render", "--scene"])
                .arg(&ply)
                .args(["--frames", "1", flag, value, "-o"])
                .arg(&out),
        );
        assert!(err.contains(flag) && err.contains(&limit), "{err}");
        assert!(!out.exists(), "{} was written", out.display());
        // Refused before anything is rendered: well under the time of one render.
        assert!(
            started.elapsed().as_secs() < 60,
            "{flag} took {:?}",
            started.elapsed()
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}
