//! Inputs that must be refused up front, with a message naming the value or file and the
//! problem once: style images that do not decode (before any output exists), image sizes
//! beyond the limits (before anything is allocated), style strengths and mixture weights out
//! of range, missing bundles or empty scenes, and style folders (their images, in name order).
//!
//! The stages run on a tiny bundle: 64 Gaussians on a grid with random 4-d features, a random
//! lifter, the real relu3_1 WCT encoder and decoder (from the shared data), and 8 orbit cameras
//! at 32 x 32 (every 4th held out).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use base::error::chain;
use dsgs_testkit::{scratch_dir, shared_path};
use gaussian::camera::MAX_IMAGE_SIDE;
use gaussian::{Camera, FeatureGaussians};
use ndarray::{Array1, Array4};
use nets::{Decoder, Encoder, Lifter};
use pipeline::bake::{BakeOverrides, BakeSettings};
use pipeline::cameras::{self, CameraRequest, CameraSource, KnownCameras, MAX_IMAGE_PIXELS};
use pipeline::consistency::WarpOptions;
use pipeline::eval::EvalSettings;
use pipeline::render::{render_views, DepthStyle, RenderKind, SceneInput};
use pipeline::stylize::{StylizeSettings, DEFAULT_STYLE_SIDE};
use pipeline::{Control, Quiet};
use runtime::{BundleInfo, CameraRecord, SceneBundle};
use train::Variant;

const FEATURES: usize = 4;

fn scratch(name: &str) -> PathBuf {
    scratch_dir("pipeline-input", name)
}

/// A pseudo-random number in [0, 1) from an index (a fixed hash, so the bundle is the same in
/// every run).
fn noise(i: usize) -> f32 {
    let x = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    ((x >> 40) as f32) / (1u64 << 24) as f32
}

fn grid_scene() -> FeatureGaussians<f32> {
    let mut g = FeatureGaussians::<f32> {
        sh_degree: 0,
        feature_dim: FEATURES,
        ..Default::default()
    };
    for i in 0..64 {
        let at = |k: usize| k as f32 * 0.3 - 0.45;
        g.means.push([at(i % 4), at((i / 4) % 4), at(i / 16)]);
        g.log_scales.push([0.12f32.ln(); 3]);
        g.quats.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logits.push(2.0);
        g.sh.push(std::array::from_fn(|c| noise(3 * i + c) - 0.5));
    }
    g.features = (0..64 * FEATURES)
        .map(|i| 2.0 * noise(1000 + i) - 1.0)
        .collect();
    g
}

/// The tiny bundle, built once.
fn bundle() -> &'static SceneBundle {
    static BUNDLE: OnceLock<SceneBundle> = OnceLock::new();
    BUNDLE.get_or_init(|| {
        let encoder: Encoder<f32> = Encoder::from_checkpoint(&shared_path(
            "weights/wct-relu1_1-3_1/vgg_normalised_conv3_1.pth",
        ))
        .unwrap();
        let decoder: Decoder<f32> = Decoder::from_checkpoint(&shared_path(
            "weights/wct-relu1_1-3_1/feature_invertor_conv3_1.pth",
        ))
        .unwrap();
        let scene = grid_scene();
        let c = *encoder.widths().last().unwrap();
        let lifter = Lifter::new(
            Array4::from_shape_fn((c, FEATURES, 1, 1), |(o, i, _, _)| {
                noise(5000 + o * FEATURES + i) - 0.5
            }),
            Array1::from_shape_fn(c, |o| 0.5 * noise(9000 + o)),
        )
        .unwrap();
        let request = CameraRequest {
            frames: Some(8),
            width: Some(32),
            height: Some(32),
            ..CameraRequest::new(CameraSource::Orbit)
        };
        let cams = cameras::select(&request, &KnownCameras::default(), &scene).unwrap();
        let records = cams
            .iter()
            .enumerate()
            .map(|(i, cam)| CameraRecord::new(format!("orbit_{i}"), cam, i % 4 == 0))
            .collect();
        let info = BundleInfo::new(
            &encoder,
            Variant::Standard,
            FEATURES,
            [0.0; 3],
            (vec![0.3; c], vec![0.5; c]),
            records,
        );
        SceneBundle {
            scene,
            encoder,
            decoder,
            lifter,
            info,
        }
    })
}

