//! Test support: a scratch directory per test, a tiny scene bundle built from real data, and a
//! deterministic pseudo-random generator.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use dsgs_testkit::shared_path;
use gaussian::ply::load_ply;
use gaussian::FeatureGaussians;
use ndarray::{Array1, Array4};
use nets::{Decoder, Encoder, Lifter};
use pipeline::cameras::{select, CameraRequest, CameraSource, KnownCameras};
use runtime::{BundleInfo, CameraRecord, SceneBundle};
use train::Variant;

/// The `dsgs` binary.
pub fn dsgs() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dsgs"))
}

/// Runs a command and asserts success, showing its error output otherwise.
pub fn ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("the dsgs binary runs");
    assert!(
        out.status.success(),
        "dsgs failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs a command that must fail and returns its error output.
pub fn fails(cmd: &mut Command) -> String {
    let out = cmd.output().expect("the dsgs binary runs");
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "dsgs unexpectedly succeeded: {err}");
    assert!(err.starts_with("error: "), "{err}");
    err
}

/// Checks the summary of a `dsgs run` or `dsgs demo` that found every stage done: each of
/// them says it was skipped.
pub fn every_stage_skipped(out: &Output) {
    let text = String::from_utf8_lossy(&out.stdout);
    for stage in ["weights", "geometry", "features", "stylize", "eval"] {
        assert!(
            text.contains(&format!("{stage}: done before, skipped")),
            "{stage}: {text}"
        );
    }
}

/// A fresh scratch directory under the cargo target's temporary directory.
pub fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A 64-bit linear congruential generator (Knuth's MMIX constants); `uniform` returns [0, 1).
pub struct Lcg(pub u64);

impl Lcg {
    pub fn uniform(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

/// The `n` Gaussians of trained_9080.ply nearest to the per-axis median of the means.
pub fn trained_subset(n: usize) -> FeatureGaussians<f32> {
    let full = load_ply(shared_path("data/gaussians/trained_9080.ply")).unwrap();
    let c = pipeline::cameras::median_centre(&full);
    let mut idx: Vec<usize> = (0..full.len()).collect();
    let d = |i: usize| {
        let m = full.means[i];
        (m[0] as f64 - c.x).powi(2) + (m[1] as f64 - c.y).powi(2) + (m[2] as f64 - c.z).powi(2)
    };
    idx.sort_by(|&a, &b| d(a).total_cmp(&d(b)));
    idx.truncate(n);
    idx.sort_unstable();
    let k = full.sh_coeffs_per_gaussian();
    FeatureGaussians {
        means: idx.iter().map(|&i| full.means[i]).collect(),
        log_scales: idx.iter().map(|&i| full.log_scales[i]).collect(),
        quats: idx.iter().map(|&i| full.quats[i]).collect(),
        opacity_logits: idx.iter().map(|&i| full.opacity_logits[i]).collect(),
        sh_degree: full.sh_degree,
        sh: idx
            .iter()
            .flat_map(|&i| full.sh[i * k..(i + 1) * k].to_vec())
            .collect(),
        feature_dim: 0,
        features: Vec::new(),
    }
}

/// Feature width of the tiny bundle.
pub const FEATURES: usize = 8;

/// The real relu3_1 WCT encoder and decoder.
pub fn wct_relu3() -> (Encoder<f32>, Decoder<f32>) {
    let enc = Encoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
    ))
    .unwrap();
    let dec = Decoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
    ))
    .unwrap();
    (enc, dec)
}

/// A tiny bundle: 1,500 Gaussians of trained_9080.ply with random 8-d features, a random lifter
/// to relu3_1's 256 channels, the real relu3_1 encoder and decoder, and 16 orbit cameras at
/// 64x64 (every 8th held out).
pub fn tiny_bundle() -> SceneBundle {
    let mut scene = trained_subset(1500);
    let mut rng = Lcg(7);
    scene.feature_dim = FEATURES;
    scene.features = (0..scene.len() * FEATURES)
        .map(|_| 2.0 * rng.uniform() - 1.0)
        .collect();
    let (encoder, decoder) = wct_relu3();
    let c = *encoder.widths().last().unwrap();
    let w = Array4::from_shape_fn((c, FEATURES, 1, 1), |_| rng.uniform() - 0.5);
    let b = Array1::from_shape_fn(c, |_| 0.5 * rng.uniform());
    let lifter = Lifter::new(w, b).unwrap();
    let mut req = CameraRequest::new(CameraSource::Orbit);
    req.frames = Some(16);
    req.width = Some(64);
    req.height = Some(64);
    let cams = select(&req, &KnownCameras::default(), &scene).unwrap();
    let cameras = cams
        .iter()
        .enumerate()
        .map(|(i, cam)| CameraRecord::new(format!("orbit_{i:02}"), cam, i % 8 == 0))
        .collect();
    let stats = (vec![0.3; c], vec![0.5; c]);
    let info = BundleInfo::new(
        &encoder,
        Variant::Standard,
        FEATURES,
        [0.0; 3],
        stats,
        cameras,
    );
    SceneBundle {
        scene,
        encoder,
        decoder,
        lifter,
        info,
    }
}

