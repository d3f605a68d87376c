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
            .arg("render")
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
            .arg("render")
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
            .arg("render")
            .arg(&ply)
            .args(["--what", "features-pca", "--frames", "1", "-o"])
            .arg(dir.join("y")),
    );
    assert!(err.contains("no per-Gaussian features"), "{err}");
    // A missing scene.
    let err = fails(
        dsgs()
            .args(["render", "no/such/scene.ply", "-o"])
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
                .arg("render")
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

/// The frames of `dir`, decoded, in name order.
fn frames(dir: &std::path::Path) -> Vec<image::RgbImage> {
    let mut names: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    names
        .iter()
        .map(|p| image::open(p).unwrap().to_rgb8())
        .collect()
}

#[test]
fn the_scene_is_the_first_argument_and_spellings_and_backgrounds_are_accepted() {
    let ply = shared_path("data/gaussians/trained_9080.ply");
    let dir = scratch("render-spellings");
    let render = |name: &str, extra: &[&str]| {
        let out = dir.join(name);
        ok(dsgs()
            .arg("render")
            .arg(&ply)
            .args(["--frames", "2"])
            .args(
                if extra.contains(&"--scale") || extra.contains(&"--downscale") {
                    &[][..]
                } else {
                    &["--width", "48"][..]
                },
            )
            .args(extra)
            .arg("-o")
            .arg(&out));
        frames(&out)
    };
    let colour = render("colour", &["--what", "colour"]);
    // Both spellings draw the same images; so does the flag the scene was given by before.
    assert_eq!(render("color", &["--what", "color"]), colour);
    let out = dir.join("flag");
    ok(dsgs()
        .args(["render", "--scene"])
        .arg(&ply)
        .args(["--frames", "2", "--width", "48", "-o"])
        .arg(&out));
    assert_eq!(frames(&out), colour);
    assert_eq!(
        render("grey", &["--what", "depth", "--depth-style", "grey"]),
        render("gray", &["--what", "depth", "--depth-style", "gray"])
    );
    // A .ply is drawn over black; --background white changes exactly the pixels the scene does
    // not cover completely, towards white.
    let white = render("white", &["--background", "white"]);
    let corner = |f: &image::RgbImage| f.get_pixel(0, 0).0;
    assert_eq!(corner(&colour[0]), [0, 0, 0]);
    assert_eq!(corner(&white[0]), [255, 255, 255]);
    for (b, w) in colour[0].pixels().zip(white[0].pixels()) {
        assert!(b.0.iter().zip(w.0).all(|(b, w)| w >= *b), "{b:?} {w:?}");
    }
    // --downscale is the inverse of --scale.
    let half = render("half", &["--scale", "0.5"]);
    assert_eq!(render("down", &["--downscale", "2"]), half);
    // Without cameras an orbit is 256 pixels square (--width alone keeps it square).
    assert_eq!(half[0].dimensions(), (128, 128));
    assert_eq!(colour[0].dimensions(), (48, 48));
    // A second scene is not taken for a repeated flag: no tip about repeating --style.
    let err = fails(
        dsgs()
            .arg("render")
            .arg(&ply)
            .arg(&ply)
            .arg("-o")
            .arg(dir.join("two")),
    );
    assert!(
        err.contains("unexpected argument") && !err.contains("--style"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
