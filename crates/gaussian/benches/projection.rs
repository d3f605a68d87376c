//! Projection (forward and backward) and SH colours over one million f32 Gaussians.
//!
//! The Gaussians are generated deterministically (a 64-bit LCG) in a box in front of a
//! 1280x720 camera, with scales and rotations like those of a trained scene.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use gaussian::project::{project, project_backward, ProjectSettings};
use gaussian::sh::{sh_colors, sh_colors_backward};
use gaussian::{Camera, Intrinsics};
use glam::{DMat3, DVec3};
use std::hint::black_box;

const N: usize = 1_000_000;

/// Knuth's MMIX LCG; the top 24 bits as a uniform number in [0, 1).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }
}

struct Scene {
    camera: Camera,
    means: Vec<[f32; 3]>,
    quats: Vec<[f32; 4]>,
    log_scales: Vec<[f32; 3]>,
    sh: Vec<[f32; 3]>,
}

fn scene() -> Scene {
    let mut r = Lcg(0x5eed);
    let camera = Camera::from_rotation_center(
        Intrinsics {
            fx: 1100.0,
            fy: 1100.0,
            cx: 640.0,
            cy: 360.0,
            width: 1280,
            height: 720,
        },
        DMat3::IDENTITY,
        DVec3::new(0.0, 0.0, -6.0),
    );
    let means = (0..N)
        .map(|_| [r.range(-4.0, 4.0), r.range(-3.0, 3.0), r.range(-3.0, 5.0)])
        .collect();
    let quats = (0..N)
        .map(|_| {
            [
                r.range(-1.0, 1.0),
                r.range(-1.0, 1.0),
                r.range(-1.0, 1.0),
                r.range(-1.0, 1.0),
            ]
        })
        .collect();
    let log_scales = (0..N)
        .map(|_| {
            [
                r.range(-6.0, -3.0),
                r.range(-6.0, -3.0),
                r.range(-6.0, -3.0),
            ]
        })
        .collect();
    let sh = (0..N * 16)
        .map(|_| [r.range(-0.3, 0.3), r.range(-0.3, 0.3), r.range(-0.3, 0.3)])
        .collect();
    Scene {
        camera,
        means,
        quats,
        log_scales,
        sh,
    }
}

fn bench(c: &mut Criterion) {
    let s = scene();
    let settings = ProjectSettings::default();
    let mut g = c.benchmark_group("projection_1M_f32");
    g.throughput(Throughput::Elements(N as u64));
    g.sample_size(20);
    g.bench_function("forward", |b| {
        b.iter(|| project(&s.camera, &s.means, &s.quats, &s.log_scales, &settings))
    });
    let p = project(&s.camera, &s.means, &s.quats, &s.log_scales, &settings);
    let visible = (0..N).filter(|&i| p.is_visible(i)).count();
    eprintln!("{visible} of {N} Gaussians visible");
    let v_m2d = vec![[0.1f32, -0.2]; N];
    let v_con = vec![[0.01f32, 0.02, -0.01]; N];
    let v_d = vec![0.05f32; N];
    g.bench_function("backward", |b| {
        b.iter(|| {
            project_backward(
                &s.camera,
                &s.means,
                &s.quats,
                &s.log_scales,
                &settings,
                black_box(&p),
                &v_m2d,
                &v_con,
                &v_d,
            )
        })
    });
    let center = s.camera.center().as_vec3().to_array();
    g.bench_function("sh3_colors", |b| {
        b.iter(|| sh_colors(3, 16, &s.sh, &s.means, black_box(center)))
    });
    let v_col = vec![[0.1f32, 0.2, 0.3]; N];
    g.bench_function("sh3_colors_backward", |b| {
        b.iter(|| sh_colors_backward(3, 16, &s.sh, &s.means, black_box(center), &v_col))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
