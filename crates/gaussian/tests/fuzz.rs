//! Robustness: truncated and corrupted PLY, JSON, COLMAP (binary and text), `.npy` and image
//! inputs must produce `Ok` or `Err`, never a panic, a hang or an absurd allocation.
//!
//! The loops are deterministic (a fixed-seed xorshift generator): every input is truncated at
//! every byte offset (or, for the large real COLMAP files, at a few hundred offsets spread over
//! the file) and mutated a few thousand times by overwriting one to four random bytes. Whatever
//! loads must also survive the next stage (saving a PLY, building cameras from poses).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use dsgs_testkit::{repo_fixture, shared_path};
use gaussian::dataset::colmap::{
    self, parse_cameras_bin, parse_cameras_txt, parse_images_bin, parse_images_txt,
    parse_points3d_bin, parse_points3d_txt, ColmapModel,
};
use gaussian::dataset::nerf::{frame_matrix, parse_transforms};
use gaussian::dataset::{images, llff, Dataset, LoadOptions};
use gaussian::npy::parse_npy;
use gaussian::ply::{encode_ply, load_ply, parse_ply, ExtraProperty, ScalarType};
use gaussian::Camera;

/// xorshift64*: a small deterministic generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// Runs `f` on the truncations of `input` at `offsets` and on `mutations` corrupted copies,
/// reporting the offending input if `f` panics. Returns how many inputs were accepted.
fn hammer(
    what: &str,
    input: &[u8],
    offsets: impl IntoIterator<Item = usize>,
    mutations: usize,
    seed: u64,
    f: &dyn Fn(&[u8]),
) -> usize {
    let accepted = std::cell::Cell::new(0usize);
    let run = |desc: &dyn Fn() -> String, bytes: &[u8]| {
        if catch_unwind(AssertUnwindSafe(|| f(bytes))).is_err() {
            panic!("{what}: panicked on {}", desc());
        }
        accepted.set(accepted.get() + 1);
    };
    for cut in offsets {
        run(
            &|| format!("truncation at byte {cut}"),
            &input[..cut.min(input.len())],
        );
    }
    let mut rng = Rng(seed);
    for m in 0..mutations {
        let mut bytes = input.to_vec();
        let mut changes = Vec::new();
        for _ in 0..1 + rng.below(4) {
            let at = rng.below(bytes.len());
            let v = rng.next() as u8;
            bytes[at] = v;
            changes.push((at, v));
        }
        run(
            &|| format!("mutation {m}: (offset, new byte) {changes:?}"),
            &bytes,
        );
    }
    accepted.get()
}

fn all_offsets(input: &[u8]) -> std::ops::Range<usize> {
    0..input.len()
}

/// `count` offsets spread over the input.
fn spread(input: &[u8], count: usize) -> Vec<usize> {
    (0..count).map(|i| i * input.len() / count).collect()
}

/// What a successfully parsed PLY must allow: saving it and reading the same scene back.
fn check_ply(bytes: &[u8]) {
    if let Ok(s) = parse_ply(bytes, Path::new("fuzz.ply")) {
        let saved = encode_ply(&s.gaussians, &s.extras, Path::new("fuzz.ply"))
            .expect("a loaded scene must save");
        let back = parse_ply(&saved, Path::new("saved.ply")).expect("a saved scene must load");
        assert_eq!(back, s);
    }
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
    for (name, input, seed) in [
        ("binary LE PLY", &binary, 1),
        ("ASCII PLY", &ascii, 2),
        ("binary BE PLY", &big_endian, 3),
    ] {
        let ok = hammer(name, input, all_offsets(input), 4000, seed, &check_ply);
        assert!(ok > 0);
        // The untouched file parses.
        assert!(parse_ply(input, Path::new("x")).is_ok(), "{name}");
    }
}

