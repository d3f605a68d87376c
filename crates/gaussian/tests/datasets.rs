//! Dataset loading: the NeRF-synthetic lego scene, the beer-can COLMAP and LLFF scenes, the
//! hand-made COLMAP text fixture, the `.npy` reader, undistortion and the evaluation split.
//!
//! The pose conventions are checked by geometry rather than by numbers copied from elsewhere:
//! COLMAP's own 3D points must reproject onto its own 2D observations (through the
//! SIMPLE_RADIAL distortion), the LLFF poses must give the same cameras as the COLMAP model they
//! were made from, and the lego cameras must sit on a sphere looking at the origin.

use std::path::{Path, PathBuf};

use dsgs_testkit::{repo_fixture, scratch_dir, shared_path};
use gaussian::dataset::colmap::{self, CameraModel};
use gaussian::dataset::images::{resize, undistort, RgbImage};
use gaussian::dataset::{
    eval_split, Dataset, DatasetError, DatasetKind, Distortion, DistortionHandling, LoadOptions,
    Resolution,
};
use gaussian::npy::{parse_npy, read_npy};
use gaussian::{Camera, Intrinsics};
use glam::DVec3;

fn beer_can() -> PathBuf {
    shared_path("data/scenes/beer_can")
}

fn lego() -> PathBuf {
    shared_path("data/scenes/lego")
}

fn opts(resolution: Resolution) -> LoadOptions {
    LoadOptions {
        resolution,
        ..LoadOptions::default()
    }
}

// ---------------------------------------------------------------------------------------------
// NeRF-synthetic

#[test]
fn lego_loads_with_cameras_on_a_sphere_looking_at_the_origin() {
    let d = Dataset::load(lego(), &LoadOptions::default()).unwrap();
    assert_eq!(d.kind, DatasetKind::NerfSynthetic);
    assert_eq!(d.len(), 100);
    assert!(d.points.is_none());
    assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    assert_eq!(d.names[0], "r_0");
    let radii: Vec<f64> = d.cameras.iter().map(|c| c.center().length()).collect();
    let mean = radii.iter().sum::<f64>() / radii.len() as f64;
    let spread = radii.iter().map(|r| (r - mean).abs()).fold(0.0, f64::max);
    println!("lego camera distance from origin: mean {mean:.4}, max deviation {spread:.2e}");
    // Blender renders the lego views at radius ~4.03 around the origin.
    assert!(
        (mean - 4.03).abs() < 0.01 && spread < 1e-3,
        "{mean} {spread}"
    );
    let mut worst = 0.0f64;
    for c in &d.cameras {
        let k = c.intrinsics;
        assert_eq!((k.width, k.height), (800, 800));
        // fx = 400 / tan(camera_angle_x / 2), camera_angle_x = 0.6911112070083618.
        assert!((k.fx - 400.0 / (0.5f64 * 0.6911112070083618).tan()).abs() < 1e-9);
        assert_eq!((k.fx, k.cx, k.cy), (k.fy, 400.0, 400.0));
        // The origin is in front of every camera and projects near the image centre.
        let (u, v, z) = c.project_point(DVec3::ZERO);
        assert!(z > 3.9);
        worst = worst.max((u - 400.0).abs()).max((v - 400.0).abs());
        // The viewing direction points at the origin.
        assert!(c.view_direction().dot(-c.center().normalize()) > 0.999);
    }
    println!("lego: origin projects within {worst:.2e} px of the image centre");
    // Blender aimed every camera at the origin; float32 matrices leave micro-pixel residue.
    assert!(worst < 1e-2, "{worst}");
}

