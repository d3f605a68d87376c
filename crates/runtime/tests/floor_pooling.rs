//! Frames of the standard variant with an encoder that pools with floor rounding (the real
//! 16x-compressed relu4_1 pair): every frame size decodes to the whole frame, and the feature
//! map's camera is the frame's scaled by exactly `1 / 8`, so its pixel grid is the encoder's
//! pooling grid. A bundle that supersamples its feature render renders each feature pixel as
//! the mean of its block of a finer render, keeps the factor through saving and loading, and
//! refuses a factor out of range.

use dsgs_testkit::shared_path;
use gaussian::camera_path::look_at;
use gaussian::{FeatureGaussians, Intrinsics};
use glam::DVec3;
use ndarray::{Array1, Array2, Array4};
use nets::checkpoint::load_checkpoint;
use nets::{Decoder, Encoder, Lifter, PoolRounding};
use runtime::{BundleInfo, CameraRecord, SceneBundle, Variant, DEFAULT_TILE_BUDGET_BYTES};
use style::ChannelStats;

/// Feature channels of the test scene.
const F: usize = 4;

/// A bundle of a few Gaussians with the compressed relu4_1 pair and a fixed lifter.
fn compressed_bundle() -> SceneBundle {
    let load = |rel: &str| load_checkpoint(&shared_path(&format!("weights/{rel}"))).unwrap();
    let encoder: Encoder =
        Encoder::from_state_dict(&load("compressed-16x-relu4_1/4SE.pth")).unwrap();
    let decoder: Decoder =
        Decoder::from_state_dict(&load("compressed-16x-relu4_1/4SD.pth")).unwrap();
    assert_eq!(encoder.pool_rounding(), PoolRounding::Floor);
    let c = *encoder.widths().last().unwrap();
    let mut scene = FeatureGaussians::<f32> {
        sh_degree: 0,
        feature_dim: F,
        ..Default::default()
    };
    for i in 0..30 {
        let t = i as f32 / 30.0;
        scene
            .means
            .push([t - 0.5, (3.0 * t).sin() * 0.4, (5.0 * t).cos() * 0.3]);
        scene.log_scales.push([0.12f32.ln(); 3]);
        scene.quats.push([1.0, 0.0, 0.0, 0.0]);
        scene.opacity_logits.push(2.0);
        scene.sh.push([0.5, -0.2, 0.1]);
        scene
            .features
            .extend((0..F).map(|j| ((i + j) % 5) as f32 / 5.0));
    }
    let lifter = Lifter::new(
        Array4::from_shape_fn((c, F, 1, 1), |(o, i, _, _)| 0.05 * ((o + 2 * i) % 7) as f32),
        Array1::zeros(c),
    )
    .unwrap();
    let info = BundleInfo::new(
        &encoder,
        Variant::Standard,
        F,
        [0.0; 3],
        (vec![0.0; c], vec![1.0; c]),
        vec![CameraRecord::new("view", &camera(64, 48), false)],
    );
    SceneBundle {
        scene,
        encoder,
        decoder,
        lifter,
        info,
    }
}

fn camera(width: u32, height: u32) -> gaussian::Camera {
    let k = Intrinsics {
        fx: 0.9 * width as f64,
        fy: 0.9 * width as f64,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        width,
        height,
    };
    look_at(k, DVec3::new(0.3, -0.2, -3.0), DVec3::ZERO, DVec3::NEG_Y).unwrap()
}

#[test]
fn frames_of_any_size_decode_to_the_whole_frame() {
    let bundle = compressed_bundle();
    bundle.validate().unwrap();
    let c = bundle.lifter.out_channels();
    let style = ChannelStats::new(
        Array2::from_shape_fn((1, c), |(_, j)| 0.1 * (j % 5) as f32),
        Array2::from_elem((1, c), 0.3),
    )
    .unwrap();
    // Sides that are and are not multiples of the pooling factor 8.
    for (w, h) in [(64, 48), (37, 29), (41, 56)] {
        let cam = camera(w, h);
        let frame = bundle
            .frame(&cam, &style, 1.0, DEFAULT_TILE_BUDGET_BYTES)
            .unwrap();
        assert_eq!((frame.image.width, frame.image.height), (w, h));
        assert_eq!(frame.image.data.len(), 3 * (w * h) as usize);
        let fc = bundle.feature_camera(&cam).intrinsics;
        assert_eq!((fc.width, fc.height), (w.div_ceil(8), h.div_ceil(8)));
    }
}

