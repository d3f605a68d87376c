//! The per-Gaussian work of one geometry iteration outside the rasterizer, on 100,000 f32
//! Gaussians of SH degree 3: the Adam step of every group; the SH colour backward followed by
//! that step (`sh_backward_then_adam`, the trainer's path before `step_from_colours`) against
//! the backward inside the SH groups' Adam pass (`sh_backward_in_adam`); and the loss (L1 +
//! D-SSIM with its gradient) of a 200x200 render.
//!
//! Inputs are generated deterministically (a 64-bit LCG).

use criterion::{criterion_group, criterion_main, Criterion};
use gaussian::FeatureGaussians;
use std::hint::black_box;
use train::loss::photometric_loss_with_grad;
use train::{AdamConfig, ColourGrads, GaussianGrads, GaussianModel, ImageShape, LearningRates};

const N: usize = 100_000;

/// Knuth's MMIX LCG; the top 24 bits as a uniform number in [lo, hi).
struct Lcg(u64);

impl Lcg {
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        lo + (hi - lo) * ((self.0 >> 40) as f32 / (1u64 << 24) as f32)
    }
    fn vec<const K: usize>(&mut self, n: usize, lo: f32, hi: f32) -> Vec<[f32; K]> {
        (0..n)
            .map(|_| std::array::from_fn(|_| self.range(lo, hi)))
            .collect()
    }
}

fn bench(c: &mut Criterion) {
    let mut r = Lcg(0x5eed);
    let scene = FeatureGaussians::<f32> {
        means: r.vec(N, -1.0, 1.0),
        log_scales: r.vec(N, -6.0, -3.0),
        quats: r.vec(N, -1.0, 1.0),
        opacity_logits: (0..N).map(|_| r.range(-2.0, 2.0)).collect(),
        sh: r.vec(N * 16, -0.3, 0.3),
        sh_degree: 3,
        ..FeatureGaussians::default()
    };
    let cfg = AdamConfig {
        eps: 1e-15,
        ..AdamConfig::default()
    };
    let mut model = GaussianModel::new(scene, &LearningRates::default(), cfg, 1.0).unwrap();
    let means = r.vec(N, -1e-3, 1e-3);
    let quats = r.vec(N, -1e-3, 1e-3);
    let log_scales = r.vec(N, -1e-3, 1e-3);
    let opacity_logits: Vec<f32> = (0..N).map(|_| r.range(-1e-3, 1e-3)).collect();
    let sh = r.vec(N * 16, -1e-4, 1e-4);
    let grads = GaussianGrads {
        means: &means,
        quats: &quats,
        log_scales: &log_scales,
        opacity_logits: &opacity_logits,
        sh: &sh,
        coeffs_per_gaussian: 16,
    };
    let mut g = c.benchmark_group("geometry_step_100k_f32");
    g.sample_size(30);
    g.bench_function("adam_step", |b| {
        b.iter(|| model.step(black_box(&grads)).unwrap())
    });

    // Colour cotangents with a zero row in four (Gaussians outside the view), seen from a
    // camera outside the unit cube.
    let center = [0.3f32, -2.5, 1.7];
    let mut colours: Vec<[f32; 3]> = r.vec(N, -1e-2, 1e-2);
    for c in colours.iter_mut().step_by(4) {
        *c = [0.0; 3];
    }
    g.bench_function("sh_backward_then_adam", |b| {
        b.iter(|| {
            let s = &model.scene;
            let (d_sh, d_means) =
                gaussian::sh_colors_backward(3, 16, &s.sh, &s.means, center, &colours);
            let mut all_means = means.clone();
            raster::add_view_direction_term(&mut all_means, &d_means);
            let grads = GaussianGrads {
                means: &all_means,
                sh: &d_sh,
                ..grads
            };
            model.step(black_box(&grads)).unwrap()
        })
    });
    g.bench_function("sh_backward_in_adam", |b| {
        b.iter(|| {
            let grads = ColourGrads {
                means: &means,
                quats: &quats,
                log_scales: &log_scales,
                opacity_logits: &opacity_logits,
                colours: &colours,
                sh_degree: 3,
                camera_center: center,
            };
            model.step_from_colours(black_box(&grads), &[]).unwrap()
        })
    });

    let shape = ImageShape::new(200, 200, 3);
    let render: Vec<f32> = (0..shape.len()).map(|_| r.range(0.0, 1.0)).collect();
    let target: Vec<f32> = (0..shape.len()).map(|_| r.range(0.0, 1.0)).collect();
    g.bench_function("loss_with_grad_200x200", |b| {
        b.iter(|| photometric_loss_with_grad(black_box(&render), &target, shape, 0.2).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
