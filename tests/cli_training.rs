//! `dsgs pretrain-decoder`, `dsgs fit-features` and `dsgs bake` on tiny inputs with the real
//! relu3_1 WCT networks: 32-pixel crops and views and a handful of iterations. Outputs exist
//! and load, the effective configurations are saved, a resumed decoder run is bit-identical to
//! an uninterrupted one, the trained bundle stylizes, and bad input is refused with a message.
//! Each command stopped by SIGTERM mid-run resumes to the uninterrupted run's output, byte for
//! byte.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

#[cfg(unix)]
use common::{assert_same_files, stop_and_resume};
use common::{dsgs, fails, ok, save_tiny_bundle, scratch, wct_relu3, Lcg};
use dsgs_testkit::shared_path;
use gaussian::ply::{load_ply, save_ply};
use gaussian::FeatureGaussians;
use nets::NetWeights;
use runtime::SceneBundle;
use train::DecoderTrainConfig;

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

/// A training command on tiny inputs: `dsgs COMMAND`, its inputs (named by their flag, or by
/// their usage name when positional) and its fixed arguments.
struct Tiny {
    command: &'static str,
    inputs: Vec<(&'static str, PathBuf)>,
    args: &'static [&'static str],
}

impl Tiny {
    /// The input named `name`.
    fn path(&self, name: &str) -> &Path {
        let (_, p) = self.inputs.iter().find(|(n, _)| *n == name).unwrap();
        p
    }

    /// The command of `iterations` without progress bars, with the fixed and the further
    /// arguments `args`, writing to `out`.
    fn command(&self, out: &Path, iterations: u64, args: &[&str]) -> Command {
        let mut cmd = self.inputs_only(out, iterations, args);
        cmd.args(self.args);
        cmd
    }

    /// The command without the fixed arguments (for a run that takes them from a saved
    /// configuration).
    fn inputs_only(&self, out: &Path, iterations: u64, args: &[&str]) -> Command {
        let mut cmd = dsgs();
        cmd.arg(self.command);
        for (name, path) in &self.inputs {
            if name.starts_with('-') {
                cmd.arg(name);
            }
            cmd.arg(path);
        }
        cmd.arg("--iterations")
            .arg(iterations.to_string())
            .args(["--no-progress", "-o"])
            .arg(out)
            .args(args);
        cmd
    }

    /// [`stop_and_resume`] of `iterations` with the further arguments `args`, writing to
    /// `output` below `dir/full` and `dir/cut`: returns those two outputs.
    #[cfg(unix)]
    fn stop_and_resume(
        &self,
        dir: &Path,
        output: &str,
        iterations: u64,
        args: &[&str],
        stopped: impl FnOnce(&Path, &str),
    ) -> (PathBuf, PathBuf) {
        let (full, cut) = (dir.join("full").join(output), dir.join("cut").join(output));
        let command = |out: &Path| self.command(out, iterations, args);
        stop_and_resume(iterations, &full, &cut, command, stopped);
        (full, cut)
    }
}

