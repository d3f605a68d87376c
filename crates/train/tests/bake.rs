//! Baking a style into a plain 3DGS scene, on a tiny bundle built here: 800 Gaussians of a real
//! trained scene (`data/gaussians/trained_9080.ply`, those nearest its median point) seen by a
//! ring of 12 cameras at 48x48 pixels, random 8-channel features (seeded), a random lifter, and
//! the real WCT relu3_1 encoder and decoder; the style is a painting from `data/styles`.
//!
//! The held-out targets are views between the bundle's cameras that the bake never trains on.
//! Expected values are computed here, independently of the module: targets from the bundle's own
//! `render_features` and `decode`, renders from `render_color`, PSNR from `train::loss::psnr`.
//! Run with `--release`.

use std::sync::atomic::AtomicBool;
use std::sync::OnceLock;

use dsgs_testkit::shared_path;
use gaussian::camera_path::orbit;
use gaussian::dataset::images::{load_rgb, resize};
use gaussian::ply::{load_ply, property_names, save_ply};
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DVec3;
use ndarray::{Array1, Array2, Array4};
use nets::{Decoder, Encoder, Lifter};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use runtime::bundle::{BundleInfo, CameraRecord, SceneBundle};
use style::{channel_stats, encode_style, ChannelStats};
use train::bake::{bake, bake_cameras, evaluate_baked, initial_baked_scene, BakeConfig, Baker};
use train::geometry::View;
use train::loss::psnr;
use train::render::render_color;
use train::{Quiet, Run, TrainError, Variant};

const SIZE: u32 = 48;
const FEATURES: usize = 8;
const GAUSSIANS: usize = 800;
const BACKGROUND: [f32; 3] = [0.0; 3];

/// An RGB image (row-major interleaved) as `[1, 3, H, W]`.
fn nchw(data: &[f32], width: usize, height: usize) -> Array4<f32> {
    Array4::from_shape_fn((1, 3, height, width), |(_, c, y, x)| {
        data[(y * width + x) * 3 + c]
    })
}

/// The tiny bundle described in the module documentation, and the point its cameras look at.
fn tiny_bundle() -> (SceneBundle, DVec3) {
    let full = load_ply(shared_path("data/gaussians/trained_9080.ply")).expect("trained scene");
    // The Gaussians nearest the per-axis median of the means: a compact piece of the scene.
    let median: [f32; 3] = std::array::from_fn(|a| {
        let mut v: Vec<f32> = full.means.iter().map(|m| m[a]).collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    });
    let d2 = |m: &[f32; 3]| (0..3).map(|a| (m[a] - median[a]).powi(2)).sum::<f32>();
    let mut idx: Vec<usize> = (0..full.len()).collect();
    idx.sort_by(|&a, &b| {
        d2(&full.means[a])
            .total_cmp(&d2(&full.means[b]))
            .then(a.cmp(&b))
    });
    idx.truncate(GAUSSIANS);
    idx.sort_unstable();
    let mut scene = full.subset(&idx);
    let radius = idx
        .iter()
        .map(|&i| d2(&full.means[i]).sqrt())
        .fold(0.0f32, f32::max) as f64;

    let mut rng = StdRng::seed_from_u64(7);
    scene.feature_dim = FEATURES;
    // Random Fourier features of the position: spatially coherent like learnt features.
    let freqs: Vec<[f32; 3]> = (0..FEATURES)
        .map(|_| {
            std::array::from_fn(|_| 3.0 * rng.sample::<f32, _>(StandardNormal) / radius as f32)
        })
        .collect();
    let phases: Vec<f32> = (0..FEATURES)
        .map(|_| rng.random_range(0.0..std::f32::consts::TAU))
        .collect();
    scene.features = scene
        .means
        .iter()
        .flat_map(|m| {
            freqs.iter().zip(&phases).map(move |(w, &ph)| {
                ((0..3).map(|a| w[a] * (m[a] - median[a])).sum::<f32>() + ph).sin()
            })
        })
        .collect();

    // A ring of cameras at three times the piece's radius, framing it.
    let distance = 3.0 * radius;
    let focal = 0.5 * SIZE as f64 * distance / (1.1 * radius);
    let k = Intrinsics {
        fx: focal,
        fy: focal,
        cx: 0.5 * SIZE as f64,
        cy: 0.5 * SIZE as f64,
        width: SIZE,
        height: SIZE,
    };
    let center = DVec3::new(median[0] as f64, median[1] as f64, median[2] as f64);
    let cameras = orbit(k, center, distance, 0.35, 12, DVec3::Z).expect("orbit");

    let encoder: Encoder = Encoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
    ))
    .expect("encoder");
    let decoder: Decoder = Decoder::from_checkpoint(&shared_path(
        "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
    ))
    .expect("decoder");
    let c = *encoder.widths().last().unwrap();
    let scale = 2.0 / (FEATURES as f32).sqrt();
    let lifter = Lifter::new(
        Array4::from_shape_fn((c, FEATURES, 1, 1), |_| {
            scale * rng.sample::<f32, _>(StandardNormal)
        }),
        Array1::from_shape_fn(c, |_| 0.1 * rng.sample::<f32, _>(StandardNormal)),
    )
    .expect("lifter");

    // The scene statistics as feature training records them: the mean over the views of the
    // deepest encoder features' statistics of the geometry's own colour renders.
    let mut mean = Array2::<f32>::zeros((1, c));
    let mut std = Array2::<f32>::zeros((1, c));
    for cam in &cameras {
        let img = render_color(cam, &scene, scene.sh_degree, BACKGROUND)
            .unwrap()
            .raster
            .image;
        let s = channel_stats(
            encoder
                .forward(nchw(&img, SIZE as usize, SIZE as usize).view())
                .unwrap()
                .last()
                .unwrap(),
        )
        .unwrap();
        mean += &(s.mean / cameras.len() as f32);
        std += &(s.std / cameras.len() as f32);
    }
    let records = cameras
        .iter()
        .enumerate()
        .map(|(i, cam)| CameraRecord::new(format!("ring_{i:02}"), cam, false))
        .collect();
    let stats = (mean.row(0).to_vec(), std.row(0).to_vec());
    let info = BundleInfo::new(
        &encoder,
        Variant::Standard,
        FEATURES,
        BACKGROUND,
        stats,
        records,
    );
    let bundle = SceneBundle {
        scene,
        encoder,
        decoder,
        lifter,
        info,
    };
    bundle.validate().expect("consistent bundle");
    (bundle, center)
}