#[test]
fn lego_rgba_is_composited_onto_the_background() {
    let white = LoadOptions {
        background: [1.0, 1.0, 1.0],
        ..LoadOptions::default()
    };
    let black = Dataset::load_nerf_synthetic(lego(), "train", &LoadOptions::default()).unwrap();
    let white = Dataset::load_nerf_synthetic(lego(), "train", &white).unwrap();
    let (b, w) = (black.load_image(0).unwrap(), white.load_image(0).unwrap());
    assert_eq!((b.width, b.height, b.data.len()), (800, 800, 800 * 800 * 3));
    // The corner of r_0 is empty (alpha 0): it shows the background.
    assert_eq!(b.pixel(0, 0), [0.0; 3]);
    assert_eq!(w.pixel(0, 0), [1.0; 3]);
    // Where the object is opaque both agree; elsewhere white >= black.
    let agree = b.data.iter().zip(&w.data).filter(|(x, y)| x == y).count();
    assert!(agree > 100_000, "{agree}");
    assert!(b
        .data
        .iter()
        .zip(&w.data)
        .all(|(x, y)| y >= x && *x >= 0.0 && *y <= 1.0));
    // Downscaling on load halves cameras and images alike.
    let half = Dataset::load(lego(), &opts(Resolution::Downscale(2.0))).unwrap();
    let k = half.cameras[0].intrinsics;
    assert_eq!((k.width, k.height, k.cx), (400, 400, 200.0));
    assert!((k.fx - black.cameras[0].intrinsics.fx / 2.0).abs() < 1e-9);
    let img = half.load_image(0).unwrap();
    assert_eq!((img.width, img.height), (400, 400));
}

// ---------------------------------------------------------------------------------------------
// COLMAP

#[test]
fn beer_can_colmap_loads_from_images_8() {
    let d = Dataset::load(beer_can(), &opts(Resolution::Folder(8))).unwrap();
    assert_eq!(d.kind, DatasetKind::Colmap);
    assert_eq!(d.len(), 71);
    let names: Vec<String> = (0..71).map(|i| format!("{i:04}.jpg")).collect();
    assert_eq!(d.names, names);
    let pts = d.points.as_ref().unwrap();
    assert_eq!(pts.positions.len(), 4414);
    assert_eq!(pts.colors.len(), 4414);
    // Each image has its own SIMPLE_RADIAL camera; the dataset camera is 1/8 of it.
    let model = colmap::read_model(&beer_can().join("sparse/0")).unwrap();
    assert_eq!(model.cameras.len(), 71);
    for (c, im) in d.cameras.iter().zip(&d.names) {
        let im = model.images.iter().find(|x| x.name == *im).unwrap();
        let full = model.cameras.iter().find(|c| c.id == im.camera_id).unwrap();
        assert_eq!(full.model, CameraModel::SimpleRadial);
        assert_eq!((full.width, full.height), (720, 1280));
        let k = c.intrinsics;
        assert_eq!((k.width, k.height), (90, 160));
        assert_eq!((k.fx, k.fy), (full.params[0] / 8.0, full.params[0] / 8.0));
        assert_eq!((k.cx, k.cy), (full.params[1] / 8.0, full.params[2] / 8.0));
    }
    // Image 0000.jpg (camera 1: f 1105.13, principal point (360, 640), k 0.0578).
    assert_eq!(d.cameras[0].intrinsics.fx, 1105.1327235097242 / 8.0);
    assert_eq!(
        (d.cameras[0].intrinsics.cx, d.cameras[0].intrinsics.cy),
        (45.0, 80.0)
    );
    assert_eq!(
        d.distortions[0],
        Some(Distortion::Radial {
            k1: 0.05780360126098173,
            k2: 0.0
        })
    );
    assert!(d.distortions.iter().all(Option::is_some));
    // The shared images_8 folder holds only the first 29 images: the rest are resized on load.
    for (i, p) in d.image_paths.iter().enumerate() {
        let folder = p.parent().unwrap().file_name().unwrap();
        assert_eq!(folder, if i < 29 { "images_8" } else { "images" }, "{i}");
    }
    assert_eq!(d.warnings.len(), 1, "{:?}", d.warnings);
    assert!(
        d.warnings[0].contains("42 of 71 images are missing"),
        "{}",
        d.warnings[0]
    );
    for i in [0, 50] {
        let img = d.load_image(i).unwrap();
        assert_eq!((img.width, img.height), (90, 160));
        assert!(img.data.iter().all(|v| (0.0..=1.0).contains(v)));
    }
    let split = d.split();
    assert_eq!(split.test, vec![0, 8, 16, 24, 32, 40, 48, 56, 64]);
    assert_eq!(split.train.len(), 62);
    let test = d.subset(&split.test).unwrap();
    assert_eq!(test.names[1], "0008.jpg");
    assert_eq!(test.cameras[1], d.cameras[8]);
}

