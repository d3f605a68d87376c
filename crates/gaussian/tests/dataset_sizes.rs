//! Every view of a dataset is loaded at one image size: photos that differ by a few pixels (or
//! whose sizes round differently after downscaling) are brought to the most common size, with
//! their intrinsics scaled per axis, and the dataset reports which views were resized.
//!
//! The scenes are tiny synthetic COLMAP text models (one PINHOLE camera per photo, as COLMAP
//! writes for photos of different sizes) and a NeRF-synthetic scene, with PNGs written to a
//! scratch folder.

use std::path::{Path, PathBuf};

use dsgs_testkit::scratch_dir;
use gaussian::dataset::colmap;
use gaussian::dataset::{Dataset, LoadOptions, Resolution};

/// A COLMAP text scene with one PINHOLE camera and one identity-pose image per entry of
/// `sizes`; image `i` is named `{i}.png` and filled with a grey level of its own. The focal
/// lengths and principal point of camera `i` differ per photo so a swapped scale would show.
fn colmap_scene(name: &str, sizes: &[(u32, u32)]) -> PathBuf {
    let dir = scratch_dir("sizes", name);
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let mut cameras = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let mut images = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for (i, &(w, h)) in sizes.iter().enumerate() {
        let id = i + 1;
        let (fx, fy) = (1.1 * w as f64 + i as f64, 0.9 * w as f64 + 2.0 * i as f64);
        let (cx, cy) = (0.5 * w as f64 + 0.25, 0.5 * h as f64 - 0.75);
        cameras.push_str(&format!("{id} PINHOLE {w} {h} {fx} {fy} {cx} {cy}\n"));
        images.push_str(&format!("{id} 1 0 0 0 0 0 {} {id} {i}.png\n\n", i as f64));
        let grey = (40 * i % 256) as u8;
        image::RgbImage::from_pixel(w, h, image::Rgb([grey, grey, grey]))
            .save(dir.join("images").join(format!("{i}.png")))
            .unwrap();
    }
    std::fs::write(sparse.join("cameras.txt"), cameras).unwrap();
    std::fs::write(sparse.join("images.txt"), images).unwrap();
    std::fs::write(sparse.join("points3D.txt"), "").unwrap();
    dir
}

fn opts(resolution: Resolution) -> LoadOptions {
    LoadOptions {
        resolution,
        ..LoadOptions::default()
    }
}

fn sizes(d: &Dataset) -> Vec<(u32, u32)> {
    d.cameras
        .iter()
        .map(|c| (c.intrinsics.width, c.intrinsics.height))
        .collect()
}

/// The COLMAP model's camera of image `name`, at its full resolution.
fn model_camera(dir: &Path, name: &str) -> colmap::ColmapCamera {
    let model = colmap::read_model(&dir.join("sparse/0")).unwrap();
    let im = model.images.iter().find(|im| im.name == name).unwrap();
    model
        .cameras
        .iter()
        .find(|c| c.id == im.camera_id)
        .unwrap()
        .clone()
}

/// Relative closeness for values computed along different (exact in reals) routes.
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0)
}