/// Saves the tiny bundle into `dir/bundle` and returns that path.
pub fn save_tiny_bundle(dir: &Path) -> PathBuf {
    let p = dir.join("bundle");
    tiny_bundle().save(&p).unwrap();
    p
}

/// The pixel size of a PNG (or any image) file.
pub fn size_of(path: &Path) -> (u32, u32) {
    image::image_dimensions(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The acceptance test of a stop request: `command(out)` builds a training run of
/// `iterations` writing to `out` (run here with `--log-every 1`). The run goes straight through
/// into `full`; again into `cut`, where SIGTERM lands once it has logged its fifth iteration,
/// and it must stop before its last iteration, exit with status 130 and name on standard error
/// the checkpoint to resume from; `stopped(checkpoint, log)` then checks what the stopped run
/// left; last, the same command with `--resume CHECKPOINT` finishes the run in `cut`. The
/// caller compares the outputs.
#[cfg(unix)]
pub fn stop_and_resume(
    iterations: u64,
    full: &Path,
    cut: &Path,
    command: impl Fn(&Path) -> Command,
    stopped: impl FnOnce(&Path, &str),
) {
    let logged = |out: &Path| {
        let mut cmd = command(out);
        cmd.args(["--log-every", "1"]);
        cmd
    };
    ok(&mut logged(full));
    let (checkpoint, log) = sigterm_mid_run(&mut logged(cut), iterations);
    stopped(&checkpoint, &log);
    ok(logged(cut).arg("--resume").arg(&checkpoint));
}

/// Runs a command that logs every iteration and sends it SIGTERM after its fifth: see
/// [`stop_and_resume`]. Returns the checkpoint named and the error output.
#[cfg(unix)]
fn sigterm_mid_run(cmd: &mut Command, iterations: u64) -> (PathBuf, String) {
    use std::io::{BufRead, BufReader, Read};
    use std::process::Stdio;

    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the dsgs binary runs");
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut log = String::new();
    loop {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            let status = child.wait().unwrap();
            panic!("the run ended ({status}) before its fifth iteration:\n{log}");
        }
        log.push_str(&line);
        if line.contains("[ITER 5]") {
            break;
        }
    }
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    stderr.read_to_string(&mut log).unwrap();
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{log}");
    assert!(
        !log.contains(&format!("[ITER {iterations}]")),
        "the run finished before the signal:\n{log}"
    );
    let checkpoint = log
        .lines()
        .find_map(|l| l.split("resume with --resume ").nth(1))
        .map(|p| PathBuf::from(p.trim()))
        .unwrap_or_else(|| panic!("no resume hint:\n{log}"));
    assert!(checkpoint.is_file(), "{}:\n{log}", checkpoint.display());
    (checkpoint, log)
}

/// Asserts that two directories hold the same files with the same bytes.
pub fn assert_same_files(a: &Path, b: &Path) {
    assert_same_files_except(a, b, &[]);
}

/// [`assert_same_files`], leaving out the entries of the top level named in `skip` (e.g. the
/// `shards` folder of a sharded output) on both sides.
pub fn assert_same_files_except(a: &Path, b: &Path, skip: &[&str]) {
    let names = |d: &Path| {
        let mut v: Vec<_> = std::fs::read_dir(d)
            .unwrap_or_else(|e| panic!("{}: {e}", d.display()))
            .map(|e| e.unwrap().file_name())
            .filter(|n| !skip.iter().any(|s| n == s))
            .collect();
        v.sort();
        v
    };
    let files = names(a);
    assert_eq!(files, names(b), "{} and {}", a.display(), b.display());
    for f in &files {
        let (x, y) = (a.join(f), b.join(f));
        if x.is_dir() {
            assert_same_files(&x, &y);
        } else {
            assert!(
                std::fs::read(&x).unwrap() == std::fs::read(&y).unwrap(),
                "{} and {} differ",
                x.display(),
                y.display()
            );
        }
    }
}