/// The images_8 files and our own bicubic downscaling of the full-resolution files show the
/// same picture (compared without undistortion, which both would share).
#[test]
fn images_8_matches_resized_full_resolution() {
    let o = LoadOptions {
        distortion: DistortionHandling::Ignore,
        ..opts(Resolution::Folder(8))
    };
    let folder = Dataset::load(beer_can(), &o).unwrap();
    let resized = Dataset::load(
        beer_can(),
        &LoadOptions {
            resolution: Resolution::Downscale(8.0),
            ..o
        },
    )
    .unwrap();
    assert_eq!(folder.cameras[3], resized.cameras[3]);
    let (a, b) = (
        folder.load_image(3).unwrap(),
        resized.load_image(3).unwrap(),
    );
    let mad = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| (x - y).abs())
        .sum::<f32>()
        / a.data.len() as f32;
    println!("images_8/0003.jpg vs resized images/0003.jpg: mean abs difference {mad:.4}");
    assert!(mad < 0.03, "{mad}");
}

/// Projects every COLMAP 3D point into every image that observes it (full-resolution camera
/// plus the SIMPLE_RADIAL distortion) and compares with the stored 2D observation. COLMAP's
/// own per-point mean reprojection error (the `error` field) is an independent check.
#[test]
fn beer_can_points_reproject_onto_their_observations() {
    let model = colmap::read_model(&beer_can().join("sparse/0")).unwrap();
    assert_eq!(model.cameras.len(), 71);
    assert_eq!(model.images.len(), 71);
    assert_eq!(model.points.len(), 4414);
    let d = Dataset::load_colmap(beer_can(), &LoadOptions::default()).unwrap();
    let point_index: std::collections::HashMap<u64, usize> = model
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| (p.id, i))
        .collect();
    let mut per_point = vec![(0.0f64, 0usize); model.points.len()];
    let (mut sum, mut max, mut n) = (0.0f64, 0.0f64, 0usize);
    for im in &model.images {
        let i = d.names.iter().position(|n| *n == im.name).unwrap();
        let cam = &d.cameras[i];
        let dist = d.distortions[i].unwrap();
        assert_eq!((cam.intrinsics.width, cam.intrinsics.height), (720, 1280));
        for (xy, pid) in &im.points2d {
            let Some(pid) = pid else { continue };
            let p = &model.points[point_index[pid]];
            let (u, v, z) = cam.project_point(DVec3::from_array(p.xyz));
            assert!(z > 0.0);
            let (u, v) = dist.distort_pixel(&cam.intrinsics, u, v);
            let e = ((u - xy[0]).powi(2) + (v - xy[1]).powi(2)).sqrt();
            sum += e;
            max = max.max(e);
            n += 1;
            let slot = &mut per_point[point_index[pid]];
            slot.0 += e;
            slot.1 += 1;
        }
    }
    let mean = sum / n as f64;
    let stored_gap = model
        .points
        .iter()
        .zip(&per_point)
        .map(|(p, (s, c))| (s / *c as f64 - p.error).abs())
        .fold(0.0f64, f64::max);
    println!(
        "beer_can reprojection over {n} observations: mean {mean:.4} px, max {max:.4} px; \
         max |per-point mean - COLMAP error| = {stored_gap:.2e} px"
    );
    assert!(mean < 1.0 && max < 4.5, "mean {mean} max {max}");
    assert!(stored_gap < 1e-3, "{stored_gap}");
}

