//! One million Gaussians at 1920x1080: forward and backward complete with bounded memory.
//! Seconds in release, so part of the full test set only:
//! `cargo test --release -p dsgs-raster --test large -- --include-ignored`.

mod common;

use common::Rng;
use raster::{rasterize, rasterize_backward, Cotangents, Splats};

#[test]
#[ignore = "slow: in the full set (-- --include-ignored)"]
fn a_million_gaussians_at_1080p() {
    let (w, h, n, d) = (1920u32, 1080u32, 1_000_000usize, 3usize);
    let mut rng = Rng(5);
    let mut means2d = Vec::with_capacity(n);
    let mut conics = Vec::with_capacity(n);
    let mut radii = Vec::with_capacity(n);
    let mut depths = Vec::with_capacity(n);
    let mut opacities = Vec::with_capacity(n);
    for _ in 0..n {
        means2d.push([
            rng.uniform(0.0, w as f64) as f32,
            rng.uniform(0.0, h as f64) as f32,
        ]);
        // Isotropic, standard deviation 1..4 px (plus the 0.3 px^2 dilation).
        let var = rng.uniform(1.0, 4.0).powi(2) + 0.3;
        conics.push([(1.0 / var) as f32, 0.0, (1.0 / var) as f32]);
        let r = (3.33 * var.sqrt()).ceil() as u32;
        radii.push([r, r]);
        depths.push(rng.uniform(1.0, 50.0) as f32);
        opacities.push(rng.uniform(0.05, 0.9) as f32);
    }
    let channels: Vec<f32> = (0..n * d).map(|_| rng.uniform(0.0, 1.0) as f32).collect();
    let splats = Splats {
        means2d: &means2d,
        conics: &conics,
        depths: &depths,
        radii: &radii,
        opacities: &opacities,
        channels: &channels,
        channel_count: d,
    };
    let bg = [0.0f32; 3];
    let t0 = std::time::Instant::now();
    let out = rasterize(&splats, w, h, &bg).unwrap();
    let t_fwd = t0.elapsed();
    let pixels = (w * h) as usize;
    let v = vec![1e-3f32; pixels * d];
    let t1 = std::time::Instant::now();
    let g = rasterize_backward(
        &splats,
        &out.bins,
        &bg,
        &Cotangents {
            image: &v,
            alpha: None,
            depth: None,
        },
    )
    .unwrap();
    let t_bwd = t1.elapsed();
    let covered = out.alpha.iter().filter(|&&a| a > 0.5).count() as f64 / pixels as f64;
    eprintln!(
        "1M Gaussians at 1080p: {} intersections ({} MiB of bins), {} blended pairs, \
         coverage {:.3}, forward {:.2?}, backward {:.2?}",
        out.bins.intersection_count(),
        out.bins.memory_bytes() >> 20,
        out.blended_pairs(),
        covered,
        t_fwd,
        t_bwd
    );
    assert!(covered > 0.99);
    assert!(out.image.iter().all(|v| v.is_finite()));
    assert!(g.means2d.iter().flatten().all(|v| v.is_finite()));
    assert!(g.channels.iter().any(|&c| c != 0.0));
}