/// The target statistics: a painting's relu3_1 statistics at strength 0.8.
fn style_stats(bundle: &SceneBundle) -> ChannelStats<f32> {
    let img = load_rgb(&shared_path("data/styles/mondrian.jpg"), [0.0; 3]).expect("style");
    let img = resize(&img, 64, 64);
    let s = encode_style(&bundle.encoder, &nchw(&img.data, 64, 64)).expect("style statistics");
    bundle.target_stats(s.deepest(), 0.8).expect("mix")
}

/// A stylized target computed directly from the bundle: features, decode, clamp.
fn target(bundle: &SceneBundle, stats: &ChannelStats<f32>, cam: &Camera) -> Vec<f32> {
    let f = bundle.render_features(cam).unwrap();
    let img = bundle.decode(&f, stats, SIZE, SIZE).unwrap();
    let (h, w) = (SIZE as usize, SIZE as usize);
    let alpha = render_color(cam, &bundle.scene, 0, BACKGROUND)
        .unwrap()
        .raster
        .alpha;
    let mut out = vec![0.0f32; h * w * 3];
    for ((_, c, y, x), v) in img.indexed_iter() {
        let a = alpha[y * w + x];
        out[(y * w + x) * 3 + c] = a * v.clamp(0.0, 1.0) + (1.0 - a) * BACKGROUND[c];
    }
    out
}

/// Mean PSNR of `scene` (rendered at its stored degree, clamped) against the targets.
fn mean_psnr(scene: &FeatureGaussians<f32>, cams: &[Camera], targets: &[Vec<f32>]) -> f64 {
    let shape = train::ImageShape::new(SIZE as usize, SIZE as usize, 3);
    let total: f64 = cams
        .iter()
        .zip(targets)
        .map(|(cam, t)| {
            let img: Vec<f32> = render_color(cam, scene, scene.sh_degree, BACKGROUND)
                .unwrap()
                .raster
                .image
                .iter()
                .map(|v| v.clamp(0.0, 1.0))
                .collect();
            psnr(&img, t, shape).unwrap()
        })
        .sum();
    total / cams.len() as f64
}