fn style() -> PathBuf {
    shared_path("data/styles/mondrian.jpg")
}

/// A file named like an image that holds text.
fn garbage(dir: &Path) -> PathBuf {
    let p = dir.join("style.jpg");
    std::fs::write(&p, "not an image at all").unwrap();
    p
}

fn stylize_settings(out: &Path, styles: Vec<PathBuf>) -> StylizeSettings {
    StylizeSettings {
        styles,
        weights: None,
        alpha: 1.0,
        preserve_colour: false,
        style_side: 64,
        out_dir: out.to_path_buf(),
        gif: false,
        mp4: false,
        fps: 10.0,
        sheet_views: 2,
        tile_budget: runtime::DEFAULT_TILE_BUDGET_BYTES,
        part: Default::default(),
    }
}

fn bake_settings(dir: &Path, bundle: &Path, styles: Vec<PathBuf>) -> BakeSettings {
    BakeSettings {
        bundle: bundle.to_path_buf(),
        styles,
        weights: None,
        alpha: 1.0,
        style_side: 64,
        variant: None,
        decoder: None,
        config: None,
        overrides: BakeOverrides {
            iterations: Some(2),
            ..Default::default()
        },
        output: dir.join("baked.ply"),
        resume: None,
        part: Default::default(),
    }
}

fn eval_settings(styles: Vec<PathBuf>) -> EvalSettings {
    EvalSettings {
        styles,
        weights: None,
        alpha: 1.0,
        preserve_colour: false,
        style_side: 64,
        warp: WarpOptions::default(),
        tile_budget: runtime::DEFAULT_TILE_BUDGET_BYTES,
        baseline: false,
        frames_out: None,
        measure_with: None,
        part: Default::default(),
    }
}

/// The bundle's cameras.
fn cams() -> Vec<Camera> {
    bundle().cameras()
}

/// Asserts that a message names `what` exactly once.
fn names_once(text: &str, what: &str) {
    assert_eq!(text.matches(what).count(), 1, "`{what}` once in: {text}");
}

