//! Forward and backward rasterization throughput in `f32`, for 3, 35 and 64 channels, 100k and
//! 1M Gaussians, 256x256 and 800x800 images, on 1 and 2 threads, with the scalar reference tile
//! loops and with the vector lane kernels at the best instruction set of the machine.
//!
//! Throughput is reported in blended Gaussian-pixel pairs per second (criterion's "elements").
//! Benchmark ids are `{forward|backward}/{scalar|simd}/{D}ch/{N}/{size}/t{threads}`; pass a
//! filter to run a subset, e.g. `cargo bench -p raster --bench raster -- forward/simd/35ch`.
//! `benches/side_by_side.sh raster` runs the two kernels in one run and prints their ratios.
//!
//! `depth_order/{f32|f64}/{N}/t{threads}` times the depth sort of binning alone on `N` uniform
//! depths: `f32` depths take the parallel 32-bit-key passes, the same depths as `f64` the
//! one-part 64-bit-key passes (the same order; the baseline in the same run).
//!
//! `binning/100k/256/t{threads}` times `TileBins::new` (tile rectangles, depth order and
//! intersection lists) on the scene of the 100k, 256x256 pass benchmarks.
//!
//! The benchmark runs with the `dsgs` binary's allocator (`base::memory::HugePageAdvice`);
//! `benches/side_by_side.sh` adds its heap setting.
//!
//! Scenes are synthetic projected Gaussians: means uniform over the image, random orientations
//! and anisotropy, standard deviations chosen so that the summed 2-sigma footprints cover every
//! pixel about 20 times on average (like a trained scene seen from a training view), opacities
//! in `[0.1, 0.9]`, depths uniform.

#[path = "../tests/common/mod.rs"]
mod common;

use common::{ellipse, Rng, Scene2d};
use criterion::{
    criterion_group, criterion_main, BenchmarkId, Criterion, SamplingMode, Throughput,
};
use raster::{
    rasterize, rasterize_backward_with, rasterize_binned_with, Cotangents, Kernel,
    DEFAULT_GRADIENT_BUFFER_VALUES,
};

/// The `dsgs` binary's allocator: large blocks advised for huge pages, so that the passes'
/// random reads of per-Gaussian data do not miss the TLB more than in the program.
#[global_allocator]
static ALLOCATOR: base::memory::HugePageAdvice = base::memory::HugePageAdvice;

fn scene(n: usize, size: u32, d: usize) -> Scene2d<f32> {
    let mut rng = Rng(n as u64 ^ ((size as u64) << 32) ^ d as u64);
    let (w, h) = (size as f64, size as f64);
    // n * pi * (2 sigma)^2 = 20 * w * h
    let sigma = (20.0 * w * h / (4.0 * std::f64::consts::PI * n as f64)).sqrt();
    let mut s = Scene2d {
        width: size,
        height: size,
        channel_count: d,
        means2d: Vec::with_capacity(n),
        conics: Vec::with_capacity(n),
        depths: Vec::with_capacity(n),
        radii: Vec::with_capacity(n),
        opacities: Vec::with_capacity(n),
        channels: Vec::with_capacity(n * d),
        background: vec![0.5; d],
    };
    for _ in 0..n {
        s.means2d
            .push([rng.uniform(0.0, w) as f32, rng.uniform(0.0, h) as f32]);
        let aniso = rng.uniform(0.5, 2.0);
        let (l1, l2) = ((sigma * aniso).powi(2) + 0.3, (sigma / aniso).powi(2) + 0.3);
        let (conic, radii) = ellipse(l1, l2, rng.uniform(0.0, std::f64::consts::PI), 3.33);
        s.conics.push(conic.map(|v| v as f32));
        s.radii.push(radii);
        s.depths.push(rng.uniform(1.0, 100.0) as f32);
        s.opacities.push(rng.uniform(0.1, 0.9) as f32);
        for _ in 0..d {
            s.channels.push(rng.uniform(0.0, 1.0) as f32);
        }
    }
    s
}

