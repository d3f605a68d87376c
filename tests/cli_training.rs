//! `dsgs pretrain-decoder`, `dsgs fit-features` and `dsgs bake` on tiny inputs with the real
//! relu3_1 WCT networks: 32-pixel crops and views and a handful of iterations. Outputs exist
//! and load, the effective configurations are saved, a resumed decoder run is bit-identical to
//! an uninterrupted one, the trained bundle stylizes, and bad input is refused with a message.

mod common;

use std::path::{Path, PathBuf};

use common::{dsgs, fails, ok, save_tiny_bundle, scratch, wct_relu3, Lcg};
use dsgs_testkit::shared_path;
use gaussian::ply::{load_ply, save_ply};
use gaussian::FeatureGaussians;
use nets::NetWeights;
use train::{DecoderTrainConfig, SceneBundle};

/// The real relu3_1 encoder and decoder saved as one canonical weights file.
fn save_networks(dir: &Path) -> PathBuf {
    let (encoder, decoder) = wct_relu3();
    let p = dir.join("nets.safetensors");
    NetWeights {
        encoder: Some(encoder),
        decoder: Some(decoder),
        lifter: None,
    }
    .save(&p)
    .unwrap();
    p
}

/// Writes the named shared images, reduced to at most 48 pixels a side, into `dir`.
fn small_images(dir: &Path, names: &[&str]) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    for n in names {
        let img = image::open(shared_path(&format!("data/{n}"))).unwrap();
        let stem = Path::new(n).file_stem().unwrap().to_string_lossy();
        img.thumbnail(48, 48)
            .to_rgb8()
            .save(dir.join(format!("{stem}.png")))
            .unwrap();
    }
    dir.to_path_buf()
}

fn styles(dir: &Path) -> PathBuf {
    small_images(
        &dir.join("styles"),
        &["styles/mondrian.jpg", "styles/small-set/3.jpg"],
    )
}