/// `pretrain-decoder` of the relu3_1 networks on two content and two style images, with a
/// configuration of two evaluation pairs and no periodic checkpoints, on 32-pixel crops, one
/// pair a batch.
fn tiny_pretrain(dir: &Path) -> Tiny {
    let config = dir.join("decoder.toml");
    std::fs::write(&config, "eval_pairs = 2\ncheckpoint_interval = 0\n").unwrap();
    let content = small_images(
        &dir.join("content"),
        &["content/sailboat.jpg", "content/flowers.jpg"],
    );
    Tiny {
        command: "pretrain-decoder",
        inputs: vec![
            ("--content", content),
            ("--style", styles(dir)),
            ("--weights", save_networks(dir)),
            ("--config", config),
        ],
        args: &["--batch-size", "1", "--resize", "32", "--crop", "32"],
    }
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn pretrain_decoder_writes_weights_and_config_and_resumes_exactly() {
    let dir = scratch("pretrain-decoder");
    let inputs = tiny_pretrain(&dir);
    let [nets, content, styles] = ["--weights", "--content", "--style"].map(|n| inputs.path(n));
    let run = |out: &Path, iterations: u64, resume: Option<&Path>| {
        let mut cmd = inputs.command(out, iterations, &[]);
        if let Some(ck) = resume {
            cmd.arg("--resume").arg(ck);
        }
        String::from_utf8_lossy(&ok(&mut cmd).stdout).into_owned()
    };
    // Three iterations straight through.
    let full = dir.join("full");
    let text = run(&full, 3, None);
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
    run(&part, 2, None);
    let text = run(&part, 3, Some(&part.join("checkpoint.safetensors")));
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
        .arg(content)
        .arg("--style")
        .arg(styles)
        .arg("--weights")
        .arg(nets)
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
            .arg(content)
            .args(["--style", "no/such/styles", "--weights"])
            .arg(nets)
            .arg("-o")
            .arg(dir.join("bad")),
    );
    assert!(err.contains("no/such/styles"), "{err}");
    // An encoder without a starting decoder is refused before anything is written.
    let err = fails(
        dsgs()
            .arg("pretrain-decoder")
            .arg("--content")
            .arg(content)
            .arg("--style")
            .arg(styles)
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

/// `fit-features` of 4-d features for 400 random Gaussians, trained on 8-pixel crops of a
/// dataset of six 32x32 white-background views, with the relu3_1 networks and two styles.
fn tiny_features(dir: &Path) -> Tiny {
    let data = dir.join("data");
    write_dataset(&data, 6);
    let geometry = dir.join("geometry.ply");
    save_ply(&geometry, &random_geometry(400)).unwrap();
    Tiny {
        command: "fit-features",
        inputs: vec![
            ("--geometry", geometry),
            ("--dataset", data),
            ("--style", styles(dir)),
            ("--weights", save_networks(dir)),
        ],
        args: &["--feature-dim", "4", "--crop", "8", "--white"],
    }
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn fit_features_writes_a_bundle_that_stylizes() {
    let dir = scratch("fit-features");
    let inputs = tiny_features(&dir);
    let [nets, styles, data] = ["--weights", "--style", "--dataset"].map(|n| inputs.path(n));
    let out = dir.join("out");
    let text = ok(&mut inputs.command(&out, 3, &[])).stdout;
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
    // The resumed run reads the views' and styles' encodings back from the first run's cache
    // (the straight run has none), so the bit-identity below also covers the cache.
    let features_run = |out: &Path, extra: &[&str]| {
        let o = ok(&mut inputs.inputs_only(out, 4, extra));
        let [stdout, stderr] =
            [o.stdout, o.stderr].map(|b| String::from_utf8_lossy(&b).into_owned());
        (stdout, stderr)
    };
    let (text, log) = features_run(
        &out,
        &[
            "--resume",
            out.join("checkpoint.safetensors").to_str().unwrap(),
        ],
    );
    assert!(text.contains("1 iterations"), "{text}");
    assert!(
        log.contains("5 views and 2 style images encoded") && log.contains("(7 reused from"),
        "{log}"
    );
    // The straight run keeps no cache: it encodes everything and leaves no OUT/encodings.
    let straight = dir.join("straight");
    let (_, log) = features_run(
        &straight,
        &[
            "--config",
            out.join("config.toml").to_str().unwrap(),
            "--no-encoding-cache",
        ],
    );
    assert!(
        log.contains("5 views and 2 style images encoded") && !log.contains("reused"),
        "{log}"
    );
    assert!(out.join("encodings").is_dir());
    assert!(!straight.join("encodings").exists());
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
            .arg(data)
            .arg("--style")
            .arg(styles)
            .arg("--weights")
            .arg(nets)
            .arg("-o")
            .arg(dir.join("bad")),
    );
    assert!(err.contains("no/such/geometry.ply"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Writes `dir/NAME`, a copy of a shared PNG cut short: its header is sound, so only decoding
/// its pixels finds the problem.
fn cut_png(dir: &Path, name: &str) -> PathBuf {
    let png = std::fs::read(shared_path("data/styles/sketch.png")).unwrap();
    let p = dir.join(name);
    std::fs::write(&p, &png[..png.len() / 3]).unwrap();
    p
}

#[test]
fn a_bad_image_stops_fit_features_before_anything_is_written() {
    let dir = scratch("fit-features-bad-image");
    let inputs = tiny_features(&dir);
    cut_png(inputs.path("--style"), "cut.png");
    let out = dir.join("out");
    let err = fails(&mut inputs.command(&out, 3, &[]));
    assert!(err.contains("cut.png"), "{err}");
    assert!(!out.exists(), "the failed run wrote into {}", out.display());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_bad_image_stops_pretrain_decoder_before_anything_is_written() {
    let dir = scratch("pretrain-decoder-bad-image");
    let inputs = tiny_pretrain(&dir);
    for (folder, name) in [
        ("--content", "cut_content.png"),
        ("--style", "cut_style.png"),
    ] {
        let bad = cut_png(inputs.path(folder), name);
        let out = dir.join("out");
        let err = fails(&mut inputs.command(&out, 3, &[]));
        assert!(err.contains(name), "{err}");
        assert!(!out.exists(), "the failed run wrote into {}", out.display());
        std::fs::remove_file(bad).unwrap();
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `bake` of the tiny bundle to SH degree 1 with the Mondrian style at 64 pixels, on four
/// training and two held-out target views.
fn tiny_bake(dir: &Path) -> Tiny {
    let config = dir.join("bake.toml");
    std::fs::write(
        &config,
        "target_views = 4\ninterpolated_per_pair = 1\nheld_out = 2\n",
    )
    .unwrap();
    Tiny {
        command: "bake",
        inputs: vec![
            ("BUNDLE", save_tiny_bundle(dir)),
            ("--style", shared_path("data/styles/mondrian.jpg")),
            ("--config", config),
        ],
        args: &["--style-size", "64", "--sh-degree", "1"],
    }
}

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn bake_writes_a_plain_ply_and_a_report() {
    let dir = scratch("bake");
    let inputs = tiny_bake(&dir);
    let (bundle, style) = (inputs.path("BUNDLE"), inputs.path("--style"));
    let out = dir.join("out/baked.ply");
    let text = ok(&mut inputs.command(&out, 8, &[])).stdout;
    let text = String::from_utf8_lossy(&text);
    println!("{text}");
    assert!(
        text.contains("4 training and 2 held-out target views"),
        "{text}"
    );
    assert!(text.contains("\n8 iterations in "), "{text}");
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
        .arg("render")
        .arg(&out)
        .arg("--dataset")
        .arg(bundle)
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
            .arg(bundle)
            .arg("--style")
            .arg(style)
            .arg("--style")
            .arg(style)
            .arg("-o")
            .arg(dir.join("two.ply")),
    );
    assert!(err.contains("--mix"), "{err}");
    // A directory that is not a bundle is named.
    let not_bundle = dir.join("not-a-bundle");
    std::fs::create_dir_all(&not_bundle).unwrap();
    let err = fails(
        dsgs()
            .arg("bake")
            .arg(&not_bundle)
            .arg("--style")
            .arg(style)
            .arg("-o")
            .arg(dir.join("x.ply")),
    );
    assert!(err.contains("not-a-bundle"), "{err}");
    assert!(!dir.join("x.ply").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// A SIGTERM in the middle of a decoder run with no periodic checkpoints: the checkpoint the
/// stop writes resumes to the uninterrupted run's decoder, byte for byte.
#[cfg(unix)]
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn pretrain_decoder_stopped_by_sigterm_resumes_exactly() {
    let dir = scratch("pretrain-decoder-sigterm");
    let no_periodic_checkpoints = ["--checkpoint-every", "0"];
    let (full, cut) = tiny_pretrain(&dir).stop_and_resume(
        &dir,
        "out",
        300,
        &no_periodic_checkpoints,
        |checkpoint, log| {
            assert!(
                checkpoint.ends_with("cut/out/checkpoint.safetensors"),
                "{log}"
            )
        },
    );
    let decoder = |out: &Path| std::fs::read(out.join("decoder.safetensors")).unwrap();
    assert!(
        decoder(&full) == decoder(&cut),
        "the resumed decoder differs from the uninterrupted one"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A SIGTERM in the middle of a feature fit: resuming from the checkpoint it writes gives the
/// uninterrupted run's bundle, every file byte for byte.
#[cfg(unix)]
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn fit_features_stopped_by_sigterm_resumes_exactly() {
    let dir = scratch("fit-features-sigterm");
    let (full, cut) = tiny_features(&dir).stop_and_resume(&dir, "out", 500, &[], |_, _| {});
    assert_same_files(&full.join("bundle"), &cut.join("bundle"));
    std::fs::remove_dir_all(&dir).ok();
}

/// A SIGTERM in the middle of a bake: no scene is written, the checkpoint goes beside the
/// output, and resuming from it gives the uninterrupted bake's scene, byte for byte, and a
/// report.
#[cfg(unix)]
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn bake_stopped_by_sigterm_resumes_exactly() {
    let dir = scratch("bake-sigterm");
    let (full, cut) =
        tiny_bake(&dir).stop_and_resume(&dir, "baked.ply", 1000, &[], |checkpoint, log| {
            let beside = dir.join("cut/baked.checkpoint/checkpoint.safetensors");
            assert_eq!(checkpoint, beside, "{log}");
            let scene = dir.join("cut/baked.ply");
            assert!(!scene.exists(), "a stopped bake wrote {}", scene.display());
        });
    assert!(
        std::fs::read(&full).unwrap() == std::fs::read(&cut).unwrap(),
        "the resumed bake differs from the uninterrupted one"
    );
    assert!(cut.with_extension("json").is_file());
    std::fs::remove_dir_all(&dir).ok();
}

/// The paper's ablations as `fit-features` switches, end to end on the tiny scene: each
/// trains, records its design in the bundle, stylizes and evaluates, and resumes bit for bit;
/// the combinations that cannot work are refused with the reason.
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn fit_features_ablation_switches() {
    let dir = scratch("fit-features-ablations");
    let inputs = tiny_features(&dir);
    let styles = inputs.path("--style").to_path_buf();
    let (_, pretrained) = wct_relu3();
    let cases: [(&str, &[&str]); 3] = [
        ("scratch", &["--decoder-mode", "scratch"]),
        ("mlp", &["--decoder-mode", "mlp", "--variant", "fullres"]),
        ("after", &["--normalize", "after-raster"]),
    ];
    for (name, args) in cases {
        let out = dir.join(name);
        ok(&mut inputs.command(&out, 3, args));
        let bundle = SceneBundle::load(&out.join("bundle")).unwrap();
        let info = &bundle.info;
        match name {
            "scratch" => {
                assert_eq!(info.decoder_mode, train::DecoderMode::Scratch);
                // The mirror CNN of the pre-trained decoder, with weights of its own.
                let shapes = |d: &nets::Decoder| {
                    d.layers()
                        .map(|l| l.weight.shape().to_vec())
                        .collect::<Vec<_>>()
                };
                assert_eq!(shapes(&bundle.decoder), shapes(&pretrained));
                for (a, b) in bundle.decoder.layers().zip(pretrained.layers()) {
                    assert_ne!(a.weight, b.weight, "{}", a.name);
                }
            }
            "mlp" => {
                assert_eq!(info.decoder_mode, train::DecoderMode::Mlp);
                assert!(bundle.decoder.is_pointwise());
                assert_eq!(bundle.decoder.layers().count(), 3);
            }
            _ => {
                assert_eq!(info.normalize, train::FeatureNorm::AfterRaster);
                assert_eq!(info.decoder_mode, train::DecoderMode::Pretrained);
                for (a, b) in bundle.decoder.layers().zip(pretrained.layers()) {
                    assert_eq!(a.weight, b.weight, "{}", a.name);
                }
            }
        }
        // One more iteration from the checkpoint equals four straight through, decoder
        // included.
        let checkpoint = out.join("checkpoint.safetensors");
        ok(&mut inputs.command(
            &out,
            4,
            &[&["--resume", checkpoint.to_str().unwrap()], args].concat(),
        ));
        let straight = dir.join(format!("{name}-straight"));
        ok(&mut inputs.command(&straight, 4, args));
        let a = SceneBundle::load(&out.join("bundle")).unwrap();
        let b = SceneBundle::load(&straight.join("bundle")).unwrap();
        assert_eq!(
            a.fingerprint(),
            b.fingerprint(),
            "{name}: resumed run differs"
        );
        assert_eq!(a.scene.features, b.scene.features);
        assert_ne!(a.fingerprint(), bundle.fingerprint());
        // The bundle stylizes and evaluates.
        let frames = dir.join(format!("{name}-frames"));
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
        let report = dir.join(format!("{name}-eval.json"));
        ok(dsgs()
            .arg("eval")
            .arg(out.join("bundle"))
            .arg("--style")
            .arg(styles.join("mondrian.png"))
            .args([
                "--frames",
                "3",
                "--width",
                "32",
                "--height",
                "32",
                "--no-progress",
                "-o",
            ])
            .arg(&report));
        let text = std::fs::read_to_string(&report).unwrap();
        assert!(text.contains("mondrian"), "{text}");
    }
    // Resuming keeps the run's design (from its saved configuration); asking for another is
    // refused, naming both.
    let checkpoint = dir.join("scratch/checkpoint.safetensors");
    let err = fails(&mut inputs.command(
        &dir.join("scratch"),
        5,
        &[
            "--resume",
            checkpoint.to_str().unwrap(),
            "--decoder-mode",
            "pretrained",
        ],
    ));
    assert!(
        err.contains("decoder_mode") && err.contains("scratch") && err.contains("pretrained"),
        "{err}"
    );
    // An MLP decoder needs fullres networks.
    let err = fails(&mut inputs.command(&dir.join("bad"), 3, &["--decoder-mode", "mlp"]));
    assert!(err.contains("fullres"), "{err}");
    assert!(!dir.join("bad").join("bundle").exists());
    // A decoder trained with the features cannot be replaced at stylization.
    let weights = inputs.path("--weights");
    let err = fails(
        dsgs()
            .arg("stylize")
            .arg(dir.join("scratch/bundle"))
            .arg("--style")
            .arg(styles.join("mondrian.png"))
            .arg("--decoder")
            .arg(weights)
            .arg("-o")
            .arg(dir.join("bad-frames")),
    );
    assert!(
        err.contains("scratch decoder") && err.contains("--decoder"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `--eval-style` and `--eval-every`: the stage-3 loss on fixed held-out samples before training,
/// on schedule and at the end, printed with the samples' kind; training views and styles with
/// `--no-eval`; a painting that does not exist is named.
#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn fit_features_evaluates_held_out_views_and_paintings() {
    let dir = scratch("fit-features-evaluation");
    let inputs = tiny_features(&dir);
    let painting = small_images(&dir.join("unseen"), &["styles/brushstrokes.jpg"]);
    let lines = |out: &Path, args: &[&str]| -> Vec<String> {
        let o = ok(&mut inputs.command(out, 3, args));
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .filter(|l| l.contains("evaluation loss"))
            .map(str::to_string)
            .collect()
    };
    let held = lines(
        &dir.join("held"),
        &[
            "--eval-style",
            painting.to_str().unwrap(),
            "--eval-every",
            "2",
        ],
    );
    let steps: Vec<&str> = held.iter().map(|l| l.split(':').next().unwrap()).collect();
    assert_eq!(
        steps,
        ["iteration 0", "iteration 2", "iteration 3"],
        "{held:?}"
    );
    assert!(
        held.iter().all(|l| l.contains("8 held-out samples")),
        "{held:?}"
    );
    let saved = std::fs::read_to_string(dir.join("held/config.toml")).unwrap();
    assert!(saved.contains("eval_interval = 2"), "{saved}");
    // Without a held-out split the training views and styles are the yardstick.
    let train = lines(&dir.join("train"), &["--no-eval"]);
    assert_eq!(train.len(), 2, "{train:?}");
    assert!(
        train.iter().all(|l| l.contains("training samples")),
        "{train:?}"
    );
    assert_ne!(held[0], train[0]);
    let err = fails(&mut inputs.command(
        &dir.join("no-held-out"),
        3,
        &["--no-eval", "--eval-style", painting.to_str().unwrap()],
    ));
    assert!(err.contains("for held-out views"), "{err}");
    let missing = dir.join("no-such-painting.jpg");
    let err = fails(&mut inputs.command(
        &dir.join("bad"),
        3,
        &["--eval-style", missing.to_str().unwrap()],
    ));
    assert!(err.contains("no-such-painting.jpg"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
