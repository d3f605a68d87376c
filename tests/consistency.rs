//! Acceptance of the multi-view consistency metric on rendered geometry.
//!
//! The scene is an opaque fronto-parallel plane `z = 3` of 100 x 100 flat Gaussians (SH degree 0,
//! a Lambertian surface) and the cameras are translations of one another parallel to it, so
//! every Gaussian keeps its depth and the rasterizer's normalised depth is exactly 3 up to f32
//! rounding. Three sequences are compared along 9 cameras:
//!
//! * a perfectly consistent rendering: every view shows the surface's texture, an affine colour
//!   field of the world point, at the point its own rendered depth back-projects to. Bilinear
//!   sampling reproduces an affine function exactly, so the warp must give RMSE 0 up to f32
//!   rounding: values below 1 stored in f32 err by at most 2^-24 (6e-8) each, and the f32 depth
//!   moves the back-projected point by a relative 6e-8, so 1e-6 bounds the RMSE;
//! * the same with independent uniform noise in [-0.1, 0.1] added to each view: the expected
//!   RMSE is `sigma sqrt(1 + sum w^2)` with `sigma = 0.2 / sqrt(12)` and the bilinear weights'
//!   `sum w^2` in [0.25, 1], i.e. between 0.0645 and 0.0816;
//! * the plain colour renders of the plane with the texture sampled at its Gaussians' centres:
//!   nearly consistent (the blend of neighbouring Gaussians shifts slightly with the camera);
//!   measured RMSE about 2e-5.

mod common;

use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::{DMat3, DVec3};
use pipeline::consistency::{sequence_consistency, DepthView, WarpOptions};
use pipeline::image_io::RgbImage;
use pipeline::render::render_colour;

const Z: f64 = 3.0;
const SH_C0: f32 = 0.282_094_8;

fn texture(p: DVec3) -> [f32; 3] {
    [
        (0.5 + 0.08 * p.x) as f32,
        (0.45 - 0.05 * p.y + 0.03 * p.x) as f32,
        (0.4 + 0.02 * p.y) as f32,
    ]
}

fn plane() -> FeatureGaussians<f32> {
    let n = 100;
    let spacing = 0.05f32;
    let mut s = FeatureGaussians::<f32> {
        sh_degree: 0,
        ..Default::default()
    };
    for i in 0..n {
        for j in 0..n {
            let x = (i as f32 - 49.5) * spacing;
            let y = (j as f32 - 49.5) * spacing;
            s.means.push([x, y, Z as f32]);
            s.log_scales
                .push([(0.6 * spacing).ln(), (0.6 * spacing).ln(), 0.001f32.ln()]);
            s.quats.push([1.0, 0.0, 0.0, 0.0]);
            s.opacity_logits.push(3.0);
            let c = texture(DVec3::new(x as f64, y as f64, Z));
            s.sh.push(c.map(|v| (v - 0.5) / SH_C0));
        }
    }
    s
}

fn cameras() -> Vec<Camera> {
    let k = Intrinsics {
        fx: 40.0,
        fy: 40.0,
        cx: 24.0,
        cy: 24.0,
        width: 48,
        height: 48,
    };
    (0..9)
        .map(|i| {
            let c = DVec3::new(0.031 * i as f64, 0.013 * i as f64, 0.0);
            Camera::from_rotation_center(k, DMat3::IDENTITY, c)
        })
        .collect()
}

/// The texture at the point each pixel's rendered depth back-projects to.
fn painted(cam: &Camera, depth: &[f32]) -> RgbImage {
    let k = cam.intrinsics;
    let mut data = Vec::new();
    for (p, &d) in depth.iter().enumerate() {
        let (x, y) = ((p % 48) as f64 + 0.5, (p / 48) as f64 + 0.5);
        let d = d as f64;
        let cam_pt = DVec3::new((x - k.cx) / k.fx * d, (y - k.cy) / k.fy * d, d);
        data.extend(texture(cam.world_from_camera().transform_point3(cam_pt)));
    }
    RgbImage {
        width: 48,
        height: 48,
        data,
    }
}

#[test]
fn consistent_renders_score_zero_and_noise_does_not() {
    let scene = plane();
    let cams = cameras();
    let renders: Vec<_> = cams
        .iter()
        .map(|c| render_colour(&scene, c, [0.0; 3]).unwrap())
        .collect();
    // The plane covers every pixel opaquely at depth 3.
    for r in &renders {
        assert!(r.alpha.iter().all(|&a| a > 0.99));
        assert!(r.depth.iter().all(|&d| (d as f64 - Z).abs() < 1e-5));
    }
    let views: Vec<DepthView> = cams
        .iter()
        .zip(&renders)
        .map(|(camera, r)| DepthView {
            camera,
            depth: &r.depth,
            alpha: &r.alpha,
        })
        .collect();
    let (encoder, _) = common::wct_relu3();
    let opts = WarpOptions::default();

    let exact: Vec<RgbImage> = cams
        .iter()
        .zip(&renders)
        .map(|(c, r)| painted(c, &r.depth))
        .collect();
    let mut rng = common::Lcg(11);
    let noisy: Vec<RgbImage> = exact
        .iter()
        .map(|img| RgbImage {
            width: img.width,
            height: img.height,
            data: img
                .data
                .iter()
                .map(|v| v + 0.2 * rng.uniform() - 0.1)
                .collect(),
        })
        .collect();
    let rendered: Vec<RgbImage> = renders.iter().map(|r| r.image.clone()).collect();

    for offset in [1, 7] {
        let e = sequence_consistency(&exact, &views, offset, &opts, Some(&encoder)).unwrap();
        let n = sequence_consistency(&noisy, &views, offset, &opts, Some(&encoder)).unwrap();
        let r = sequence_consistency(&rendered, &views, offset, &opts, Some(&encoder)).unwrap();
        println!("offset {offset}: consistent {e:?}\n  noisy {n:?}\n  rendered {r:?}");
        assert_eq!(e.pairs, 9 - offset);
        // Shifts of up to 7 x (0.78, 0.17) pixels keep most of each view comparable.
        assert!(e.valid_fraction > 0.8, "{}", e.valid_fraction);
        let (ermse, nrmse, rrmse) = (e.rmse.unwrap(), n.rmse.unwrap(), r.rmse.unwrap());
        assert!(ermse < 1e-6, "consistent RMSE {ermse}");
        assert!(
            (0.0645 * 0.95..=0.0816 * 1.05).contains(&nrmse),
            "noisy RMSE {nrmse}"
        );
        // Neighbouring Gaussians differ in colour by at most |grad| * spacing =
        // sqrt(0.08^2 + 0.03^2 + 0.02^2) * 0.05 = 0.0044, which bounds how much a shift of the
        // blend weights can change a pixel.
        assert!(rrmse < 0.0044, "rendered RMSE {rrmse}");
        let (ep, np) = (e.perceptual.unwrap(), n.perceptual.unwrap());
        // The perceptual distance of identical images is 0; f32 rounding of the inputs leaves
        // far less than the noise's distance.
        assert!(ep < 1e-4 * np, "perceptual {ep} vs noise {np}");
    }
}