#[test]
fn a_style_that_does_not_decode_fails_stylize_before_any_output() {
    let dir = scratch("stylize-garbage");
    let bad = garbage(&dir);
    let out = dir.join("out");
    // The good style first: the bad one is still decoded before anything is rendered.
    let settings = stylize_settings(&out, vec![style(), bad.clone()]);
    let e = pipeline::stylize::run(bundle(), &cams(), &settings, &Quiet).unwrap_err();
    let text = chain(&e);
    assert!(
        text.starts_with(&format!("style image {}: ", bad.display())),
        "{text}"
    );
    names_once(&text, "style.jpg");
    assert!(!out.exists(), "{} was created", out.display());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_style_that_does_not_decode_fails_bake_before_any_output() {
    let dir = scratch("bake-garbage");
    let bundle_dir = dir.join("bundle");
    bundle().save(&bundle_dir).unwrap();
    let bad = garbage(&dir);
    let settings = bake_settings(&dir, &bundle_dir, vec![bad.clone()]);
    let e = pipeline::bake::run(&settings, &Control::quiet()).unwrap_err();
    let text = chain(&e);
    assert!(
        text.starts_with(&format!("style image {}: ", bad.display())),
        "{text}"
    );
    names_once(&text, "style.jpg");
    let ply = &settings.output;
    for p in [
        ply.clone(),
        pipeline::bake::report_path(ply),
        pipeline::bake::checkpoint_dir(ply),
    ] {
        assert!(!p.exists(), "{} was written", p.display());
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_huge_size_is_refused_before_any_camera_is_made() {
    let scene = grid_scene();
    let none = KnownCameras::default();
    let side = MAX_IMAGE_SIDE.to_string();
    // A width far beyond the limit (a render at it would ask for hundreds of GB).
    let req = CameraRequest {
        width: Some(100_000_000),
        ..CameraRequest::new(CameraSource::Orbit)
    };
    let text = cameras::select(&req, &none, &scene)
        .unwrap_err()
        .to_string();
    assert!(text.contains("--width 100000000"), "{text}");
    assert!(text.contains(&side), "{text}");
    // Each side within the limit, but too many pixels together.
    let req = CameraRequest {
        width: Some(MAX_IMAGE_SIDE),
        height: Some(MAX_IMAGE_SIDE),
        ..CameraRequest::new(CameraSource::Orbit)
    };
    let text = cameras::select(&req, &none, &scene)
        .unwrap_err()
        .to_string();
    assert!(text.contains("--width"), "{text}");
    assert!(text.contains(&MAX_IMAGE_PIXELS.to_string()), "{text}");
    // A scale factor that multiplies known cameras beyond the limit: the cameras' origin and
    // the flag are named.
    let known = KnownCameras {
        cameras: cams(),
        held_out: vec![false; cams().len()],
        names: Vec::new(),
        origin: "scenes/tiny".into(),
    };
    let req = CameraRequest {
        scale: Some(1e12),
        ..CameraRequest::new(CameraSource::Dataset)
    };
    let text = cameras::select(&req, &known, &scene)
        .unwrap_err()
        .to_string();
    assert!(
        text.contains("scenes/tiny") && text.contains("--scale 1000000000000"),
        "{text}"
    );
    assert!(text.contains(&side), "{text}");
    // A height computed from the aspect ratio of a very flat camera.
    let mut flat = cams()[0];
    flat.intrinsics = flat.intrinsics.resized(4000, 1);
    let known = KnownCameras {
        cameras: vec![flat],
        held_out: vec![false],
        names: Vec::new(),
        origin: "scenes/flat".into(),
    };
    let req = CameraRequest {
        height: Some(100),
        ..CameraRequest::new(CameraSource::Dataset)
    };
    let text = cameras::select(&req, &known, &scene)
        .unwrap_err()
        .to_string();
    assert!(text.contains("400000 x 100"), "{text}");
    // Sizes within the limits pass, at the size asked for.
    let req = CameraRequest {
        height: Some(2),
        ..CameraRequest::new(CameraSource::Dataset)
    };
    let ok = cameras::select(&req, &known, &scene).unwrap();
    assert_eq!((ok[0].intrinsics.width, ok[0].intrinsics.height), (8000, 2));
}

#[test]
fn a_bake_scale_beyond_the_size_limit_is_refused_before_any_output() {
    let dir = scratch("bake-scale");
    let bundle_dir = dir.join("bundle");
    bundle().save(&bundle_dir).unwrap();
    let mut settings = bake_settings(&dir, &bundle_dir, vec![style()]);
    settings.overrides.resolution_scale = Some(1e6);
    let text = chain(&pipeline::bake::run(&settings, &Control::quiet()).unwrap_err());
    assert!(
        text.contains("--resolution-scale") && text.contains(&MAX_IMAGE_SIDE.to_string()),
        "{text}"
    );
    assert!(text.contains(&bundle_dir.display().to_string()), "{text}");
    let ply = &settings.output;
    assert!(!ply.exists() && !pipeline::bake::checkpoint_dir(ply).exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn oversized_cameras_given_to_a_stage_are_refused_before_any_output() {
    let dir = scratch("oversized");
    let mut huge = cams()[0];
    huge.intrinsics = huge.intrinsics.resized(u32::MAX, u32::MAX);
    let out = dir.join("frames");
    let scene = SceneInput::Ply {
        path: dir.join("grid.ply"),
        scene: grid_scene(),
    };
    let e = render_views(
        &scene,
        &[cams()[0], huge],
        (RenderKind::Colour, DepthStyle::Colour),
        None,
        &out,
        &Quiet,
    )
    .unwrap_err();
    let text = e.to_string();
    assert!(
        text.starts_with("camera 1:") && text.contains(&MAX_IMAGE_SIDE.to_string()),
        "{text}"
    );
    assert!(!out.exists());
    let settings = stylize_settings(&out, vec![style()]);
    let e = pipeline::stylize::run(bundle(), &[huge], &settings, &Quiet).unwrap_err();
    assert!(e.to_string().contains(&MAX_IMAGE_SIDE.to_string()), "{e}");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_style_size_beyond_the_limit_is_refused() {
    let too_big = MAX_IMAGE_SIDE + 1;
    let e = pipeline::image_io::load_style_image(&style(), too_big).unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains(&format!("--style-size {too_big}"))
            && text.contains(&MAX_IMAGE_SIDE.to_string()),
        "{text}"
    );
    // Within the limit, the longer side is reduced to the size asked for.
    let img = pipeline::image_io::load_style_image(&style(), 40).unwrap();
    assert_eq!(img.width.max(img.height), 40);
    // The default size is accepted.
    assert!(pipeline::image_io::load_style_image(&style(), DEFAULT_STYLE_SIDE).is_ok());
}

/// The strengths outside [0, 1], as given and as a message shows them.
const BAD_ALPHAS: [(f64, &str); 4] = [
    (5.0, "--alpha 5"),
    (-0.1, "--alpha -0.1"),
    (f64::NAN, "--alpha NaN"),
    (f64::INFINITY, "--alpha inf"),
];

/// Mixture weights for two styles that must be refused, and what the message names.
fn bad_weights() -> Vec<(Vec<f64>, &'static str)> {
    vec![
        (vec![-1.0, 1.0], "weight 1 is -1"),
        (vec![1.0, f64::NAN], "weight 2 is NaN"),
        (vec![f64::INFINITY, 1.0], "weight 1 is inf"),
        (vec![0.0, 0.0], "--mix 0,0"),
    ]
}

#[test]
fn stylize_refuses_a_strength_or_weights_out_of_range() {
    let dir = scratch("stylize-alpha");
    let out = dir.join("out");
    for (alpha, shown) in BAD_ALPHAS {
        let settings = StylizeSettings {
            alpha,
            ..stylize_settings(&out, vec![style()])
        };
        let text = pipeline::stylize::run(bundle(), &cams(), &settings, &Quiet)
            .unwrap_err()
            .to_string();
        assert!(text.starts_with(shown), "{text}");
        assert!(text.contains("from 0") && text.contains("to 1"), "{text}");
    }
    for (weights, shown) in bad_weights() {
        let settings = StylizeSettings {
            weights: Some(weights),
            ..stylize_settings(&out, vec![style(), style()])
        };
        let text = pipeline::stylize::run(bundle(), &cams(), &settings, &Quiet)
            .unwrap_err()
            .to_string();
        assert!(text.contains(shown), "{text}");
    }
    assert!(!out.exists());
    // The bounds themselves are strengths.
    for alpha in [0.0, 1.0] {
        assert!(pipeline::stylize::check_alpha(alpha).is_ok());
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bake_refuses_a_strength_or_weights_out_of_range() {
    let dir = scratch("bake-alpha");
    // No bundle is needed: the settings are checked first.
    let bundle_dir = dir.join("bundle");
    for (alpha, shown) in BAD_ALPHAS {
        let settings = BakeSettings {
            alpha,
            ..bake_settings(&dir, &bundle_dir, vec![style()])
        };
        let text = pipeline::bake::run(&settings, &Control::quiet())
            .unwrap_err()
            .to_string();
        assert!(text.starts_with(shown), "{text}");
    }
    for (weights, shown) in bad_weights() {
        let settings = BakeSettings {
            weights: Some(weights),
            ..bake_settings(&dir, &bundle_dir, vec![style(), style()])
        };
        let text = pipeline::bake::run(&settings, &Control::quiet())
            .unwrap_err()
            .to_string();
        assert!(text.contains(shown), "{text}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn eval_refuses_a_strength_or_weights_out_of_range() {
    let cams = &cams()[..2];
    for (alpha, shown) in BAD_ALPHAS {
        let settings = EvalSettings {
            alpha,
            ..eval_settings(vec![style()])
        };
        let text = pipeline::eval::evaluate_bundle(bundle(), "tiny", cams, &settings, &Quiet)
            .unwrap_err()
            .to_string();
        assert!(text.starts_with(shown), "{text}");
    }
    for (weights, shown) in bad_weights() {
        let settings = EvalSettings {
            weights: Some(weights),
            ..eval_settings(vec![style(), style()])
        };
        let text = pipeline::eval::evaluate_bundle(bundle(), "tiny", cams, &settings, &Quiet)
            .unwrap_err()
            .to_string();
        assert!(text.contains(shown), "{text}");
    }
}

#[test]
fn a_missing_bundle_is_said_once() {
    let dir = scratch("missing-bundle");
    let gone = dir.join("gone");
    let text = chain(&pipeline::open::load_bundle(&gone, None, None).unwrap_err());
    assert_eq!(text, format!("bundle folder {} not found", gone.display()));
    // An empty folder, for stylize and for render.
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let want = format!("{}: no bundle.json", empty.display());
    let text = chain(&pipeline::open::load_bundle(&empty, None, None).unwrap_err());
    assert!(text.starts_with(&want), "{text}");
    names_once(&text, "empty");
    let text = chain(&SceneInput::open(&empty).err().unwrap());
    assert!(text.starts_with(&want), "{text}");
    assert!(!text.contains("os error"), "{text}");
    // A bundle.json that cannot be read: the system's reason is shown once.
    let odd = dir.join("odd");
    std::fs::create_dir_all(odd.join("bundle.json")).unwrap();
    let text = chain(&pipeline::open::load_bundle(&odd, None, None).unwrap_err());
    assert!(text.contains("bundle.json: cannot be read: "), "{text}");
    let reason = text.rsplit("cannot be read: ").next().unwrap();
    names_once(&text, reason);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_orbit_around_an_empty_scene_names_its_file() {
    let dir = scratch("empty-scene");
    let ply = dir.join("nothing.ply");
    let scene = SceneInput::Ply {
        path: ply.clone(),
        scene: FeatureGaussians::default(),
    };
    let req = CameraRequest::new(CameraSource::Orbit);
    let text = cameras::select(&req, &scene.known_cameras(), scene.gaussians())
        .unwrap_err()
        .to_string();
    assert!(
        text.starts_with(&format!("{}: ", ply.display())) && text.contains("no Gaussians"),
        "{text}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A style folder stands for its images in name order (other files ignored); an empty folder
/// is an error naming it; files given beside a folder keep their place.
#[test]
fn a_style_folder_stands_for_its_images_in_name_order() {
    let dir = scratch("style-folder");
    let folder = dir.join("paintings");
    std::fs::create_dir_all(&folder).unwrap();
    for name in ["b.png", "a.jpg"] {
        std::fs::copy(style(), folder.join(name)).unwrap();
    }
    std::fs::write(folder.join("notes.txt"), "not an image").unwrap();
    let styles = pipeline::stylize::load_styles(&[style(), folder.clone()], 64).unwrap();
    let paths: Vec<PathBuf> = styles.iter().map(|s| s.path.clone()).collect();
    assert_eq!(paths, [style(), folder.join("a.jpg"), folder.join("b.png")]);
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = format!(
        "{:#}",
        pipeline::stylize::load_styles(std::slice::from_ref(&empty), 64).unwrap_err()
    );
    assert!(
        err.contains("empty") && err.contains("no .png or .jpg"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