struct Fixture {
    bundle: SceneBundle,
    stats: ChannelStats<f32>,
    /// The point the bundle's cameras look at.
    center: DVec3,
}

/// The bundle and target statistics, built once for all tests of this file.
fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let (bundle, center) = tiny_bundle();
        let stats = style_stats(&bundle);
        Fixture {
            bundle,
            stats,
            center,
        }
    })
}

/// The test bake: 150 iterations at ten times the 3DGS colour rate (so that so few iterations
/// converge), degree 3, two interpolated cameras per pair, three of them held out.
fn config() -> BakeConfig {
    BakeConfig {
        iterations: 150,
        feature_lr: 0.025,
        sh_degree: 3,
        interpolated_per_pair: 2,
        held_out: 3,
        ..BakeConfig::default()
    }
}

/// Property names in a PLY header, in order.
fn header_properties(bytes: &[u8]) -> Vec<String> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header");
    std::str::from_utf8(&bytes[..end])
        .unwrap()
        .lines()
        .filter_map(|l| l.strip_prefix("property float ").map(str::to_string))
        .collect()
}

fn same_geometry(a: &FeatureGaussians<f32>, b: &FeatureGaussians<f32>) -> bool {
    let bits3 = |v: &[[f32; 3]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    let bits4 = |v: &[[f32; 4]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    bits3(&a.means) == bits3(&b.means) && bits4(&a.quats) == bits4(&b.quats)
}

#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "slow without optimisation: run with --release"
)]
fn baked_colours_reproduce_held_out_stylized_views() {
    let Fixture { bundle, stats, .. } = fixture();
    let cfg = config();
    let report = bake(bundle, stats, &cfg, None, &Run::in_memory()).unwrap();
    let cams = bake_cameras(&bundle.cameras(), &cfg).unwrap();
    assert_eq!(report.run.step, 150);
    assert!(!report.run.interrupted);
    assert_eq!(report.train_views, cams.train.len());
    assert_eq!(report.held_out_views, 3);

    // The held-out cameras are interpolated: none is a training or dataset camera.
    let dataset = bundle.cameras();
    for h in &cams.held_out {
        let m = h.camera.camera_from_world;
        assert!(cams.train.iter().all(|t| t.camera.camera_from_world != m));
        assert!(dataset.iter().all(|d| d.camera_from_world != m));
    }

    // Held-out PSNR, computed here: baked colours against the unbaked geometry's own colours.
    let held: Vec<Camera> = cams.held_out.iter().map(|c| c.camera).collect();
    let targets: Vec<Vec<f32>> = held.iter().map(|c| target(bundle, stats, c)).collect();
    let baked = mean_psnr(&report.scene, &held, &targets);
    let unbaked = mean_psnr(&bundle.scene, &held, &targets);
    println!(
        "held-out PSNR: baked {baked:.2} dB, unbaked {unbaked:.2} dB; training PSNR: baked {:.2} \
         dB, unbaked {:.2} dB ({} training targets)",
        report.train_psnr, report.unbaked_train_psnr, report.train_views
    );
    // The report computes the same figures with the same arithmetic.
    let reported = report.held_out_psnr.unwrap();
    assert!((reported - baked).abs() < 1e-9, "{reported} vs {baked}");
    assert!((report.unbaked_held_out_psnr.unwrap() - unbaked).abs() < 1e-9);
    let evaluated = evaluate_baked(bundle, stats, &report.scene, &held, &cfg)
        .unwrap()
        .unwrap();
    assert!((evaluated - baked).abs() < 1e-9);
    // Baking must beat the geometry's own colours on unseen views by a wide margin: the style
    // moves colours far from the photograph's (here about 21 dB against about 35 dB after
    // baking); 10 dB leaves room for platform rounding while failing any bake that does not fit.
    assert!(
        baked >= unbaked + 10.0,
        "baked {baked:.2} dB vs unbaked {unbaked:.2} dB"
    );
    assert!(report.train_psnr >= report.unbaked_train_psnr + 10.0);

    // A plain 3DGS scene over the bundle's unchanged geometry.
    let s = &report.scene;
    assert_eq!(s.feature_dim, 0);
    assert!(s.features.is_empty());
    assert_eq!(s.sh_degree, 3);
    assert_eq!(s.len(), bundle.scene.len());
    assert!(same_geometry(s, &bundle.scene));
    assert_eq!(s.opacity_logits, bundle.scene.opacity_logits);
    assert_eq!(s.log_scales, bundle.scene.log_scales);

    // The official layout on disk, and an exact round trip.
    let dir = std::env::temp_dir().join(format!("dsgs-bake-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("baked.ply");
    save_ply(&path, s).unwrap();
    let names = header_properties(&std::fs::read(&path).unwrap());
    assert_eq!(names.len(), 62);
    assert_eq!(names, property_names(3, 0));
    let back = load_ply(&path).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(&back, s);
}

/// The closed-form colour solve alone (`iterations = 0`) already reproduces held-out stylized
/// views far better than the bundle's colours, and changes only the DC colours and degree 1
/// (only the DC at `sh_degree` 0); without it (`solve_iterations = 0` too) the colours are the
/// bundle's DC.
#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "slow without optimisation: run with --release"
)]
fn the_colour_solve_alone_bakes_the_style() {
    let Fixture { bundle, stats, .. } = fixture();
    let cfg = BakeConfig {
        iterations: 0,
        ..config()
    };
    let report = bake(bundle, stats, &cfg, None, &Run::in_memory()).unwrap();
    assert_eq!(report.run.step, 0);
    let solve = report.solve.as_ref().expect("a fresh bake solves");
    assert!(solve.iterations >= 1 && solve.iterations <= cfg.solve_iterations);
    assert!(solve.residual < 1.0);
    // With no optimisation after it, the solve's scene is the baked one.
    assert_eq!(solve.held_out_psnr, report.held_out_psnr);
    let (solved, unbaked) = (
        report.held_out_psnr.unwrap(),
        report.unbaked_held_out_psnr.unwrap(),
    );
    // The same margin as the optimised bake's test above.
    assert!(
        solved >= unbaked + 10.0,
        "solved {solved:.2} dB vs unbaked {unbaked:.2} dB"
    );
    let s = &report.scene;
    assert!(same_geometry(s, &bundle.scene));
    assert_eq!(s.opacity_logits, bundle.scene.opacity_logits);
    let k = s.sh_coeffs_per_gaussian();
    let zero_from = |s: &FeatureGaussians<f32>, from: usize| {
        (0..s.len()).all(|i| {
            s.sh[i * k + from..(i + 1) * k]
                .iter()
                .flatten()
                .all(|&v| v == 0.0)
        })
    };
    assert_eq!(solve.degree, 1);
    assert!(zero_from(s, 4));
    assert!(!zero_from(s, 1), "the degree-1 solve left degree 1 at zero");
    let dc_only = bake(
        bundle,
        stats,
        &BakeConfig {
            sh_degree: 0,
            ..cfg.clone()
        },
        None,
        &Run::in_memory(),
    )
    .unwrap();
    assert_eq!(dc_only.solve.as_ref().map(|s| s.degree), Some(0));
    assert!(zero_from(&dc_only.scene, 1));
    // No solve and no optimisation: the bundle's own colours.
    let none = BakeConfig {
        solve_iterations: 0,
        ..cfg
    };
    let plain = bake(bundle, stats, &none, None, &Run::in_memory()).unwrap();
    assert!(plain.solve.is_none());
    let (kb, ps) = (bundle.scene.sh_coeffs_per_gaussian(), &plain.scene);
    assert!((0..ps.len()).all(|i| ps.sh[i * k] == bundle.scene.sh[i * kb]));
    println!(
        "held-out PSNR: solved {solved:.2} dB in {} iterations, {:.2} s; bundle's DC {:.2} dB",
        solve.iterations,
        solve.seconds,
        plain.held_out_psnr.unwrap()
    );
}