#[test]
fn pretrain_decoder_writes_weights_and_config_and_resumes_exactly() {
    let dir = scratch("pretrain-decoder");
    let nets = save_networks(&dir);
    let content = small_images(
        &dir.join("content"),
        &["content/sailboat.jpg", "content/flowers.jpg"],
    );
    let styles = styles(&dir);
    let cfg = dir.join("decoder.toml");
    std::fs::write(&cfg, "eval_pairs = 2\ncheckpoint_interval = 0\n").unwrap();
    let run = |out: &Path, iterations: &str, resume: Option<&Path>| {
        let mut cmd = dsgs();
        cmd.arg("pretrain-decoder")
            .arg("--content")
            .arg(&content)
            .arg("--style")
            .arg(&styles)
            .arg("--weights")
            .arg(&nets)
            .arg("--config")
            .arg(&cfg)
            .args([
                "--iterations",
                iterations,
                "--batch-size",
                "1",
                "--resize",
                "32",
                "--crop",
                "32",
                "--no-progress",
                "-o",
            ])
            .arg(out);
        if let Some(ck) = resume {
            cmd.arg("--resume").arg(ck);
        }
        String::from_utf8_lossy(&ok(&mut cmd).stdout).into_owned()
    };
    // Three iterations straight through.
    let full = dir.join("full");
    let text = run(&full, "3", None);
    println!("{text}");
    assert!(text.contains("2 content and 2 style images"), "{text}");
    assert!(text.contains("iteration 3: evaluation loss"), "{text}");
    let trained = NetWeights::load(&full.join("decoder.safetensors")).unwrap();
    let (_, initial) = wct_relu3();
    let decoder = trained.decoder.expect("a decoder");
    assert_eq!(decoder.in_channels(), initial.in_channels());
    let changed = decoder
        .layers()
        .zip(initial.layers())
        .any(|(a, b)| a.weight != b.weight);
    assert!(changed, "training left the decoder unchanged");
    let saved: DecoderTrainConfig =
        toml::from_str(&std::fs::read_to_string(full.join("config.toml")).unwrap()).unwrap();
    assert_eq!(
        (saved.iterations, saved.batch_size, saved.crop, saved.resize),
        (3, 1, 32, 32)
    );
    assert_eq!((saved.eval_pairs, saved.checkpoint_interval), (2, 0));
    // Two iterations, then one more from the final checkpoint: the same weights, bit for bit
    // (compared as tensors: the order of the file's metadata is not fixed).
    let part = dir.join("part");
    run(&part, "2", None);
    let text = run(&part, "3", Some(&part.join("checkpoint.safetensors")));
    assert!(text.contains("1 iterations"), "{text}");
    let resumed = NetWeights::load(&part.join("decoder.safetensors"))
        .unwrap()
        .decoder
        .unwrap();
    let same = resumed
        .layers()
        .zip(decoder.layers())
        .all(|(a, b)| a.name == b.name && a.weight == b.weight && a.bias == b.bias);
    assert!(
        same && resumed.layers().count() == decoder.layers().count(),
        "the resumed run differs from the uninterrupted one"
    );
    // From scratch: a decoder for the encoder is initialised and trained.
    let scratch_out = dir.join("from-scratch");
    ok(dsgs()
        .arg("pretrain-decoder")
        .arg("--content")
        .arg(&content)
        .arg("--style")
        .arg(&styles)
        .arg("--weights")
        .arg(&nets)
        .arg("--from-scratch")
        .args([
            "--iterations",
            "1",
            "--resize",
            "32",
            "--crop",
            "32",
            "--no-progress",
            "-o",
        ])
        .arg(&scratch_out));
    let w = NetWeights::load(&scratch_out.join("decoder.safetensors")).unwrap();
    assert_eq!(w.decoder.unwrap().in_channels(), initial.in_channels());
    // A missing style folder is named.
    let err = fails(
        dsgs()
            .arg("pretrain-decoder")
            .arg("--content")
            .arg(&content)
            .args(["--style", "no/such/styles", "--weights"])
            .arg(&nets)
            .arg("-o")
            .arg(dir.join("bad")),
    );
    assert!(err.contains("no/such/styles"), "{err}");
    // An encoder without a starting decoder is refused before anything is written.
    let err = fails(
        dsgs()
            .arg("pretrain-decoder")
            .arg("--content")
            .arg(&content)
            .arg("--style")
            .arg(&styles)
            .arg("--encoder")
            .arg(shared_path(
                "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
            ))
            .arg("-o")
            .arg(dir.join("bad")),
    );
    assert!(err.contains("--from-scratch"), "{err}");
    assert!(!dir.join("bad").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// Writes a NeRF-synthetic dataset of `n` 32x32 views on a circle of radius 3 around the
/// origin (OpenGL camera-to-world poses, world up +z) of an opaque coloured disc.
fn write_dataset(dir: &Path, n: usize) {
    std::fs::create_dir_all(dir.join("train")).unwrap();
    let norm = |v: [f64; 3]| {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|x| x / l)
    };
    let mut frames = Vec::new();
    for i in 0..n {
        let a = i as f64 / n as f64 * std::f64::consts::TAU;
        let eye = [3.0 * a.cos(), 3.0 * a.sin(), 1.0];
        let z = norm(eye);
        let x = norm([-z[1], z[0], 0.0]); // up x z with up = +z
        let y = [
            z[1] * x[2] - z[2] * x[1],
            z[2] * x[0] - z[0] * x[2],
            z[0] * x[1] - z[1] * x[0],
        ];
        let m: Vec<Vec<f64>> = (0..3)
            .map(|r| vec![x[r], y[r], z[r], eye[r]])
            .chain([vec![0.0, 0.0, 0.0, 1.0]])
            .collect();
        frames.push(
            serde_json::json!({"file_path": format!("./train/r_{i}"), "transform_matrix": m}),
        );
        let img = image::RgbaImage::from_fn(32, 32, |px, py| {
            let (dx, dy) = (px as f32 - 15.5, py as f32 - 15.5);
            let alpha = if dx * dx + dy * dy < 100.0 { 255 } else { 0 };
            image::Rgba([
                (128.0 + 8.0 * dx) as u8,
                (128.0 + 8.0 * dy) as u8,
                (40 * (i % 6)) as u8,
                alpha,
            ])
        });
        img.save(dir.join(format!("train/r_{i}.png"))).unwrap();
    }
    let json = serde_json::json!({"camera_angle_x": 0.69, "frames": frames});
    std::fs::write(dir.join("transforms_train.json"), json.to_string()).unwrap();
}

/// `n` small random Gaussians (SH degree 0) in the cube `[-0.6, 0.6]^3`.
fn random_geometry(n: usize) -> FeatureGaussians<f32> {
    let mut rng = Lcg(3);
    let mut u = move |lo: f32, hi: f32| lo + (hi - lo) * rng.uniform();
    let mut g = FeatureGaussians {
        means: Vec::new(),
        log_scales: Vec::new(),
        quats: Vec::new(),
        opacity_logits: Vec::new(),
        sh_degree: 0,
        sh: Vec::new(),
        feature_dim: 0,
        features: Vec::new(),
    };
    for _ in 0..n {
        g.means.push([u(-0.6, 0.6), u(-0.6, 0.6), u(-0.6, 0.6)]);
        g.log_scales
            .push([u(-3.5, -2.5), u(-3.5, -2.5), u(-3.5, -2.5)]);
        g.quats
            .push([1.0, u(-0.3, 0.3), u(-0.3, 0.3), u(-0.3, 0.3)]);
        g.opacity_logits.push(u(-1.0, 2.0));
        g.sh.push([u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)]);
    }
    g
}

