//! Synthetic scenes and views, the oracle's networks and small image sets for the training
//! tests.

#![allow(dead_code)]

use dsgs_testkit::nets::networks;
use dsgs_testkit::oracle::nets_fixture;
use dsgs_testkit::shared_path;
use gaussian::camera_path::look_at;
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DVec3;
use ndarray::{Array1, Array4};
use nets::{ConvLayer, Decoder, Encoder, Lifter, Resolution};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use runtime::bundle::{BundleInfo, CameraRecord, SceneBundle};
use train::geometry::View;
use train::image_folder::ImageSet;
use train::render::render_color;
use train::Variant;

/// A known scene: `n` opaque-ish Gaussians of degree-0 colour in the cube `[-0.8, 0.8]^3`.
pub fn synthetic_scene(n: usize, seed: u64) -> FeatureGaussians<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut g = FeatureGaussians {
        sh_degree: 0,
        ..Default::default()
    };
    for _ in 0..n {
        g.means
            .push(std::array::from_fn(|_| rng.random_range(-0.8f32..0.8)));
        g.log_scales.push(std::array::from_fn(|_| {
            rng.random_range(0.04f32..0.15).ln()
        }));
        g.quats
            .push(std::array::from_fn(|_| rng.random_range(-1.0f32..1.0)));
        g.opacity_logits.push(rng.random_range(0.5f32..3.0));
        // colour in [0.1, 0.9]: DC = (rgb - 0.5) / C0
        g.sh.push(std::array::from_fn(|_| {
            (rng.random_range(0.1f32..0.9) - 0.5) / 0.282_094_8
        }));
    }
    g
}

/// `count` cameras on a sphere of radius `radius` around the origin (a Fibonacci spiral, so
/// consecutive cameras are spread out), `size x size` pixels.
pub fn sphere_cameras(count: usize, radius: f64, size: u32, focal: f64) -> Vec<Camera> {
    let k = Intrinsics {
        fx: focal,
        fy: focal,
        cx: size as f64 / 2.0,
        cy: size as f64 / 2.0,
        width: size,
        height: size,
    };
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|i| {
            // elevations in (-0.85, 0.85) to keep away from the poles of the up vector
            let z = 0.85 * (1.0 - 2.0 * (i as f64 + 0.5) / count as f64);
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            let eye = DVec3::new(r * phi.cos(), r * phi.sin(), z) * radius;
            look_at(k, eye, DVec3::ZERO, DVec3::Z).expect("non-degenerate camera")
        })
        .collect()
}

/// Ground-truth views of `scene` rendered with the rasterizer.
pub fn render_views(
    scene: &FeatureGaussians<f32>,
    cameras: &[Camera],
    background: [f32; 3],
) -> Vec<View> {
    cameras
        .iter()
        .enumerate()
        .map(|(i, c)| View {
            name: format!("view{i:03}"),
            camera: *c,
            image: render_color(c, scene, scene.sh_degree, background)
                .expect("render")
                .raster
                .image,
        })
        .collect()
}

/// The oracle's encoder (to relu4_1) and decoder in `f32`, standard variant (1/8 of the VGG
/// widths).
pub fn fixture_networks() -> (Encoder<f32>, Decoder<f32>) {
    networks(&nets_fixture(), Resolution::Standard)
}

/// A few shared images `{dir}/{name}` (relative to the shared directory), loaded once and shrunk
/// to the short side `short_side` so that every step is cheap.
pub fn shared_images(dir: &str, names: &[&str], short_side: u32) -> ImageSet {
    let set = ImageSet::from_files(
        names
            .iter()
            .map(|n| shared_path(&format!("{dir}/{n}")))
            .collect(),
    )
    .unwrap();
    let images = (0..set.len())
        .map(|i| {
            (
                names[i].to_string(),
                set.load_resized(i, short_side).unwrap(),
            )
        })
        .collect();
    ImageSet::from_images(images).unwrap()
}

/// The bits of every weight and bias of the layers, in order (for bit-identity checks).
pub fn net_bits<'a>(layers: impl Iterator<Item = &'a ConvLayer<f32>>) -> Vec<u32> {
    layers
        .flat_map(|l| l.weight.iter().chain(l.bias.iter()).map(|v| v.to_bits()))
        .collect()
}

/// A small valid scene bundle: the oracle's networks, 50 Gaussians with `features` feature
/// channels, a fixed lifter, identity scene statistics and four 32x32 sphere cameras (the last
/// held out, named `view000` to `view003`).
pub fn small_bundle(features: usize) -> SceneBundle {
    let (encoder, decoder) = fixture_networks();
    let c = *encoder.widths().last().unwrap();
    let mut scene = synthetic_scene(50, 3);
    scene.feature_dim = features;
    scene.features = (0..scene.len() * features)
        .map(|i| (i % 7) as f32 / 7.0)
        .collect();
    let lifter = Lifter::new(
        Array4::from_shape_fn((c, features, 1, 1), |(o, i, _, _)| {
            0.1 * ((o + i) % 3) as f32
        }),
        Array1::zeros(c),
    )
    .unwrap();
    let records = sphere_cameras(4, 4.0, 32, 36.0)
        .iter()
        .enumerate()
        .map(|(i, cam)| CameraRecord::new(format!("view{i:03}"), cam, i == 3))
        .collect();
    let info = BundleInfo::new(
        &encoder,
        Variant::Standard,
        features,
        [0.0; 3],
        (vec![0.0; c], vec![1.0; c]),
        records,
    );
    SceneBundle {
        scene,
        encoder,
        decoder,
        lifter,
        info,
    }
}