#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "slow without optimisation: run with --release"
)]
fn adapted_geometry_stays_within_its_budget_for_any_thread_count() {
    let Fixture { bundle, stats, .. } = fixture();
    // Rates far above the defaults, so that the budgets bind within 40 iterations.
    let cfg = BakeConfig {
        iterations: 40,
        sh_degree: 1,
        adapt_geometry: true,
        opacity_lr: 0.05,
        scaling_lr: 0.05,
        opacity_logit_budget: 0.3,
        log_scale_budget: 0.05,
        ..config()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            bake(bundle, stats, &cfg, None, &Run::in_memory())
                .unwrap()
                .scene
        })
    };
    let one = run(1);
    let three = run(3);
    assert_eq!(one, three, "the bake depends on the thread count");

    let s = &one;
    let s0 = &bundle.scene;
    assert!(same_geometry(s, s0), "means or rotations moved");
    let (mut moved, mut at_bound) = (0, 0);
    let mut check = |v: f32, v0: f32, budget: f32| {
        // The projection is `clamp(v0 - budget, v0 + budget)` in f32: compare with exactly that.
        assert!(
            v >= v0 - budget && v <= v0 + budget,
            "{v} escapes {v0} +- {budget}"
        );
        moved += (v != v0) as usize;
        at_bound += (v == v0 - budget || v == v0 + budget) as usize;
    };
    for (&v, &v0) in s.opacity_logits.iter().zip(&s0.opacity_logits) {
        check(v, v0, cfg.opacity_logit_budget);
    }
    for (v, v0) in s
        .log_scales
        .iter()
        .flatten()
        .zip(s0.log_scales.iter().flatten())
    {
        check(v.to_owned(), v0.to_owned(), cfg.log_scale_budget);
    }
    println!("adapted geometry: {moved} values moved, {at_bound} at their bound");
    assert!(moved > 0 && at_bound > 0);
    // Degree 1 is optimised; the stored coefficients of degrees 2 and 3 stay zero.
    for row in s.sh.chunks_exact(16) {
        assert!(row[4..].iter().flatten().all(|&v| v == 0.0));
    }
}

