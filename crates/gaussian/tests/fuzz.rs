//! Robustness: truncated and corrupted PLY, NeRF JSON, COLMAP (binary and text), LLFF `.npy`
//! and image inputs must produce `Ok` or `Err`, never a panic, a hang or an absurd allocation.
//!
//! Each test is a fuzz target of the testkit's harness ([`dsgs_testkit::fuzz`]): the valid seed
//! inputs, every truncation of them (a few hundred spread over the large real COLMAP files), then
//! mutated copies: byte-level mutations for all, and number, string, word and line mutations for
//! the text formats and text headers (PLY headers, `.npy` headers, JSON, COLMAP text), which
//! reach the checks past the syntax (counts claiming terabytes, non-finite or negative values,
//! unknown names). Whatever loads must also survive the next stage (saving a PLY and reading it
//! back, building and using cameras from poses, loading the images of a dataset).
//!
//! The number of mutated inputs per target is bounded for CI; `DSGS_FUZZ_CASES=N` (or
//! `unbounded`) and `DSGS_FUZZ_SEED` change it, e.g.
//! `DSGS_FUZZ_CASES=100000 cargo test --release -p dsgs-gaussian --test fuzz -- --nocapture`
//! (see `docs/robustness.md`).

use std::path::Path;

use dsgs_testkit::fuzz::{text_mutators, write_input, CappedAlloc, Target, Truncations};
use dsgs_testkit::{repo_fixture, scratch_dir, shared_path};
use gaussian::dataset::colmap::{
    self, parse_cameras_bin, parse_cameras_txt, parse_images_bin, parse_images_txt,
    parse_points3d_bin, parse_points3d_txt, ColmapModel,
};
use gaussian::dataset::nerf::{frame_matrix, parse_transforms};
use gaussian::dataset::{images, llff, Dataset, LoadOptions};
use gaussian::npy::parse_npy;
use gaussian::ply::{encode_ply, load_ply, parse_ply, ExtraProperty, ScalarType};
use gaussian::Camera;

#[global_allocator]
static ALLOC: CappedAlloc = CappedAlloc;

/// What a successfully parsed PLY must allow: saving it and reading the same scene back. The
/// scenes are compared through their encodings, bit for bit (a corrupted file may hold NaNs,
/// which `==` never matches).
fn check_ply(bytes: &[u8]) -> bool {
    let Ok(s) = parse_ply(bytes, Path::new("fuzz.ply")) else {
        return false;
    };
    let saved =
        encode_ply(&s.gaussians, &s.extras, Path::new("fuzz.ply")).expect("a loaded scene saves");
    let back = parse_ply(&saved, Path::new("saved.ply")).expect("a saved scene loads");
    let again = encode_ply(&back.gaussians, &back.extras, Path::new("saved.ply")).unwrap();
    assert!(again == saved, "a save/load round trip changed the scene");
    true
}

#[test]
fn ply_inputs_never_panic() {
    // A small binary little-endian file from the real scene: 12 Gaussians of degree 3, with
    // 4 feature channels and an extra int column.
    let mut scene = load_ply(shared_path("data/gaussians/trained_9080.ply")).unwrap();
    scene = scene.subset(&(0..12).collect::<Vec<_>>());
    scene = scene.with_features(4, 0.5);
    let extra = ExtraProperty {
        name: "label".into(),
        ty: ScalarType::I32,
        values: (0..12).map(|i| i as f64 - 6.0).collect(),
    };
    let binary = encode_ply(&scene, &[extra], Path::new("small.ply")).unwrap();
    let ascii = std::fs::read(repo_fixture("ply/tiny_ascii_deg1.ply")).unwrap();
    let big_endian = std::fs::read(repo_fixture("ply/tiny_be_deg0_feat2.ply")).unwrap();
    Target::new("PLY", 12_000)
        .seed(binary)
        .seed(ascii)
        .seed(big_endian)
        .mutators(text_mutators())
        .run(check_ply);
}

