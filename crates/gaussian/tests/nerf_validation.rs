//! Validation of NeRF-synthetic `transforms_*.json` files: image sizes `w`, `h` that round to
//! zero pixels and intrinsics that are not finite are refused, and so is every `file_path`
//! that leaves the scene folder (`..` above it, or an absolute path), while the usual
//! `./train/r_0` form keeps loading.
//!
//! Each scene is written to a scratch folder `root/scene`; the files that a bad `file_path`
//! would reach (`root/outside/r_0.png`, `root/r_0.png`) exist too, so a loader without the
//! checks would load them rather than fail for a missing file.

use std::path::{Path, PathBuf};

use dsgs_testkit::scratch_dir;
use gaussian::dataset::nerf::parse_transforms;
use gaussian::dataset::{Dataset, DatasetError, LoadOptions};
use serde_json::{json, Value};

const W: u32 = 8;
const H: u32 = 6;

fn identity() -> Value {
    json!([
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 4.0],
        [0.0, 0.0, 0.0, 1.0]
    ])
}

fn write_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbaImage::from_pixel(W, H, image::Rgba([255, 0, 0, 255]))
        .save(path)
        .unwrap();
}

/// A scratch `root` holding the scene folder `root/scene` (with `train/r_0.png`,
/// `train/r_1.png` and `transforms_train.json` made from `top` plus frames with `file_paths`)
/// and the decoys `root/outside/r_0.png` and `root/r_0.png`. Returns `(root, scene)`.
fn write_scene(name: &str, top: Value, file_paths: &[&str]) -> (PathBuf, PathBuf) {
    let root = scratch_dir("nerf-validation", name);
    let scene = root.join("scene");
    write_png(&scene.join("train/r_0.png"));
    write_png(&scene.join("train/r_1.png"));
    write_png(&root.join("outside/r_0.png"));
    write_png(&root.join("r_0.png"));
    let mut t = top;
    t["frames"] = file_paths
        .iter()
        .map(|p| json!({ "file_path": p, "transform_matrix": identity() }))
        .collect();
    std::fs::write(
        scene.join("transforms_train.json"),
        serde_json::to_string_pretty(&t).unwrap(),
    )
    .unwrap();
    (root, scene)
}

fn angle() -> Value {
    json!({ "camera_angle_x": 0.7 })
}

/// Loads the scene and returns the error message, failing the test if it loads.
fn load_error(scene: &Path) -> String {
    match Dataset::load(scene, &LoadOptions::default()) {
        Ok(d) => panic!(
            "loaded although it should not: paths {:?}, intrinsics {:?}",
            d.image_paths, d.cameras[0].intrinsics
        ),
        Err(e) => {
            assert!(matches!(e, DatasetError::Malformed { .. }), "{e:?}");
            println!("{e}");
            e.to_string()
        }
    }
}

#[test]
fn valid_scene_loads() {
    let (root, scene) = write_scene(
        "valid",
        json!({ "camera_angle_x": 0.7, "w": 8, "h": 6 }),
        &["./train/r_0", "./train/r_1"],
    );
    let d = Dataset::load(&scene, &LoadOptions::default()).unwrap();
    assert_eq!(d.names, ["r_0", "r_1"]);
    assert_eq!(d.image_paths[0], scene.join("train/r_0.png"));
    let k = d.cameras[0].intrinsics;
    assert_eq!((k.width, k.height, k.cx, k.cy), (W, H, 4.0, 3.0));
    assert!((k.fx - 4.0 / 0.35f64.tan()).abs() < 1e-12 && k.fy == k.fx);
    assert_eq!(d.load_image(1).unwrap().pixel(0, 0), [1.0, 0.0, 0.0]);
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn paths_that_stay_inside_the_scene_folder_load() {
    let (root, scene) = write_scene(
        "inside",
        json!({ "fl_x": 10.0, "fl_y": 12.0, "cx": 4.5, "cy": 2.5, "w": 16.2, "h": 11.8 }),
        &["train/r_0.png", "./train/../train/r_1", "train/./r_0"],
    );
    let d = Dataset::load(&scene, &LoadOptions::default()).unwrap();
    assert_eq!(d.names, ["r_0", "r_1", "r_0"]);
    for p in &d.image_paths {
        assert!(p.starts_with(&scene) && p.is_file(), "{}", p.display());
    }
    // `w`, `h` round to 16 x 12; the 8 x 6 files halve the intrinsics.
    let k = d.cameras[1].intrinsics;
    assert_eq!(
        (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        (5.0, 6.0, 2.25, 1.25, W, H)
    );
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn w_that_rounds_to_zero_is_refused() {
    let (root, scene) = write_scene(
        "w_zero",
        json!({ "camera_angle_x": 0.7, "w": 0.3, "h": 6 }),
        &["./train/r_0"],
    );
    let err = load_error(&scene);
    assert!(
        err.contains("transforms_train.json")
            && err.contains("`w` = 0.3")
            && err.contains("0 pixels"),
        "{err}"
    );
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn h_that_rounds_to_zero_is_refused() {
    let (root, scene) = write_scene(
        "h_zero",
        json!({ "fl_x": 10.0, "fl_y": 10.0, "w": 8, "h": 0.4 }),
        &["./train/r_0"],
    );
    let err = load_error(&scene);
    assert!(
        err.contains("transforms_train.json")
            && err.contains("`h` = 0.4")
            && err.contains("0 pixels"),
        "{err}"
    );
    // The parser alone refuses it too.
    let text = std::fs::read_to_string(scene.join("transforms_train.json")).unwrap();
    assert!(parse_transforms(&text, Path::new("t.json")).is_err());
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn focal_length_that_overflows_is_refused() {
    // Half the smallest subnormal angle is 0, so `fx = (w / 2) / tan(0)` would be infinite.
    let (root, scene) = write_scene(
        "fx_inf",
        json!({ "camera_angle_x": 5e-324 }),
        &["./train/r_0"],
    );
    let err = load_error(&scene);
    assert!(
        err.contains("transforms_train.json") && err.contains("frame 0") && err.contains("fx"),
        "{err}"
    );
    std::fs::remove_dir_all(root).unwrap();
}

/// Checks that a scene whose frame 1 has `bad` as `file_path` is refused with `what`.
fn assert_path_refused(name: &str, bad: &str, what: &str) {
    let (root, scene) = write_scene(name, angle(), &["./train/r_0", bad]);
    let err = load_error(&scene);
    assert!(
        err.contains("transforms_train.json")
            && err.contains("frame 1")
            && err.contains(&format!("file_path {bad:?}"))
            && err.contains(what),
        "{err}"
    );
    let text = std::fs::read_to_string(scene.join("transforms_train.json")).unwrap();
    assert!(parse_transforms(&text, Path::new("t.json")).is_err());
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn file_path_with_leading_parent_dir_is_refused() {
    assert_path_refused("parent", "../outside/r_0", "leaves the scene folder");
}

#[test]
fn file_path_climbing_out_through_a_subfolder_is_refused() {
    assert_path_refused("climb", "./train/../../r_0", "leaves the scene folder");
}

#[test]
fn absolute_file_path_is_refused() {
    let name = "absolute";
    // The decoy that the absolute path names exists (written by `write_scene`).
    let abs = scratch_dir("nerf-validation", name).join("outside/r_0");
    assert!(abs.is_absolute());
    assert_path_refused(name, abs.to_str().unwrap(), "is absolute");
}