#[test]
fn target_cameras() {
    let Fixture { bundle, center, .. } = fixture();
    let ring = bundle.cameras();
    let base = BakeConfig {
        interpolated_per_pair: 2,
        held_out: 3,
        ..BakeConfig::default()
    };
    let cams = bake_cameras(&ring, &base).unwrap();
    // On an evenly spaced ring each camera's nearest neighbour is adjacent: at most 12 pairs,
    // at least 6 (every camera in one pair).
    let interpolated = cams.train.len() + cams.held_out.len() - ring.len();
    assert!((12..=24).contains(&interpolated), "{interpolated}");
    assert_eq!(interpolated % 2, 0);
    assert!(cams.held_out.iter().all(|c| c.name.starts_with("interp_")));

    // Subsampling and resolution.
    let cfg = BakeConfig {
        target_views: 10,
        resolution_scale: 0.5,
        ..base.clone()
    };
    let cams = bake_cameras(&ring, &cfg).unwrap();
    assert_eq!(cams.train.len(), 10);
    for c in cams.train.iter().chain(&cams.held_out) {
        assert_eq!(
            (c.camera.intrinsics.width, c.camera.intrinsics.height),
            (24, 24)
        );
    }

    // Orbit cameras circle the point the ring looks at (the ring's centre).
    let cfg = BakeConfig {
        orbit_views: 6,
        ..base.clone()
    };
    let cams = bake_cameras(&ring, &cfg).unwrap();
    let orbit: Vec<&Camera> = cams
        .train
        .iter()
        .filter(|c| c.name.starts_with("orbit_"))
        .map(|c| &c.camera)
        .collect();
    assert_eq!(orbit.len(), 6);
    for c in orbit {
        let (u, v, _) = c.project_point(*center);
        let k = c.intrinsics;
        // 1e-6 px: the centre is found by a 3x3 least-squares solve in f64.
        assert!(
            (u - k.cx).abs() < 1e-6 && (v - k.cy).abs() < 1e-6,
            "({u}, {v})"
        );
    }

    // Impossible requests are refused with a message naming the setting.
    let too_many = BakeConfig {
        held_out: 1000,
        ..base.clone()
    };
    let e = bake_cameras(&ring, &too_many).unwrap_err().to_string();
    assert!(e.contains("held-out"), "{e}");
    let bad_degree = BakeConfig {
        sh_degree: 4,
        ..base.clone()
    };
    let e = bake_cameras(&ring, &bad_degree).unwrap_err().to_string();
    assert!(e.contains("sh_degree"), "{e}");
    let e = bake_cameras(&[], &base).unwrap_err().to_string();
    assert!(e.contains("no cameras"), "{e}");
}