/// The LLFF poses of beer can were made from its COLMAP model (same world frame), so both
/// loaders must produce the same cameras.
#[test]
fn beer_can_llff_and_colmap_poses_agree() {
    let ignore = LoadOptions {
        distortion: DistortionHandling::Ignore,
        ..LoadOptions::default()
    };
    let c = Dataset::load_colmap(beer_can(), &ignore).unwrap();
    let l = Dataset::load_llff(beer_can(), &ignore).unwrap();
    assert_eq!(l.kind, DatasetKind::Llff);
    assert_eq!(l.names, c.names);
    assert_eq!(l.points, c.points);
    let nf = l.near_far.as_ref().unwrap();
    assert!(nf.iter().all(|[n, f]| 0.0 < *n && n < f));
    let (mut dc, mut dr) = (0.0f64, 0.0f64);
    for (a, b) in l.cameras.iter().zip(&c.cameras) {
        dc = dc.max(a.center().distance(b.center()));
        dr = dr.max(
            (a.rotation() - b.rotation())
                .abs()
                .to_cols_array()
                .iter()
                .fold(0.0, |m, v| m.max(*v)),
        );
        // LLFF keeps a single focal length, that of the first COLMAP camera.
        let (ka, kb) = (a.intrinsics, b.intrinsics);
        assert_eq!(
            (ka.width, ka.height, ka.cx, ka.cy),
            (kb.width, kb.height, kb.cx, kb.cy)
        );
        assert_eq!((ka.fx, ka.fy), (1105.1327235097242, 1105.1327235097242));
    }
    let (lo, hi) = c.cameras.iter().fold((f64::MAX, 0.0f64), |(lo, hi), k| {
        (lo.min(k.intrinsics.fx), hi.max(k.intrinsics.fx))
    });
    println!(
        "beer_can COLMAP focal lengths range over [{lo:.2}, {hi:.2}] px; LLFF uses 1105.13 for all"
    );
    println!("beer_can LLFF vs COLMAP: max centre distance {dc:.2e}, max rotation entry difference {dr:.2e}");
    assert!(dc < 1e-9 && dr < 1e-9, "{dc} {dr}");
}

#[test]
fn distortion_handling_choices() {
    let err = Dataset::load_colmap(
        beer_can(),
        &LoadOptions {
            distortion: DistortionHandling::Reject,
            ..LoadOptions::default()
        },
    )
    .unwrap_err();
    assert!(matches!(
        err,
        DatasetError::UnsupportedCameraModel {
            model: "SIMPLE_RADIAL",
            ..
        }
    ));
    assert!(err.to_string().contains("cameras.bin"), "{err}");
    let ignore = Dataset::load_colmap(
        beer_can(),
        &LoadOptions {
            distortion: DistortionHandling::Ignore,
            ..LoadOptions::default()
        },
    )
    .unwrap();
    assert!(ignore.distortions.iter().all(Option::is_none));
    assert_eq!(ignore.warnings.len(), 1);
    let w = &ignore.warnings[0];
    assert!(
        w.contains("71 of 71 cameras") && w.contains("SIMPLE_RADIAL") && w.contains("k1=0.0578"),
        "{w}"
    );
}

