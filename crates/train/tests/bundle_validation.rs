//! The cameras of `bundle.json` are checked when a bundle is loaded: a small valid bundle (the
//! oracle's networks, a synthetic scene, four sphere cameras) is written with
//! `SceneBundle::save`, one camera of its `bundle.json` is broken (as `serde_json::Value`), and
//! both `BundleInfo::load` and `SceneBundle::load` must fail with a message naming the file, the
//! camera and the problem.

mod common;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use dsgs_testkit::scratch_dir;
use runtime::bundle::{BundleInfo, SceneBundle, INFO_FILE, MAX_IMAGE_SIDE};
use runtime::RuntimeError;
use serde_json::Value;

/// Feature channels of the test bundle.
const FEATURES: usize = 4;
/// The camera every bad case edits, and its name.
const BAD: usize = 2;
const BAD_NAME: &str = "view002";

/// The valid bundle, built once for all tests of this file.
fn valid_bundle() -> &'static SceneBundle {
    static BUNDLE: OnceLock<SceneBundle> = OnceLock::new();
    BUNDLE.get_or_init(|| common::small_bundle(FEATURES))
}

/// The valid bundle saved in a directory of its own, with `edit` applied to its `bundle.json`.
fn edited(name: &str, edit: impl FnOnce(&mut Value)) -> PathBuf {
    let dir = scratch_dir("bundleval", name);
    valid_bundle().save(&dir).unwrap();
    let path = dir.join(INFO_FILE);
    let mut json: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut json);
    std::fs::write(&path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
    dir
}

/// The edited camera's JSON object.
fn bad_camera(json: &mut Value) -> &mut Value {
    let cam = &mut json["cameras"][BAD];
    assert_eq!(cam["name"], BAD_NAME);
    cam
}

/// Entry `[r][c]` of the edited camera's `camera_from_world`, through `f`.
fn edit_matrix(json: &mut Value, f: impl Fn(usize, usize, f64) -> f64) {
    let m = &mut bad_camera(json)["camera_from_world"];
    for r in 0..4 {
        for c in 0..4 {
            let v = m[r][c].as_f64().unwrap();
            m[r][c] = serde_json::json!(f(r, c, v));
        }
    }
}