#[test]
fn stop_flag_ends_the_bake() {
    let Fixture { bundle, stats, .. } = fixture();
    let stop = AtomicBool::new(true);
    // Raised before the targets exist: nothing to bake.
    let stopped = Run {
        out_dir: None,
        stop: Some(&stop),
        sink: &Quiet,
    };
    let e = bake(bundle, stats, &config(), None, &stopped).unwrap_err();
    assert!(matches!(e, TrainError::Interrupted(_)), "{e}");
    // Raised during the optimisation: the scene as it was, reported as interrupted.
    let targets = two_targets();
    let before = initial_baked_scene(&bundle.scene).unwrap();
    let mut baker = Baker::new(before.clone(), &targets, BACKGROUND, &config()).unwrap();
    let outcome = baker.train(&stopped).unwrap();
    assert_eq!((outcome.step, outcome.interrupted), (0, true));
    let scene = baker.scene;
    assert_eq!(scene, before);
    // The starting scene: the bundle's DC, zero higher bands, no features.
    let k0 = bundle.scene.sh_coeffs_per_gaussian();
    for (i, row) in scene.sh.chunks_exact(16).enumerate() {
        assert_eq!(row[0], bundle.scene.sh[i * k0]);
        assert!(row[1..].iter().flatten().all(|&v| v == 0.0));
    }
}

/// Two training targets of the fixture, rendered here.
fn two_targets() -> Vec<View> {
    let Fixture { bundle, stats, .. } = fixture();
    let cams = bake_cameras(&bundle.cameras(), &config()).unwrap();
    cams.train
        .iter()
        .take(2)
        .map(|c| View {
            name: c.name.clone(),
            camera: c.camera,
            image: target(bundle, stats, &c.camera),
        })
        .collect()
}

#[test]
#[cfg_attr(
    debug_assertions,
    ignore = "slow without optimisation: run with --release"
)]
fn a_bake_resumed_from_its_checkpoint_ends_bit_identical() {
    let Fixture { bundle, .. } = fixture();
    let targets = two_targets();
    // 5 iterations over 2 targets: the checkpoint at 3 falls inside the second pass, so the
    // resumed view order must continue that pass; adapting geometry covers every Adam group.
    let cfg = BakeConfig {
        iterations: 5,
        checkpoint_interval: 3,
        adapt_geometry: true,
        ..config()
    };
    let dir = std::env::temp_dir().join(format!("dsgs-bake-resume-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let initial = initial_baked_scene(&bundle.scene).unwrap();
    let mut whole = Baker::new(initial.clone(), &targets, BACKGROUND, &cfg).unwrap();
    let outcome = whole.train(&Run::into_dir(&dir)).unwrap();
    assert_eq!((outcome.step, outcome.interrupted), (5, false));
    let ck = dir.join(train::driver::CHECKPOINT_FILE);
    let mut resumed = Baker::resume(&ck, initial.clone(), &targets, BACKGROUND, &cfg).unwrap();
    assert_eq!(resumed.step(), 3);
    resumed.train(&Run::in_memory()).unwrap();
    assert_eq!(resumed.scene, whole.scene, "resumed bake differs");
    assert_ne!(resumed.scene, initial, "the bake changed nothing");

    // Other targets or another configuration are refused, naming the checkpoint.
    let other: Vec<View> = targets.iter().rev().cloned().collect();
    let e = Baker::resume(&ck, initial.clone(), &other, BACKGROUND, &cfg)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("other targets") && e.contains("checkpoint.safetensors"),
        "{e}"
    );
    let lr = BakeConfig {
        feature_lr: 0.5,
        ..cfg.clone()
    };
    let e = Baker::resume(&ck, initial, &targets, BACKGROUND, &lr)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("another bake configuration"), "{e}");
    // The tile budget changes no target: a bake resumes under another one.
    let budget = BakeConfig {
        tile_budget_mib: cfg.tile_budget_mib + 1,
        ..cfg.clone()
    };
    let resumed = Baker::resume(
        &ck,
        initial_baked_scene(&bundle.scene).unwrap(),
        &targets,
        BACKGROUND,
        &budget,
    );
    assert_eq!(resumed.map(|b| b.step()).ok(), Some(3));
    std::fs::remove_dir_all(&dir).unwrap();
}