#[test]
fn nerf_json_never_panics() {
    let text =
        std::fs::read_to_string(shared_path("data/scenes/lego/transforms_train.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["frames"].as_array_mut().unwrap().truncate(3);
    let small = serde_json::to_string_pretty(&v).unwrap();
    Target::new("NeRF transforms JSON", 5_000)
        .seed(small)
        .mutators(text_mutators())
        .run(|bytes| {
            let text = String::from_utf8_lossy(bytes);
            let Ok(t) = parse_transforms(&text, Path::new("transforms.json")) else {
                return false;
            };
            for f in &t.frames {
                let m = frame_matrix(f).expect("checked by parse_transforms");
                let cam = Camera::from_opengl_world_from_camera(t.intrinsics(800, 800), m);
                let _ = cam.project_point(glam::DVec3::ZERO);
            }
            true
        });
}

/// Encodes a model in COLMAP's binary layout (as documented in `dataset::colmap`).
fn encode_model_bin(m: &ColmapModel) -> [Vec<u8>; 3] {
    let mut cams = (m.cameras.len() as u64).to_le_bytes().to_vec();
    for c in &m.cameras {
        let id = [
            "SIMPLE_PINHOLE",
            "PINHOLE",
            "SIMPLE_RADIAL",
            "RADIAL",
            "OPENCV",
        ]
        .iter()
        .position(|n| *n == c.model.name())
        .unwrap() as i32;
        cams.extend(c.id.to_le_bytes());
        cams.extend(id.to_le_bytes());
        cams.extend(c.width.to_le_bytes());
        cams.extend(c.height.to_le_bytes());
        c.params.iter().for_each(|p| cams.extend(p.to_le_bytes()));
    }
    let mut imgs = (m.images.len() as u64).to_le_bytes().to_vec();
    for im in &m.images {
        imgs.extend(im.id.to_le_bytes());
        im.qvec
            .iter()
            .chain(&im.tvec)
            .for_each(|v| imgs.extend(v.to_le_bytes()));
        imgs.extend(im.camera_id.to_le_bytes());
        imgs.extend(im.name.as_bytes());
        imgs.push(0);
        imgs.extend((im.points2d.len() as u64).to_le_bytes());
        for (xy, pid) in &im.points2d {
            imgs.extend(xy[0].to_le_bytes());
            imgs.extend(xy[1].to_le_bytes());
            imgs.extend(pid.unwrap_or(u64::MAX).to_le_bytes());
        }
    }
    let mut pts = (m.points.len() as u64).to_le_bytes().to_vec();
    for p in &m.points {
        pts.extend(p.id.to_le_bytes());
        p.xyz.iter().for_each(|v| pts.extend(v.to_le_bytes()));
        pts.extend(p.rgb);
        pts.extend(p.error.to_le_bytes());
        pts.extend((p.track.len() as u64).to_le_bytes());
        for (i, j) in &p.track {
            pts.extend(i.to_le_bytes());
            pts.extend(j.to_le_bytes());
        }
    }
    [cams, imgs, pts]
}

const BIN: &str = "fuzz.bin";
const TXT: &str = "fuzz.txt";

#[test]
fn colmap_binary_never_panics() {
    let dir = repo_fixture("colmap_tiny/sparse/0");
    let model = colmap::read_model(&dir).unwrap();
    // The binary encoding of the text fixture parses back to the same model.
    let [cams, imgs, pts] = encode_model_bin(&model);
    let p = Path::new(BIN);
    assert_eq!(parse_cameras_bin(&cams, p).unwrap(), model.cameras);
    assert_eq!(parse_images_bin(&imgs, p).unwrap(), model.images);
    assert_eq!(parse_points3d_bin(&pts, p).unwrap(), model.points);
    // The real (small) cameras.bin is a second seed of its parser.
    let real_cams =
        std::fs::read(shared_path("data/scenes/beer_can/sparse/0/cameras.bin")).unwrap();
    Target::new("COLMAP cameras.bin", 5_000)
        .seed(cams)
        .seed(real_cams)
        .run(|b| parse_cameras_bin(b, Path::new(BIN)).is_ok());
    Target::new("COLMAP images.bin", 5_000)
        .seed(imgs)
        .run(|b| parse_images_bin(b, Path::new(BIN)).is_ok());
    Target::new("COLMAP points3D.bin", 5_000)
        .seed(pts)
        .run(|b| parse_points3d_bin(b, Path::new(BIN)).is_ok());
}

#[test]
fn colmap_text_never_panics() {
    let dir = repo_fixture("colmap_tiny/sparse/0");
    let read = |f: &str| std::fs::read(dir.join(f)).unwrap();
    Target::new("COLMAP cameras.txt", 5_000)
        .seed(read("cameras.txt"))
        .mutators(text_mutators())
        .run(|b| parse_cameras_txt(b, Path::new(TXT)).is_ok());
    Target::new("COLMAP images.txt", 5_000)
        .seed(read("images.txt"))
        .mutators(text_mutators())
        .run(|b| parse_images_txt(b, Path::new(TXT)).is_ok());
    Target::new("COLMAP points3D.txt", 5_000)
        .seed(read("points3D.txt"))
        .mutators(text_mutators())
        .run(|b| parse_points3d_txt(b, Path::new(TXT)).is_ok());
}

/// The real COLMAP model of the beer_can capture (2 MB of images, 4,414 points), truncated at a
/// few hundred offsets and mutated.
#[test]
fn real_colmap_binaries_never_panic() {
    let dir = shared_path("data/scenes/beer_can/sparse/0");
    let read = |f: &str| std::fs::read(dir.join(f)).unwrap();
    Target::new("beer_can images.bin", 1_000)
        .seed(read("images.bin"))
        .truncations(Truncations::Spread(150))
        .run(|b| parse_images_bin(b, Path::new(BIN)).is_ok());
    Target::new("beer_can points3D.bin", 1_000)
        .seed(read("points3D.bin"))
        .truncations(Truncations::Spread(150))
        .run(|b| parse_points3d_bin(b, Path::new(BIN)).is_ok());
}

/// A tiny COLMAP dataset on disk (the text fixture and two 64x48 PNGs) whose camera and image
/// files are corrupted: loading the dataset and its images gives `Ok` or `Err`.
#[test]
fn colmap_dataset_loading_never_panics() {
    let root = scratch_dir("fuzz", "colmap-dataset");
    let sparse = root.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::create_dir_all(root.join("images")).unwrap();
    for name in ["a.png", "b.png"] {
        image::RgbImage::from_pixel(64, 48, image::Rgb([9, 99, 199]))
            .save(root.join("images").join(name))
            .unwrap();
    }
    let src = repo_fixture("colmap_tiny/sparse/0");
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::copy(src.join(f), sparse.join(f)).unwrap();
    }
    for file in ["cameras.txt", "images.txt"] {
        let good = std::fs::read(src.join(file)).unwrap();
        let (root, target) = (root.clone(), sparse.join(file));
        Target::new(&format!("COLMAP dataset {file}"), 3_000)
            .seed(good.clone())
            .mutators(text_mutators())
            .truncations(Truncations::Spread(60))
            .run(move |b| load_dataset(&root, &target, b));
        std::fs::write(sparse.join(file), &good).unwrap();
    }
    std::fs::remove_dir_all(&root).unwrap();
}

/// Writes `bytes` to `file` and loads the dataset at `root` with all its images.
fn load_dataset(root: &Path, file: &Path, bytes: &[u8]) -> bool {
    write_input(file, bytes);
    let Ok(d) = Dataset::load(root, &LoadOptions::default()) else {
        return false;
    };
    for i in 0..d.len() {
        let _ = d.load_image(i);
    }
    true
}

#[test]
fn llff_npy_never_panics() {
    let npy = std::fs::read(shared_path("data/scenes/beer_can/poses_bounds.npy")).unwrap();
    // The header (a Python dict literal with the shape) gets the text mutators.
    Target::new("LLFF poses_bounds.npy", 5_000)
        .seed(npy)
        .mutators(text_mutators().iter().map(|m| m.within(0..128)))
        .run(|b| {
            let p = Path::new("fuzz.npy");
            let Ok(a) = parse_npy(b, p) else {
                return false;
            };
            if let Ok(poses) = llff::poses_from_array(&a, p) {
                for pose in poses {
                    let _ = pose.camera.center();
                }
            }
            true
        });
}

#[test]
fn corrupted_images_give_errors() {
    let jpg = std::fs::read(shared_path("data/scenes/beer_can/images_8/0000.jpg")).unwrap();
    let dir = scratch_dir("fuzz", "jpeg");
    let file = dir.join("x.jpg");
    Target::new("JPEG image", 2_000)
        .seed(jpg)
        .truncations(Truncations::Spread(100))
        .run(move |b| {
            write_input(&file, b);
            images::load_rgb(&file, [0.0; 3]).is_ok()
        });
    std::fs::remove_dir_all(&dir).unwrap();
}