#[test]
fn the_feature_camera_is_the_frame_scaled_by_the_pooling_factor() {
    let bundle = compressed_bundle();
    for (w, h) in [(64, 48), (37, 29)] {
        let cam = camera(w, h);
        let fc = bundle.feature_camera(&cam);
        assert_eq!(fc.camera_from_world, cam.camera_from_world);
        let (k, kf) = (cam.intrinsics, fc.intrinsics);
        // Scaling by a power of two is exact in floating point.
        for (a, b) in [(k.fx, kf.fx), (k.fy, kf.fy), (k.cx, kf.cx), (k.cy, kf.cy)] {
            assert_eq!(b * 8.0, a);
        }
    }
}

/// A bundle with `supersample` 4 renders the mean of each 4x4 block of the render 4 times finer
/// (the feature camera scaled by exactly 4); its fingerprint differs from the plain bundle's; it
/// saves and loads with the factor; a `bundle.json` with a factor of 0 or 17 is refused.
#[test]
fn a_supersampled_bundle_renders_block_means_and_keeps_its_factor() {
    let plain = compressed_bundle();
    let mut bundle = compressed_bundle();
    bundle.info.supersample = 4;
    let cam = camera(37, 29);
    let fc = bundle.feature_camera(&cam);
    let (w, h) = (fc.intrinsics.width, fc.intrinsics.height);
    let map = bundle.render_features(&cam).unwrap();
    assert_eq!(map.dim(), (1, F, h as usize, w as usize));
    let fine = runtime::frame::render_feature_map(
        &bundle.scene,
        &fc.resized(4 * w, 4 * h),
        (4 * w, 4 * h),
        &bundle.info.feature_background,
        1,
    )
    .unwrap();
    for ((_, c, y, x), &v) in map.indexed_iter() {
        let mut sum = 0.0f32;
        for j in 0..4 {
            for i in 0..4 {
                sum += fine[[0, c, 4 * y + j, 4 * x + i]];
            }
        }
        // 16 additions in f32 in another order than the block mean's.
        assert!(
            (v - sum / 16.0).abs() <= 1e-5 * (1.0 + v.abs()),
            "({x}, {y}, {c})"
        );
    }
    assert_ne!(map, plain.render_features(&cam).unwrap());
    assert_ne!(bundle.fingerprint(), plain.fingerprint());

    let dir = dsgs_testkit::scratch_dir("runtime-supersample", "bundle");
    bundle.save(&dir).unwrap();
    let loaded = SceneBundle::load(&dir).unwrap();
    assert_eq!(loaded.info.supersample, 4);
    assert_eq!(loaded.fingerprint(), bundle.fingerprint());
    let json = dir.join("bundle.json");
    let text = std::fs::read_to_string(&json).unwrap();
    for bad in [0, 17] {
        std::fs::write(
            &json,
            text.replace("\"supersample\": 4", &format!("\"supersample\": {bad}")),
        )
        .unwrap();
        let err = SceneBundle::load(&dir).unwrap_err().to_string();
        assert!(
            err.contains("bundle.json") && err.contains(&format!("supersample is {bad}")),
            "{err}"
        );
    }
    // Older bundles have no factor: one sample per feature pixel.
    std::fs::write(&json, text.replace(",\n  \"supersample\": 4", "")).unwrap();
    assert_eq!(SceneBundle::load(&dir).unwrap().info.supersample, 1);
    std::fs::remove_dir_all(&dir).ok();
}

/// Training aligns the encoder's own feature map (`floor(side / 8)` pixels a side) and
/// stylization decodes one pixel more where a side is not a multiple of 8: both render through
/// `feature_map_camera`, so the training map is the top-left of the stylization map, and a
/// Gaussian lands on the same feature pixel in both.
#[test]
fn training_and_stylization_render_features_on_one_grid() {
    let bundle = compressed_bundle();
    for (w, h) in [(90, 160), (37, 29), (64, 48)] {
        let cam = camera(w, h);
        let own = (w / 8, h / 8);
        let train_cam =
            runtime::bundle::feature_map_camera(&bundle.encoder, Variant::Standard, &cam, own);
        let k = bundle.feature_camera(&cam).intrinsics;
        let t = train_cam.intrinsics;
        assert_eq!((t.fx, t.fy, t.cx, t.cy), (k.fx, k.fy, k.cx, k.cy));
        let trained = runtime::frame::render_feature_map(
            &bundle.scene,
            &train_cam,
            own,
            &bundle.info.feature_background,
            1,
        )
        .unwrap();
        let styled = bundle.render_features(&cam).unwrap();
        let (ow, oh) = (own.0 as usize, own.1 as usize);
        // Each pixel blends the same Gaussians in the same order on either image size.
        assert_eq!(
            trained,
            styled.slice(ndarray::s![.., .., ..oh, ..ow]).to_owned(),
            "{w}x{h}"
        );
    }
}