fn bench(c: &mut Criterion) {
    let pools: Vec<(usize, rayon::ThreadPool)> = [1usize, 2]
        .into_iter()
        .map(|t| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .unwrap();
            (t, pool)
        })
        .collect();
    // The scalar reference loops and the lane kernels at the best instruction set (or the one
    // `DSGS_KERNEL` names).
    let kernels = [
        ("scalar", Kernel::Scalar),
        ("simd", Kernel::auto().expect("DSGS_KERNEL")),
    ];
    eprintln!("simd kernel: {}", kernels[1].1.name());
    for n in [100_000usize, 1_000_000] {
        for size in [256u32, 800] {
            for d in [3usize, 35, 64] {
                let tag = format!("{d}ch/{}k/{size}", n / 1000);
                // Build the scene only when some benchmark of this configuration is selected.
                let wanted = |pass: &str| {
                    let args: Vec<String> = std::env::args().skip(1).collect();
                    let filters: Vec<&String> =
                        args.iter().filter(|a| !a.starts_with('-')).collect();
                    let ids: Vec<String> = kernels
                        .iter()
                        .flat_map(|(k, _)| {
                            pools
                                .iter()
                                .map(|(t, _)| format!("{pass}/{k}/{tag}/t{t}"))
                                .collect::<Vec<_>>()
                        })
                        .collect();
                    filters.is_empty()
                        || filters
                            .iter()
                            .any(|f| ids.iter().any(|id| id.contains(f.as_str())))
                };
                if !wanted("forward") && !wanted("backward") {
                    continue;
                }
                let s = scene(n, size, d);
                let out = rasterize(&s.splats(), s.width, s.height, &s.background).unwrap();
                let pairs = out.blended_pairs();
                let pixels = (size * size) as usize;
                let v_image = vec![0.01f32; pixels * d];
                let v_alpha = vec![0.01f32; pixels];
                let v_depth = vec![0.001f32; pixels];
                eprintln!(
                    "{tag}: {} intersections, {pairs} blended pairs ({:.1} per pixel)",
                    out.bins.intersection_count(),
                    pairs as f64 / pixels as f64
                );
                for pass in ["forward", "backward"] {
                    let mut g = c.benchmark_group(pass);
                    g.sampling_mode(SamplingMode::Flat)
                        .sample_size(10)
                        .warm_up_time(std::time::Duration::from_millis(200))
                        .measurement_time(std::time::Duration::from_secs(2))
                        .throughput(Throughput::Elements(pairs));
                    for &(name, kernel) in &kernels {
                        for (t, pool) in &pools {
                            let id = BenchmarkId::new(format!("{name}/{tag}"), format!("t{t}"));
                            if pass == "forward" {
                                g.bench_function(id, |b| {
                                    pool.install(|| {
                                        b.iter(|| {
                                            rasterize_binned_with(
                                                &s.splats(),
                                                s.tile_bins(),
                                                &s.background,
                                                kernel,
                                            )
                                            .unwrap()
                                        })
                                    })
                                });
                            } else {
                                let cot = Cotangents {
                                    image: &v_image,
                                    alpha: Some(&v_alpha),
                                    depth: Some(&v_depth),
                                };
                                // The bins of this kernel's own forward pass, with what it
                                // keeps for the backward pass, as in training.
                                let forward = rasterize_binned_with(
                                    &s.splats(),
                                    s.tile_bins(),
                                    &s.background,
                                    kernel,
                                )
                                .unwrap();
                                g.bench_function(id, |b| {
                                    pool.install(|| {
                                        b.iter(|| {
                                            rasterize_backward_with(
                                                &s.splats(),
                                                &forward.bins,
                                                &s.background,
                                                &cot,
                                                DEFAULT_GRADIENT_BUFFER_VALUES,
                                                kernel,
                                            )
                                            .unwrap()
                                        })
                                    })
                                });
                            }
                        }
                    }
                    g.finish();
                }
            }
        }
    }
}

fn sort(c: &mut Criterion) {
    // Build the depths only when some benchmark of the group is selected.
    let ids: Vec<String> = ["f32", "f64"]
        .iter()
        .flat_map(|p| {
            ["100k", "1000k"]
                .iter()
                .flat_map(move |n| [1, 2].map(|t| format!("depth_order/{p}/{n}/t{t}")))
        })
        .collect();
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    if !filters.is_empty()
        && !filters
            .iter()
            .any(|f| ids.iter().any(|id| id.contains(f.as_str())))
    {
        return;
    }
    let mut g = c.benchmark_group("depth_order");
    g.sample_size(20);
    for n in [100_000usize, 1_000_000] {
        let mut rng = Rng(n as u64);
        let d32: Vec<f32> = (0..n).map(|_| rng.uniform(1.0, 100.0) as f32).collect();
        let d64: Vec<f64> = d32.iter().map(|&d| d as f64).collect();
        let ids: Vec<u32> = (0..n as u32).collect();
        for t in [1usize, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .unwrap();
            let id = |p: &str| format!("{p}/{}k/t{t}", n / 1000);
            g.bench_function(id("f32"), |b| {
                pool.install(|| b.iter(|| raster::tiles::depth_order(ids.clone(), &d32)))
            });
            g.bench_function(id("f64"), |b| {
                pool.install(|| b.iter(|| raster::tiles::depth_order(ids.clone(), &d64)))
            });
        }
    }
    g.finish();
}

fn binning(c: &mut Criterion) {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    if !filters.is_empty()
        && !filters.iter().any(|f| {
            "binning/100k/256/t1".contains(f.as_str()) || "binning/100k/256/t2".contains(f.as_str())
        })
    {
        return;
    }
    // Binning alone (tile rectangles, depth order, intersection lists) on the scene of the
    // 100k, 256x256 pass benchmarks.
    let s = scene(100_000, 256, 3);
    let mut g = c.benchmark_group("binning");
    g.sample_size(20);
    for t in [1usize, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build()
            .unwrap();
        g.bench_function(format!("100k/256/t{t}"), |b| {
            pool.install(|| {
                b.iter(|| {
                    raster::tiles::TileBins::new(s.width, s.height, &s.means2d, &s.depths, &s.radii)
                        .unwrap()
                })
            })
        });
    }
    g.finish();
}

criterion_group!(benches, sort, binning, bench);
criterion_main!(benches);