/// Asserts that the bundle in `dir` is refused by `BundleInfo::load` and `SceneBundle::load`,
/// with a message naming `bundle.json`, the edited camera and every part of `problem`.
fn assert_rejected(dir: &Path, problem: &[&str]) {
    let file = dir.join(INFO_FILE).display().to_string();
    let camera = format!("camera {BAD} ({BAD_NAME})");
    let check = |result: Result<(), RuntimeError>| {
        let msg = result.expect_err("the bad camera was accepted").to_string();
        assert!(msg.contains(&file), "does not name {file}: {msg}");
        assert!(msg.contains(&camera), "does not name {camera}: {msg}");
        for p in problem {
            assert!(msg.contains(p), "does not say `{p}`: {msg}");
        }
    };
    check(BundleInfo::load(dir).map(|_| ()));
    check(SceneBundle::load(dir).map(|_| ()));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_valid_bundle_loads() {
    let dir = edited("unchanged", |_| {});
    let info = BundleInfo::load(&dir).unwrap();
    assert_eq!(info.cameras.len(), 4);
    for (i, rec) in info.cameras.iter().enumerate() {
        assert_eq!(rec.check(), Ok(()), "camera {i}");
    }
    let bundle = SceneBundle::load(&dir).unwrap();
    assert_eq!(bundle.cameras(), info.cameras());
    // serde_json may read a float back one ulp off, so the matrices are compared loosely.
    for (read, written) in info.cameras.iter().zip(&valid_bundle().info.cameras) {
        assert_eq!(read.name, written.name);
        let (a, b) = (read.camera_from_world, written.camera_from_world);
        assert!((0..16).all(|i| (a[i / 4][i % 4] - b[i / 4][i % 4]).abs() < 1e-12));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_largest_documented_size_loads() {
    let dir = edited("max-size", |json| {
        let cam = bad_camera(json);
        cam["width"] = MAX_IMAGE_SIDE.into();
        cam["height"] = MAX_IMAGE_SIDE.into();
    });
    let info = BundleInfo::load(&dir).unwrap();
    assert_eq!(info.cameras[BAD].width, MAX_IMAGE_SIDE);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn width_zero_is_rejected() {
    let dir = edited("width-0", |json| bad_camera(json)["width"] = 0.into());
    assert_rejected(&dir, &["width is 0", "image size must be 1 to 16384"]);
}

#[test]
fn width_u32_max_is_rejected() {
    let dir = edited("width-max", |json| {
        bad_camera(json)["width"] = u32::MAX.into()
    });
    assert_rejected(
        &dir,
        &["width is 4294967295", "image size must be 1 to 16384"],
    );
}

#[test]
fn height_above_the_limit_is_rejected() {
    let dir = edited("height-limit", |json| {
        bad_camera(json)["height"] = (MAX_IMAGE_SIDE + 1).into()
    });
    assert_rejected(&dir, &["height is 16385", "image size must be 1 to 16384"]);
}

#[test]
fn fx_zero_is_rejected() {
    let dir = edited("fx-0", |json| bad_camera(json)["fx"] = 0.0.into());
    assert_rejected(
        &dir,
        &["fx is 0", "focal length must be finite and positive"],
    );
}

#[test]
fn fx_nan_is_rejected() {
    // JSON has no NaN: serde_json writes a NaN focal length as `null`.
    let nan = serde_json::to_value(f64::NAN).unwrap();
    assert_eq!(nan, Value::Null);
    let dir = edited("fx-nan", |json| bad_camera(json)["fx"] = nan);
    assert_rejected(
        &dir,
        &["fx is NaN", "focal length must be finite and positive"],
    );
}

#[test]
fn a_non_finite_matrix_entry_is_rejected() {
    let dir = edited("matrix-nan", |json| {
        bad_camera(json)["camera_from_world"][1][3] = Value::Null
    });
    assert_rejected(
        &dir,
        &[
            "camera_from_world: matrix entry [1][3] is NaN",
            "must be finite",
        ],
    );
}

#[test]
fn a_scaled_rotation_is_rejected() {
    // 1% larger: R^T R = 1.0201 I.
    let dir = edited("scaled", |json| {
        edit_matrix(json, |r, c, v| if r < 3 && c < 3 { 1.01 * v } else { v })
    });
    assert_rejected(&dir, &["not orthonormal", "rigid transform"]);
}

#[test]
fn a_reflection_is_rejected() {
    // The camera's z axis flipped: orthonormal, determinant -1.
    let dir = edited("reflection", |json| {
        edit_matrix(json, |r, _, v| if r == 2 { -v } else { v })
    });
    assert_rejected(&dir, &["determinant -1", "reflection", "determinant +1"]);
}

/// Asserts that `SceneBundle::load` refuses the bundle in `dir` naming `bundle.json` and every
/// part of `problem` (values that only the scene or the networks can contradict).
fn assert_load_rejected(dir: &Path, problem: &[&str]) {
    let file = dir.join(INFO_FILE).display().to_string();
    let msg = SceneBundle::load(dir)
        .map(|_| ())
        .expect_err("the bad bundle.json was accepted")
        .to_string();
    assert!(msg.contains(&file), "does not name {file}: {msg}");
    assert!(!msg.starts_with("checkpoint"), "{msg}");
    for p in problem {
        assert!(msg.contains(p), "does not say `{p}`: {msg}");
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn a_camera_smaller_than_the_networks_decode_is_rejected_at_load() {
    let min = valid_bundle().min_view_side();
    assert!(min >= 2, "{min}");
    // The networks need the feature map to keep 2x2 positions after pooling.
    let (w, h) = valid_bundle().feature_size(min, min);
    assert!(w.min(h) >= 2, "{w}x{h}");
    let (w, h) = valid_bundle().feature_size(min - 1, min - 1);
    assert!(w.min(h) < 2, "{w}x{h}");
    let dir = edited("tiny-camera", |json| {
        let cam = bad_camera(json);
        cam["width"] = serde_json::json!(1);
        cam["height"] = serde_json::json!(1);
        cam["cx"] = serde_json::json!(0.5);
        cam["cy"] = serde_json::json!(0.5);
    });
    assert_load_rejected(
        &dir,
        &[
            &format!("camera {BAD} ({BAD_NAME}) is 1x1"),
            &format!("at least {min} pixels"),
        ],
    );
}

/// A case: its name, the edit of `bundle.json`, and the words the error must hold.
type Case = (&'static str, fn(&mut Value), &'static [&'static str]);

#[test]
fn bundle_json_values_that_do_not_fit_are_named_by_key() {
    let cases: [Case; 4] = [
        (
            "feature-dim",
            |j| j["feature_dim"] = serde_json::json!(FEATURES + 1),
            &["feature_dim is 5"],
        ),
        (
            "background-len",
            |j| j["feature_background"] = serde_json::json!([0.0]),
            &["feature_background has 1 values"],
        ),
        (
            "scene-std-len",
            |j| j["scene_std"] = serde_json::json!([1.0]),
            &["scene_mean and scene_std"],
        ),
        (
            "encoder-widths",
            |j| j["encoder_widths"] = serde_json::json!([1, 2]),
            &["encoder_widths is [1, 2]"],
        ),
    ];
    for (name, edit, problem) in cases {
        let dir = edited(name, edit);
        assert_load_rejected(&dir, problem);
    }
}