#[test]
fn nerf_json_never_panics() {
    let text =
        std::fs::read_to_string(shared_path("data/scenes/lego/transforms_train.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["frames"].as_array_mut().unwrap().truncate(3);
    let small = serde_json::to_string_pretty(&v).unwrap().into_bytes();
    hammer(
        "transforms JSON",
        &small,
        all_offsets(&small),
        4000,
        4,
        &|bytes| {
            let text = String::from_utf8_lossy(bytes);
            if let Ok(t) = parse_transforms(&text, Path::new("transforms.json")) {
                for f in &t.frames {
                    let m = frame_matrix(f).expect("checked by parse_transforms");
                    let cam = Camera::from_opengl_world_from_camera(t.intrinsics(800, 800), m);
                    let _ = cam.project_point(glam::DVec3::ZERO);
                }
            }
        },
    );
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

#[test]
fn colmap_text_and_binary_never_panic() {
    let dir = repo_fixture("colmap_tiny/sparse/0");
    let model = colmap::read_model(&dir).unwrap();
    // The binary encoding of the text fixture parses back to the same model.
    let [cams, imgs, pts] = encode_model_bin(&model);
    let p = Path::new("fuzz.bin");
    assert_eq!(parse_cameras_bin(&cams, p).unwrap(), model.cameras);
    assert_eq!(parse_images_bin(&imgs, p).unwrap(), model.images);
    assert_eq!(parse_points3d_bin(&pts, p).unwrap(), model.points);

    hammer("cameras.bin", &cams, all_offsets(&cams), 3000, 5, &|b| {
        let _ = parse_cameras_bin(b, p);
    });
    hammer("images.bin", &imgs, all_offsets(&imgs), 3000, 6, &|b| {
        let _ = parse_images_bin(b, p);
    });
    hammer("points3D.bin", &pts, all_offsets(&pts), 3000, 7, &|b| {
        let _ = parse_points3d_bin(b, p);
    });
    for (file, seed) in [("cameras.txt", 8), ("images.txt", 9), ("points3D.txt", 10)] {
        let text = std::fs::read(dir.join(file)).unwrap();
        hammer(file, &text, all_offsets(&text), 3000, seed, &|b| {
            let _ = parse_cameras_txt(b, p);
            let _ = parse_images_txt(b, p);
            let _ = parse_points3d_txt(b, p);
        });
    }
}

#[test]
fn real_colmap_binaries_never_panic() {
    let dir = shared_path("data/scenes/beer_can/sparse/0");
    let p = Path::new("fuzz.bin");
    let cams = std::fs::read(dir.join("cameras.bin")).unwrap();
    hammer(
        "beer_can cameras.bin",
        &cams,
        all_offsets(&cams),
        1000,
        11,
        &|b| {
            let _ = parse_cameras_bin(b, p);
        },
    );
    let imgs = std::fs::read(dir.join("images.bin")).unwrap();
    hammer(
        "beer_can images.bin",
        &imgs,
        spread(&imgs, 150),
        150,
        12,
        &|b| {
            let _ = parse_images_bin(b, p);
        },
    );
    let pts = std::fs::read(dir.join("points3D.bin")).unwrap();
    hammer(
        "beer_can points3D.bin",
        &pts,
        spread(&pts, 150),
        150,
        13,
        &|b| {
            let _ = parse_points3d_bin(b, p);
        },
    );
}

/// Corrupted camera and image files of a whole (tiny) COLMAP dataset on disk.
#[test]
fn colmap_dataset_loading_never_panics() {
    let root = std::env::temp_dir().join(format!("dsgs-fuzz-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
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
    assert!(Dataset::load(&root, &LoadOptions::default()).is_ok());
    for (file, seed) in [("cameras.txt", 14), ("images.txt", 15)] {
        let good = std::fs::read(src.join(file)).unwrap();
        hammer(file, &good, spread(&good, 60), 300, seed, &|b| {
            std::fs::write(sparse.join(file), b).unwrap();
            if let Ok(d) = Dataset::load(&root, &LoadOptions::default()) {
                for i in 0..d.len() {
                    let _ = d.load_image(i);
                }
            }
        });
        std::fs::write(sparse.join(file), &good).unwrap();
    }
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn npy_never_panics() {
    let npy = std::fs::read(shared_path("data/scenes/beer_can/poses_bounds.npy")).unwrap();
    let p = Path::new("fuzz.npy");
    hammer(
        "poses_bounds.npy",
        &npy,
        all_offsets(&npy),
        3000,
        16,
        &|b| {
            if let Ok(a) = parse_npy(b, p) {
                if let Ok(poses) = llff::poses_from_array(&a, p) {
                    for pose in poses {
                        let _ = pose.camera.center();
                    }
                }
            }
        },
    );
}

#[test]
fn corrupted_images_give_errors() {
    let jpg = std::fs::read(shared_path("data/scenes/beer_can/images_8/0000.jpg")).unwrap();
    let dir = std::env::temp_dir().join(format!("dsgs-fuzz-img-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("x.jpg");
    hammer("JPEG", &jpg, spread(&jpg, 100), 100, 17, &|b| {
        std::fs::write(&file, b).unwrap();
        let _ = images::load_rgb(&file, [0.0; 3]);
    });
    std::fs::remove_dir_all(&dir).unwrap();
}