/// A smooth test pattern `g` is "photographed" through a distortion by evaluating it at the
/// undistorted position of every source pixel (found by fixed-point iteration, independent of
/// the library's forward mapping); undistorting must give `g` back at every output pixel.
#[test]
fn undistortion_inverts_a_synthetic_distortion() {
    let k = Intrinsics {
        fx: 60.0,
        fy: 55.0,
        cx: 41.0,
        cy: 29.5,
        width: 80,
        height: 60,
    };
    let g = |x: f64, y: f64| 0.5 + 0.4 * (x / 9.0).sin() * (y / 7.0).cos();
    for dist in [
        Distortion::Radial {
            k1: -0.12,
            k2: 0.02,
        },
        Distortion::OpenCv {
            k1: 0.08,
            k2: -0.01,
            p1: 0.004,
            p2: -0.003,
        },
    ] {
        let (k1, k2, p1, p2) = match dist {
            Distortion::Radial { k1, k2 } => (k1, k2, 0.0, 0.0),
            Distortion::OpenCv { k1, k2, p1, p2 } => (k1, k2, p1, p2),
        };
        let mut data = Vec::new();
        for y in 0..k.height {
            for x in 0..k.width {
                let (ud, vd) = (
                    (x as f64 + 0.5 - k.cx) / k.fx,
                    (y as f64 + 0.5 - k.cy) / k.fy,
                );
                // Solve distort(u, v) = (ud, vd) by fixed-point iteration.
                let (mut u, mut v) = (ud, vd);
                for _ in 0..100 {
                    let r2 = u * u + v * v;
                    let s = 1.0 + k1 * r2 + k2 * r2 * r2;
                    let tu = 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
                    let tv = 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v);
                    u = (ud - tu) / s;
                    v = (vd - tv) / s;
                }
                let value = g(k.fx * u + k.cx, k.fy * v + k.cy) as f32;
                data.extend([value, value, 1.0 - value]);
            }
        }
        let photo = RgbImage {
            width: k.width,
            height: k.height,
            data,
        };
        let out = undistort(&photo, &k, &dist);
        let mut worst = 0.0f64;
        for y in 0..k.height {
            for x in 0..k.width {
                let (sx, sy) = dist.distort_pixel(&k, x as f64 + 0.5, y as f64 + 0.5);
                if sx < 1.0 || sy < 1.0 || sx > k.width as f64 - 1.0 || sy > k.height as f64 - 1.0 {
                    continue; // the source lies outside the photograph
                }
                let e = (out.pixel(x, y)[0] as f64 - g(x as f64 + 0.5, y as f64 + 0.5)).abs();
                worst = worst.max(e);
            }
        }
        println!("undistortion of {dist:?}: max error {worst:.2e}");
        // Bilinear interpolation error of g (second derivatives <= 0.4/49) over a unit cell.
        assert!(worst < 0.004, "{worst}");
    }
    // The identity distortion samples exactly at pixel centres: the image is unchanged.
    let img = RgbImage {
        width: 3,
        height: 2,
        data: (0..18).map(|v| v as f32 / 17.0).collect(),
    };
    assert_eq!(
        undistort(
            &img,
            &Intrinsics {
                fx: 2.0,
                fy: 2.0,
                cx: 1.5,
                cy: 1.0,
                width: 3,
                height: 2
            },
            &Distortion::Radial { k1: 0.0, k2: 0.0 }
        ),
        img
    );
    assert_eq!(resize(&img, 3, 2), img);
}

// ---------------------------------------------------------------------------------------------
// the hand-made COLMAP text fixture

/// Expected values computed by hand from the fixture text.
#[test]
fn colmap_text_fixture() {
    let model = colmap::read_model(&repo_fixture("colmap_tiny/sparse/0")).unwrap();
    assert_eq!(model.cameras.len(), 2);
    assert_eq!(model.cameras[0].model, CameraModel::Pinhole);
    assert_eq!(model.cameras[1].model, CameraModel::SimpleRadial);
    assert_eq!(model.cameras[1].params, vec![50.0, 32.0, 24.0, 0.1]);
    assert_eq!(model.images.len(), 2);
    assert_eq!(
        model.images[0].points2d,
        vec![
            ([37.0, 19.2], Some(1)),
            ([10.0, 20.0], None),
            ([19.5, 39.0], Some(2))
        ]
    );
    assert!(model.images[1].points2d.is_empty());
    assert_eq!(model.images[1].name, "b.png");
    assert_eq!(model.points[1].rgb, [0, 128, 255]);
    assert_eq!(model.points[1].track, vec![(1, 2)]);

    // Camera 1 (PINHOLE 50 60 32 24) at the identity pose sees (0.5, -0.4, 5) at
    // (50 * 0.1 + 32, 60 * -0.08 + 24) = (37, 19.2) and (-1, 1, 4) at (19.5, 39).
    let k = Intrinsics {
        fx: 50.0,
        fy: 60.0,
        cx: 32.0,
        cy: 24.0,
        width: 64,
        height: 48,
    };
    let cam = Camera::new(k, glam::DMat4::IDENTITY);
    for (xy, pid) in model.images[0].points2d.iter().filter(|p| p.1.is_some()) {
        let p = model.points.iter().find(|p| Some(p.id) == *pid).unwrap();
        let (u, v, _) = cam.project_point(DVec3::from_array(p.xyz));
        assert!((u - xy[0]).abs() < 1e-12 && (v - xy[1]).abs() < 1e-12);
    }
}