/// Two photos 62 px tall and one 61 px tall: at full resolution the odd one is brought to
/// 100x62, with its vertical intrinsics scaled by 62/61 and its horizontal ones unchanged.
#[test]
fn photos_a_few_pixels_apart_load_at_one_size_with_scaled_intrinsics() {
    let dir = colmap_scene("full", &[(100, 61), (100, 62), (100, 62)]);
    let d = Dataset::load(&dir, &opts(Resolution::Full)).unwrap();
    let common = d.image_size().unwrap();
    assert_eq!(common, (100, 62), "the most common size wins");
    assert!(sizes(&d).iter().all(|&s| s == common), "{:?}", sizes(&d));

    // The report names exactly the odd view, with the size it had.
    assert_eq!(d.resized.len(), 1, "{:?}", d.resized);
    let r = &d.resized[0];
    assert_eq!((r.index, r.name.as_str(), r.from), (0, "0.png", (100, 61)));
    assert!(d.warnings.is_empty(), "{:?}", d.warnings);

    // Its intrinsics are the model's, scaled per axis by the ratio of the sizes.
    let cam = model_camera(&dir, "0.png");
    let (sx, sy) = (
        common.0 as f64 / cam.width as f64,
        common.1 as f64 / cam.height as f64,
    );
    let p = &cam.params;
    let k = d.cameras[0].intrinsics;
    assert!(close(k.fx, p[0] * sx) && close(k.cx, p[2] * sx), "{k:?}");
    assert!(close(k.fy, p[1] * sy) && close(k.cy, p[3] * sy), "{k:?}");
    assert!(
        k.fy != p[1] && k.cy != p[3],
        "the vertical intrinsics changed"
    );
    // The views that already had the common size keep the model's intrinsics.
    let cam1 = model_camera(&dir, "1.png");
    let k1 = d.cameras[1].intrinsics;
    assert_eq!(
        [k1.fx, k1.fy, k1.cx, k1.cy],
        [
            cam1.params[0],
            cam1.params[1],
            cam1.params[2],
            cam1.params[3]
        ]
    );

    // Every image decodes at its camera's (common) size, the resized one showing its picture.
    for i in 0..d.len() {
        let img = d.load_image(i).unwrap();
        assert_eq!((img.width, img.height), common, "view {i}");
    }
    let img = d.load_image(0).unwrap();
    assert!(
        img.data.iter().all(|&v| v == img.data[0]),
        "a flat image stays flat"
    );

    // A subset keeps the report, with indices into the subset.
    let sub = d.subset(&[2, 0]).unwrap();
    assert_eq!(sub.resized.len(), 1);
    assert_eq!(
        (sub.resized[0].index, sub.resized[0].name.as_str()),
        (1, "0.png")
    );
    assert!(d.subset(&[1, 2]).unwrap().resized.is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The case of the issue: heights 656 and 662 downscaled by 6 round to 109 and 110. In
/// miniature: heights 61 and 62 downscaled by 4 round to 15 and 16 (15.25 and 15.5, rounded
/// half away from zero), and the views still come out at one size.
#[test]
fn sizes_that_round_apart_after_downscaling_are_unified() {
    let dir = colmap_scene("down", &[(100, 61), (100, 62), (100, 62)]);
    let d = Dataset::load(&dir, &opts(Resolution::Downscale(4.0))).unwrap();
    let common = d.image_size().unwrap();
    assert!(sizes(&d).iter().all(|&s| s == common), "{:?}", sizes(&d));
    assert_eq!(d.resized.len(), 1, "{:?}", d.resized);
    let r = &d.resized[0];
    assert_eq!(r.name, "0.png");
    assert_ne!(r.from, common);
    assert!(
        d.warnings.is_empty(),
        "rounding is no stretch: {:?}",
        d.warnings
    );
    // The odd view's camera is the model camera scaled to the common size, per axis.
    let cam = model_camera(&dir, "0.png");
    let k = d.cameras[0].intrinsics;
    let (sx, sy) = (
        common.0 as f64 / cam.width as f64,
        common.1 as f64 / cam.height as f64,
    );
    assert!(close(k.fx, cam.params[0] * sx) && close(k.fy, cam.params[1] * sy));
    assert!(close(k.cx, cam.params[2] * sx) && close(k.cy, cam.params[3] * sy));
    for i in 0..d.len() {
        let img = d.load_image(i).unwrap();
        assert_eq!((img.width, img.height), common, "view {i}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// On a tie the size of the first view wins; uniform datasets report nothing.
#[test]
fn ties_go_to_the_first_size_and_uniform_datasets_report_nothing() {
    let dir = colmap_scene("tie", &[(64, 50), (64, 48)]);
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(d.image_size(), Some((64, 50)));
    assert_eq!(d.resized.len(), 1);
    assert_eq!(d.resized[0].name, "1.png");
    std::fs::remove_dir_all(&dir).unwrap();

    let dir = colmap_scene("same", &[(64, 48), (64, 48)]);
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert!(d.resized.is_empty() && d.warnings.is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A view of another shape (a portrait photo among landscape ones) is brought to the common
/// size too, and the warning names it, since its pixels are stretched.
#[test]
fn a_view_of_another_aspect_ratio_is_named_in_a_warning() {
    let dir = colmap_scene("portrait", &[(64, 48), (48, 64), (64, 48)]);
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(d.image_size(), Some((64, 48)));
    assert!(sizes(&d).iter().all(|&s| s == (64, 48)));
    assert_eq!(d.resized.len(), 1);
    assert_eq!(d.warnings.len(), 1, "{:?}", d.warnings);
    assert!(
        d.warnings[0].contains("1.png") && d.warnings[0].contains("aspect"),
        "{}",
        d.warnings[0]
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The rule holds for every loader: a NeRF-synthetic scene with frames of two sizes.
#[test]
fn nerf_frames_of_different_sizes_load_at_one_size() {
    let dir = scratch_dir("sizes", "nerf");
    std::fs::create_dir_all(dir.join("train")).unwrap();
    let frames: Vec<String> = [(40u32, 30u32), (40, 31), (40, 30)]
        .iter()
        .enumerate()
        .map(|(i, &(w, h))| {
            image::RgbaImage::from_pixel(w, h, image::Rgba([9, 99, 199, 255]))
                .save(dir.join(format!("train/r_{i}.png")))
                .unwrap();
            format!(
                r#"{{"file_path": "./train/r_{i}", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,{}],[0,0,0,1]]}}"#,
                4 + i
            )
        })
        .collect();
    std::fs::write(
        dir.join("transforms_train.json"),
        format!(
            r#"{{"camera_angle_x": 0.7, "frames": [{}]}}"#,
            frames.join(",")
        ),
    )
    .unwrap();
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(d.image_size(), Some((40, 30)));
    assert!(sizes(&d).iter().all(|&s| s == (40, 30)), "{:?}", sizes(&d));
    assert_eq!(d.resized.len(), 1);
    assert_eq!((d.resized[0].index, d.resized[0].from), (1, (40, 31)));
    assert_eq!(d.load_image(1).unwrap().height, 30);
    std::fs::remove_dir_all(&dir).unwrap();
}