#[test]
fn fit_features_writes_a_bundle_that_stylizes() {
    let dir = scratch("fit-features");
    let nets = save_networks(&dir);
    let styles = styles(&dir);
    let data = dir.join("data");
    write_dataset(&data, 6);
    let ply = dir.join("geometry.ply");
    save_ply(&ply, &random_geometry(400)).unwrap();
    let out = dir.join("out");
    let text = ok(dsgs()
        .arg("fit-features")
        .arg("--geometry")
        .arg(&ply)
        .arg("--dataset")
        .arg(&data)
        .arg("--style")
        .arg(&styles)
        .arg("--weights")
        .arg(&nets)
        .args([
            "--iterations",
            "3",
            "--feature-dim",
            "4",
            "--crop",
            "8",
            "--white",
            "--no-progress",
            "-o",
        ])
        .arg(&out))
    .stdout;
    let text = String::from_utf8_lossy(&text);
    println!("{text}");
    // Every 8th view is held out: 5 of the 6 are trained on.
    assert!(
        text.contains("400 Gaussians, 5 training views, 2 style images, 4-d features"),
        "{text}"
    );
    let bundle = SceneBundle::load(&out.join("bundle")).unwrap();
    assert_eq!(bundle.scene.len(), 400);
    assert_eq!(bundle.info.feature_dim, 4);
    assert_eq!(bundle.info.background, [1.0; 3]);
    assert_eq!(bundle.info.cameras.len(), 6);
    assert_eq!(bundle.info.cameras.iter().filter(|c| c.held_out).count(), 1);
    assert!(out.join("checkpoint.safetensors").is_file());
    let saved = std::fs::read_to_string(out.join("config.toml")).unwrap();
    for key in ["iterations = 3", "feature_dim = 4", "crop = 8"] {
        assert!(saved.contains(key), "config.toml lacks `{key}`:\n{saved}");
    }
    // One more iteration from the final checkpoint (with the saved configuration) gives the
    // features and lifter of four iterations straight through, bit for bit.
    let features_run = |out: &Path, extra: &[&str]| {
        let text = ok(dsgs()
            .arg("fit-features")
            .arg("--geometry")
            .arg(&ply)
            .arg("--dataset")
            .arg(&data)
            .arg("--style")
            .arg(&styles)
            .arg("--weights")
            .arg(&nets)
            .args(extra)
            .arg("-o")
            .arg(out))
        .stdout;
        String::from_utf8_lossy(&text).into_owned()
    };
    let text = features_run(
        &out,
        &[
            "--iterations",
            "4",
            "--resume",
            out.join("checkpoint.safetensors").to_str().unwrap(),
        ],
    );
    assert!(text.contains("1 iterations"), "{text}");
    let straight = dir.join("straight");
    features_run(
        &straight,
        &[
            "--config",
            out.join("config.toml").to_str().unwrap(),
            "--iterations",
            "4",
        ],
    );
    let a = SceneBundle::load(&out.join("bundle")).unwrap();
    let b = SceneBundle::load(&straight.join("bundle")).unwrap();
    assert_eq!(a.scene.features, b.scene.features);
    assert_eq!(a.lifter.layer().weight, b.lifter.layer().weight);
    assert_eq!(a.lifter.layer().bias, b.lifter.layer().bias);
    assert_ne!(a.scene.features, bundle.scene.features);
    // The bundle is what `dsgs stylize` reads.
    let frames = dir.join("frames");
    ok(dsgs()
        .arg("stylize")
        .arg(out.join("bundle"))
        .arg("--style")
        .arg(styles.join("mondrian.png"))
        .args(["--cameras", "dataset", "--frames", "2", "-o"])
        .arg(&frames));
    assert_eq!(
        common::size_of(&frames.join("mondrian/frame_0000.png")),
        (32, 32)
    );
    // A missing geometry file is named.
    let err = fails(
        dsgs()
            .args([
                "fit-features",
                "--geometry",
                "no/such/geometry.ply",
                "--dataset",
            ])
            .arg(&data)
            .arg("--style")
            .arg(&styles)
            .arg("--weights")
            .arg(&nets)
            .arg("-o")
            .arg(dir.join("bad")),
    );
    assert!(err.contains("no/such/geometry.ply"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bake_writes_a_plain_ply_and_a_report() {
    let dir = scratch("bake");
    let bundle = save_tiny_bundle(&dir);
    let style = shared_path("data/styles/mondrian.jpg");
    let cfg = dir.join("bake.toml");
    std::fs::write(
        &cfg,
        "target_views = 4\ninterpolated_per_pair = 1\nheld_out = 2\n",
    )
    .unwrap();
    let out = dir.join("out/baked.ply");
    let text = ok(dsgs()
        .arg("bake")
        .arg(&bundle)
        .arg("--style")
        .arg(&style)
        .arg("--config")
        .arg(&cfg)
        .args([
            "--style-size",
            "64",
            "--iterations",
            "8",
            "--sh-degree",
            "1",
            "--no-progress",
            "-o",
        ])
        .arg(&out))
    .stdout;
    let text = String::from_utf8_lossy(&text);
    println!("{text}");
    assert!(
        text.contains("4 training and 2 held-out target views, 8 iterations"),
        "{text}"
    );
    assert!(text.contains("held-out PSNR: baked "), "{text}");
    let baked = load_ply(&out).unwrap();
    assert_eq!(baked.len(), 1500);
    assert_eq!((baked.sh_degree, baked.feature_dim), (3, 0));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/baked.json")).unwrap())
            .unwrap();
    assert_eq!(report["iterations"], 8);
    assert_eq!(report["config"]["sh_degree"], 1);
    assert_eq!(report["config"]["target_views"], 4);
    for key in ["held_out_psnr", "unbaked_held_out_psnr", "train_psnr"] {
        let v = report[key].as_f64().unwrap_or(f64::NAN);
        assert!(v.is_finite() && v > 0.0, "{key} = {}", report[key]);
    }
    // The baked scene renders from the bundle's own held-out cameras (`--dataset BUNDLE`):
    // cameras 0 and 8 of the 16 64x64 orbit cameras.
    let frames = dir.join("baked_test");
    ok(dsgs()
        .args(["render", "--scene"])
        .arg(&out)
        .arg("--dataset")
        .arg(&bundle)
        .args(["--cameras", "test", "-o"])
        .arg(&frames));
    let mut names: Vec<_> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "png"))
        .collect();
    names.sort();
    assert_eq!(names.len(), 2, "{names:?}");
    for f in &names {
        assert_eq!(common::size_of(f), (64, 64), "{}", f.display());
        let px = image::open(f).unwrap().to_rgb8();
        let first = *px.get_pixel(0, 0);
        assert!(px.pixels().any(|p| *p != first), "{} is blank", f.display());
    }
    // Two styles without mixture weights cannot be baked into one scene.
    let err = fails(
        dsgs()
            .arg("bake")
            .arg(&bundle)
            .arg("--style")
            .arg(&style)
            .arg("--style")
            .arg(&style)
            .arg("-o")
            .arg(dir.join("two.ply")),
    );
    assert!(err.contains("--weights"), "{err}");
    // A directory that is not a bundle is named.
    let not_bundle = dir.join("not-a-bundle");
    std::fs::create_dir_all(&not_bundle).unwrap();
    let err = fails(
        dsgs()
            .arg("bake")
            .arg(&not_bundle)
            .arg("--style")
            .arg(&style)
            .arg("-o")
            .arg(dir.join("x.ply")),
    );
    assert!(err.contains("not-a-bundle"), "{err}");
    assert!(!dir.join("x.ply").exists());
    std::fs::remove_dir_all(&dir).ok();
}