/// The fixture loads as a dataset once image files exist, and image 2 (a 90 degree turn about
/// y, t = (0, 0, 4)) has its centre at -R^T t = (4, 0, 0) and looks along -x.
#[test]
fn colmap_text_fixture_as_dataset() {
    let dir = scratch_dir("data", "colmap_tiny");
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::copy(repo_fixture("colmap_tiny/sparse/0").join(f), sparse.join(f)).unwrap();
    }
    std::fs::create_dir_all(dir.join("images")).unwrap();
    for name in ["a.png", "b.png"] {
        image::RgbImage::from_pixel(64, 48, image::Rgb([255, 0, 0]))
            .save(dir.join("images").join(name))
            .unwrap();
    }
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(d.names, vec!["a.png", "b.png"]);
    assert!(d.distortions[0].is_none());
    assert_eq!(
        d.distortions[1],
        Some(Distortion::Radial { k1: 0.1, k2: 0.0 })
    );
    assert!(d.cameras[1].center().distance(DVec3::new(4.0, 0.0, 0.0)) < 1e-12);
    assert!(
        d.cameras[1]
            .view_direction()
            .distance(DVec3::new(-1.0, 0.0, 0.0))
            < 1e-12
    );
    assert_eq!(
        d.points.as_ref().unwrap().colors,
        vec![[255, 0, 0], [0, 128, 255]]
    );
    let img = d.load_image(1).unwrap();
    assert_eq!(img.pixel(10, 10), [1.0, 0.0, 0.0]);
    assert!(matches!(
        d.load_image(2),
        Err(DatasetError::Index { index: 2, len: 2 })
    ));

    // An unsupported model is refused with its name and the file.
    std::fs::write(
        sparse.join("cameras.txt"),
        "1 OPENCV_FISHEYE 64 48 50 50 32 24 0 0 0 0\n2 PINHOLE 64 48 50 60 32 24\n",
    )
    .unwrap();
    let err = Dataset::load(&dir, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("OPENCV_FISHEYE") && err.contains("cameras.txt"),
        "{err}"
    );
    // A missing image file is named.
    std::fs::write(
        sparse.join("cameras.txt"),
        "1 PINHOLE 64 48 50 60 32 24\n2 PINHOLE 64 48 50 60 32 24\n",
    )
    .unwrap();
    std::fs::remove_file(dir.join("images/b.png")).unwrap();
    let err = Dataset::load(&dir, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("b.png") && err.contains("not found"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Image names that leave the dataset's `images/` folder (absolute, or `..` above it) are
/// refused before any file is opened, naming `images.txt` and the image; a point whose position
/// is not finite is refused naming `points3D.txt` and the point.
#[test]
fn colmap_names_stay_inside_the_dataset_and_points_are_finite() {
    let dir = scratch_dir("data", "colmap_escape");
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    for f in ["cameras.txt", "points3D.txt"] {
        std::fs::copy(repo_fixture("colmap_tiny/sparse/0").join(f), sparse.join(f)).unwrap();
    }
    std::fs::create_dir_all(dir.join("images/sub")).unwrap();
    for name in ["a.png", "sub/b.png"] {
        image::RgbImage::from_pixel(64, 48, image::Rgb([255, 0, 0]))
            .save(dir.join("images").join(name))
            .unwrap();
    }
    // A readable file outside the dataset: a name reaching it must not load it.
    let outside = dir.join("x.png");
    image::RgbImage::from_pixel(64, 48, image::Rgb([0, 255, 0]))
        .save(&outside)
        .unwrap();
    let images_txt = |second: &str| {
        std::fs::write(
            sparse.join("images.txt"),
            format!("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 4 2 {second}\n\n"),
        )
        .unwrap();
    };
    // Inside the folder, `..` that stays inside is fine.
    images_txt("sub/../sub/b.png");
    let d = Dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(d.len(), 2);
    for (bad, why) in [
        ("../x.png", "leaves the images folder"),
        ("sub/../../x.png", "leaves the images folder"),
        ("/etc/hostname", "is absolute"),
        (outside.to_str().unwrap(), "is absolute"),
    ] {
        images_txt(bad);
        let err = Dataset::load(&dir, &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("images.txt") && err.contains(why) && err.contains(bad),
            "{bad}: {err}"
        );
    }
    images_txt("a.png");
    std::fs::write(
        sparse.join("points3D.txt"),
        "1 0 0 0 255 0 0 0.5 1 0\n7 1 nan 2 0 128 255 0.5 2 0\n",
    )
    .unwrap();
    let err = Dataset::load(&dir, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("points3D.txt") && err.contains("point 7") && err.contains("not finite"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// npy and split

#[test]
fn npy_reader() {
    let a = read_npy(beer_can().join("poses_bounds.npy")).unwrap();
    assert_eq!(a.shape, vec![71, 17]);
    // hwf of the first pose: height 1280, width 720.
    assert_eq!((a.data[4], a.data[9]), (1280.0, 720.0));

    let header = |descr: &str, fortran: &str, shape: &str| {
        let mut h =
            format!("{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b
    };
    let mut b = header("<f4", "False", "(3,)");
    for v in [1.5f32, -2.0, 0.25] {
        b.extend(v.to_le_bytes());
    }
    let a = parse_npy(&b, Path::new("a.npy")).unwrap();
    assert_eq!((a.shape, a.data), (vec![3], vec![1.5, -2.0, 0.25]));
    let mut b = header(">f8", "False", "(1, 2)");
    for v in [3.0f64, -4.5] {
        b.extend(v.to_be_bytes());
    }
    let a = parse_npy(&b, Path::new("b.npy")).unwrap();
    assert_eq!((a.shape, a.data), (vec![1, 2], vec![3.0, -4.5]));
    let b = header("<f8", "False", "()");
    let mut b0 = b.clone();
    b0.extend(7.0f64.to_le_bytes());
    assert_eq!(parse_npy(&b0, Path::new("s.npy")).unwrap().data, vec![7.0]);

    let err = |b: &[u8]| parse_npy(b, Path::new("bad.npy")).unwrap_err().to_string();
    assert!(err(&header("<f8", "True", "(2, 2)")).contains("Fortran order"));
    assert!(err(&header("<i8", "False", "(2,)")).contains("unsupported dtype '<i8'"));
    assert!(err(&header("<f8", "False", "(2,)")).contains("needs 16 data bytes, the file has 0"));
    assert!(err(&header("<f8", "False", "(4611686018427387904, 4)")).contains("too large"));
    assert!(err(b"\x93NUMPZ").contains("magic"));
}

#[test]
fn evaluation_split_holds_out_every_eighth_image() {
    let s = eval_split(17);
    assert_eq!(s.test, vec![0, 8, 16]);
    assert_eq!(
        s.train,
        vec![1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15]
    );
    assert!(eval_split(0).test.is_empty());
}
