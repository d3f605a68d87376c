//! Renders the official trained 3DGS scene (`data/gaussians/trained_9080.ply`, no cameras) from an
//! orbit camera placed from the scene's robust bounds, and writes the image as a PNG into the
//! cargo target's temporary directory for inspection.

use dsgs_testkit::shared_path;
use gaussian::camera_path::look_at;
use gaussian::ply::load_ply;
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::{DQuat, DVec3};
use raster::{render, Channels, RenderOptions};

/// The `q`-quantile of one coordinate of the means.
fn quantile(s: &FeatureGaussians<f32>, axis: usize, q: f64) -> f64 {
    let mut v: Vec<f64> = s.means.iter().map(|m| m[axis] as f64).collect();
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A camera on an orbit around the scene's robust centre (the per-axis medians of the means).
///
/// The file carries no cameras. 3DGS scenes live in COLMAP's world frame, whose up axis is
/// roughly `-y`, and this capture is an indoor, forward-facing one: its content lies ahead (`+z`)
/// of the world origin, near which the capture cameras were, while the Gaussians span hundreds of
/// units around it (an outside view would look at the backs of walls and at large floaters). So
/// the orbit runs about the vertical axis through the centre at the distance from the centre to
/// the origin, starting at the origin (`azimuth` 0), and the camera looks at the centre with a
/// 60 degree horizontal field of view.
fn orbit_camera(s: &FeatureGaussians<f32>, width: u32, height: u32, azimuth: f64) -> Camera {
    let center = DVec3::new(
        quantile(s, 0, 0.5),
        quantile(s, 1, 0.5),
        quantile(s, 2, 0.5),
    );
    let up = DVec3::new(0.0, -1.0, 0.0);
    let offset = DQuat::from_axis_angle(up, azimuth) * -center;
    let focal = 0.5 * width as f64 / (30f64.to_radians()).tan();
    let intrinsics = Intrinsics {
        fx: focal,
        fy: focal,
        cx: 0.5 * width as f64,
        cy: 0.5 * height as f64,
        width,
        height,
    };
    look_at(intrinsics, center + offset, center, up).expect("view axis is not vertical")
}

/// Writes an RGB image atomically (temporary file in the same directory, then rename).
fn write_png(path: &std::path::Path, width: u32, height: u32, rgb: &[f32]) {
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let img = image::RgbImage::from_raw(width, height, bytes).unwrap();
    let tmp = path.with_extension("png.tmp");
    img.save_with_format(&tmp, image::ImageFormat::Png).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

#[test]
fn trained_scene_renders_to_a_plausible_image() {
    let path = shared_path("data/gaussians/trained_9080.ply");
    let scene = load_ply(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(scene.len(), 9080);
    let (width, height) = (480u32, 360u32);
    let opts = RenderOptions::new(
        Channels::Color {
            sh_degree: scene.sh_degree,
        },
        vec![0.0f32; 3],
    );
    for (k, azimuth) in [-15.0f64, 0.0, 15.0].iter().enumerate() {
        let camera = orbit_camera(&scene, width, height, azimuth.to_radians());
        let r = render(&camera, &scene, &opts).unwrap();
        let img = &r.raster;
        let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("trained_9080_orbit{k}.png"));
        write_png(&out, width, height, &img.image);
        assert!(img.image.iter().all(|v| v.is_finite()), "non-finite colour");
        assert!(img.alpha.iter().all(|&a| (0.0..=1.0).contains(&a)));
        let covered =
            img.alpha.iter().filter(|&&a| a > 0.5).count() as f64 / img.alpha.len() as f64;
        let visible = r.projected.radii.iter().filter(|r| r[0] > 0).count();
        // Luminance spread: a plausible view has structure, not one flat colour.
        let lum: Vec<f64> = img
            .image
            .chunks_exact(3)
            .map(|p| (0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2]) as f64)
            .collect();
        let mean = lum.iter().sum::<f64>() / lum.len() as f64;
        let std =
            (lum.iter().map(|l| (l - mean) * (l - mean)).sum::<f64>() / lum.len() as f64).sqrt();
        eprintln!(
            "view {k}: {visible} visible Gaussians, {:.1}% of pixels with alpha > 0.5, \
             luminance {mean:.3} +- {std:.3}, {} blended pairs, written to {}",
            100.0 * covered,
            img.blended_pairs(),
            out.display()
        );
        // Seen from inside, the room fills the frame.
        assert!(covered > 0.9, "coverage {covered}");
        assert!(visible > 1000, "only {visible} Gaussians visible");
        assert!(
            mean > 0.2 && mean < 0.9 && std > 0.03,
            "flat image: {mean} +- {std}"
        );
    }
}
