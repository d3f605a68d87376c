//! Feature training on tiny synthetic scenes: from a perturbed optimum built in the test (its
//! own networks, scene and view) the loss falls at every step, gradients reach the features and
//! the lifter while geometry and networks stay untouched; with the oracle's networks (1/8 of the
//! VGG widths, to relu4_1) on 32 x 32 views of 300 Gaussians, the standard variant and the
//! alignment-only ablation train, a resumed run is bit-identical, and the bundle saves, loads
//! and renders.

mod common;
#[path = "common/known_optimum.rs"]
mod known_optimum;

use train::Run;

use common::{
    fixture_networks, net_bits, render_views, shared_images, sphere_cameras, synthetic_scene,
};
use std::path::Path;

use dsgs_testkit::scratch_dir;
use gaussian::dataset::images::RgbImage;
use gaussian::FeatureGaussians;
use known_optimum::InvertibleNets;
use ndarray::Array4;
use nets::weights_file::serialize_canonical;
use nets::Resolution;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use runtime::bundle::{CameraRecord, SceneBundle, Variant};
use runtime::frame::render_feature_map;
use safetensors::tensor::TensorView;
use safetensors::SafeTensors;
use style::{channel_stats, STATS_EPS};
use train::features::{
    CropWindow, FeatureInputs, FeatureTrainConfig, FeatureTrainer, BUNDLE_DIR,
    FEATURE_CHECKPOINT_FILE,
};
use train::geometry::View;
use train::image_folder::{to_tensor, ImageSet};

fn geometry() -> FeatureGaussians<f32> {
    synthetic_scene(300, 11)
}

/// Four 32 x 32 views of the scene; the last is held out of training.
fn views() -> (Vec<View>, Vec<CameraRecord>) {
    let all = render_views(&geometry(), &sphere_cameras(4, 4.0, 32, 36.0), [0.0; 3]);
    let records = all
        .iter()
        .enumerate()
        .map(|(i, v)| CameraRecord::new(v.name.clone(), &v.camera, i == 3))
        .collect();
    (all[..3].to_vec(), records)
}

/// Two style images, short side 40.
fn styles() -> ImageSet {
    shared_images("data/styles", &["brushstrokes.jpg", "mondrian.jpg"], 40)
}

fn inputs() -> FeatureInputs {
    let (enc, dec) = fixture_networks();
    let (views, cameras) = views();
    FeatureInputs {
        geometry: geometry(),
        views,
        cameras,
        styles: styles(),
        encoder: enc,
        decoder: dec,
        background: [0.0; 3],
        provenance: vec![("scene".into(), "synthetic".into())],
    }
}

fn config(variant: Variant) -> FeatureTrainConfig {
    FeatureTrainConfig {
        iterations: 20,
        feature_dim: 8,
        variant,
        crop: Some(16),
        style_size: 32,
        // faster than the defaults, which are meant for thousands of iterations
        lr_features: 0.05,
        lr_lifter: 0.01,
        seed: 5,
        checkpoint_interval: 0,
        ..FeatureTrainConfig::default()
    }
}

/// Every (view, style) pair.
const PAIRS: [(usize, usize); 6] = [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (2, 1)];

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn geometry_bits(g: &FeatureGaussians<f32>) -> Vec<u32> {
    let mut out = Vec::new();
    for i in 0..g.len() {
        out.extend(bits(&g.means[i]));
        out.extend(bits(&g.log_scales[i]));
        out.extend(bits(&g.quats[i]));
        out.push(g.opacity_logits[i].to_bits());
    }
    out.extend(g.sh.iter().flat_map(|c| bits(c)));
    out
}

fn lifter_bits(t: &FeatureTrainer) -> Vec<u32> {
    net_bits(std::iter::once(t.lifter().layer()))
}

/// A trainer at step 0 whose features and lifter are the given ones (`lifter_weight` is
/// `[C, F]` row-major): the checkpoint of a fresh trainer with those three tensors replaced,
/// resumed. (The trainer draws its initial values from the seed; a checkpoint is how a run's
/// parameters are set from outside.)
fn trainer_at(
    cfg: &FeatureTrainConfig,
    inputs: &dyn Fn() -> FeatureInputs,
    features: &[f32],
    lifter_weight: &[f32],
    lifter_bias: &[f32],
    dir: &Path,
) -> FeatureTrainer {
    let bytes = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .checkpoint_bytes()
        .unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let le = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
    let replaced = [
        ("features", le(features)),
        ("lifter.weight", le(lifter_weight)),
        ("lifter.bias", le(lifter_bias)),
    ];
    let tensors: Vec<_> = st
        .tensors()
        .into_iter()
        .map(|(name, v)| {
            let data = replaced
                .iter()
                .find(|(n, _)| *n == name)
                .map_or_else(|| v.data().to_vec(), |(_, d)| d.clone());
            assert_eq!(data.len(), v.data().len(), "{name}");
            (name, v.dtype(), v.shape().to_vec(), data)
        })
        .collect();
    for (n, _) in &replaced {
        assert!(tensors.iter().any(|t| t.0 == *n), "no tensor {n}");
    }
    let views = tensors
        .iter()
        .map(|(n, d, shape, data)| (n.clone(), TensorView::new(*d, shape.clone(), data).unwrap()))
        .collect();
    let meta = header.metadata().clone().unwrap();
    let path = dir.join("start.safetensors");
    std::fs::write(&path, serialize_canonical(views, meta).unwrap()).unwrap();
    FeatureTrainer::resume(&path, cfg.clone(), inputs()).unwrap()
}

/// A few training steps from a perturbed optimum lower the loss at every step and change only
/// the features and the lifter, for scenes and networks built from several seeds.
///
/// The optimum is built in the test. The encoder and decoder ([`InvertibleNets`], 3 channels
/// throughout, fullres) invert each other on positive values, so the content term
/// `content(phi_k(g(t)), t)` is zero for every `t` near the optimum. The style image is flat:
/// its per-channel std is `sqrt(eps)`, so `t = std_s l + mean_s` barely varies and the style
/// term is of the order of `eps = 1e-5`, negligible. What is left is the alignment term, the
/// mean of `(relu(z) - target)^2` with `z = W r + b` the lifter's pre-activation of the
/// rasterized features `r`. Random features and a random lifter give a `z*` whose channels the
/// test normalises (zero mean, unit unbiased variance) by rescaling `W` and `b`; the single
/// training view is then the image whose deepest encoder features are `0.8 + a z*`, so that its
/// alignment target, their instance normalisation, is `kappa z*` with
/// `kappa = a / sqrt(a^2 + eps)`. With the lifter scaled by `kappa`, `z = target` at every
/// pixel: where the target is positive the pixel's term is zero, where it is negative the ReLU
/// gives 0 and `target^2` is the least any lifter output can give. That is the global minimum.
///
/// Noise of size `SIGMA` on the features, `W` and `b` moves away from it. Except at the few
/// pixels whose target is within the noise of 0 (where the ReLU may switch, and moving towards
/// the target still never raises the pixel's loss), the loss is a quadratic around the minimum,
/// and Adam steps of at most about `lr` per parameter, `STEPS lr sqrt(n)` in all, a tenth of
/// `SIGMA`, lower it at every step, as in the decoder-training test of the same construction.
/// (With a learning rate 100 times higher the loss still falls at every step for 20 seeds.)
/// There is one view and one style and the crop covers the whole map, so every step descends
/// the loss that is evaluated.
#[test]
fn a_few_steps_lower_the_loss_and_change_only_features_and_lifter() {
    const F: usize = 4;
    const SIDE: u32 = 24;
    const SIGMA: f64 = 0.05;
    const STEPS: u64 = 5;
    let dir = scratch_dir("feattrain", "optimum");
    let pixels = (SIDE * SIDE) as usize;
    for seed in 1..=6 {
        let nets = InvertibleNets::new(seed, &[3, 3], &[2, 1]);
        let geometry = synthetic_scene(200, seed);
        let camera = sphere_cameras(1, 4.0, SIDE, 27.0)[0];
        let mut rng = StdRng::seed_from_u64(seed);
        let mut normal = move || rng.sample::<f64, _>(StandardNormal);

        // the optimum: random features, a random lifter normalised so that z* is zero-mean with
        // unit (unbiased) variance per channel
        let features: Vec<f32> = (0..geometry.len() * F).map(|_| normal() as f32).collect();
        let mut w: Vec<f64> = (0..3 * F).map(|_| normal() / (F as f64).sqrt()).collect();
        let mut b = [0.0f64; 3];
        let mut scene = geometry.clone().with_features(F, 0.0);
        scene.features = features.clone();
        let r = render_feature_map(&scene, &camera, (SIDE, SIDE), &[0.0; F], 1).unwrap();
        let r: Vec<[f64; F]> = (0..pixels)
            .map(|p| {
                let (y, x) = (p / SIDE as usize, p % SIDE as usize);
                std::array::from_fn(|k| r[[0, k, y, x]] as f64)
            })
            .collect();
        let lift = |w: &[f64], b: &[f64; 3], c: usize, rp: &[f64; F]| -> f64 {
            b[c] + (0..F).map(|k| w[c * F + k] * rp[k]).sum::<f64>()
        };
        for c in 0..3 {
            let z: Vec<f64> = r.iter().map(|rp| lift(&w, &b, c, rp)).collect();
            let mean = z.iter().sum::<f64>() / pixels as f64;
            let var = z.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (pixels - 1) as f64;
            let std = var.sqrt();
            assert!(std > 1e-3, "seed {seed}: channel {c} of z is flat");
            for k in 0..F {
                w[c * F + k] /= std;
            }
            b[c] = -mean / std;
        }
        let z: Vec<[f64; 3]> = r
            .iter()
            .map(|rp| std::array::from_fn(|c| lift(&w, &b, c, rp)))
            .collect();
        // the view whose deepest features are 0.8 + a z*, and the lifter that matches its target
        let a = 0.1 / z.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
        let kappa = a / (a * a + STATS_EPS).sqrt();
        let image: Vec<f32> = z
            .iter()
            .flat_map(|zp| {
                let y = zp.map(|v| 0.8 + a * v);
                nets.preimage(&y, 0.05)
                    .expect("the view's pixels and activations are positive")
                    .map(|v| v as f32)
            })
            .collect();
        let lifter_w: Vec<f32> = w.iter().map(|v| (kappa * v) as f32).collect();
        let lifter_b: Vec<f32> = b.iter().map(|v| (kappa * v) as f32).collect();

        let view = View {
            name: "view000".into(),
            camera,
            image,
        };
        let flat = RgbImage {
            width: 16,
            height: 16,
            data: vec![0.5; 16 * 16 * 3],
        };
        let inputs = || FeatureInputs {
            geometry: geometry.clone(),
            views: vec![view.clone()],
            cameras: Vec::new(),
            styles: ImageSet::from_images(vec![("flat".into(), flat.clone())]).unwrap(),
            encoder: nets.encoder.clone(),
            decoder: nets.decoder.clone(),
            background: [0.0; 3],
            provenance: Vec::new(),
        };
        let n = features.len() + lifter_w.len() + lifter_b.len();
        let lr = SIGMA / (10.0 * STEPS as f64 * (n as f64).sqrt());
        let cfg = FeatureTrainConfig {
            iterations: STEPS,
            feature_dim: F,
            variant: Variant::Fullres,
            crop: Some(SIDE),
            style_size: 16,
            lr_features: lr,
            lr_lifter: lr,
            seed,
            checkpoint_interval: 0,
            ..FeatureTrainConfig::default()
        };
        let optimum = trainer_at(&cfg, &inputs, &features, &lifter_w, &lifter_b, &dir)
            .evaluate(&[(0, 0)])
            .unwrap();
        // the construction: at the optimum only the negative targets, which no ReLU output
        // reaches, contribute to the alignment term
        let floor = z
            .iter()
            .flatten()
            .filter(|&&v| v < 0.0)
            .map(|v| (kappa * v).powi(2))
            .sum::<f64>()
            / (3 * pixels) as f64;
        assert!(
            (optimum.loss_align - floor).abs() <= 1e-4 * floor,
            "seed {seed}: {optimum:?}, expected an alignment term of {floor}"
        );

        let mut noisy =
            |v: &[f32]| -> Vec<f32> { v.iter().map(|&x| x + (SIGMA * normal()) as f32).collect() };
        let (features0, w0, b0) = (noisy(&features), noisy(&lifter_w), noisy(&lifter_b));
        let mut t = trainer_at(&cfg, &inputs, &features0, &w0, &b0, &dir);
        assert_eq!(t.counts(), (1, 1));
        let lifter0 = lifter_bits(&t);

        // gradients reach the features of the Gaussians in view and the lifter
        let g = t.sample_gradients(0, 0, None).unwrap();
        assert!(g.features.iter().any(|&v| v != 0.0));
        assert!(g.lifter.weight.iter().any(|&v| v != 0.0));
        assert!(g.lifter.bias.iter().any(|&v| v != 0.0));
        assert!(g.loss_align > 0.0 && g.loss_style > 0.0);
        // the terms and the total are each rounded to f32 once (relative error 2^-24 each)
        let total = g.loss_align + g.loss_content + g.loss_style;
        assert!((g.loss - total).abs() <= 2.5e-7 * total);

        let before = t.evaluate(&[(0, 0)]).unwrap();
        assert!(
            optimum.loss < before.loss,
            "seed {seed}: {optimum:?} vs {before:?}"
        );
        let mut losses = vec![before.loss];
        for i in 1..=cfg.iterations {
            let r = t.train_step().unwrap();
            assert_eq!(r.step, i);
            assert_eq!((r.view, r.style), (0, 0));
            assert_eq!(r.window, CropWindow::full(SIDE as usize, SIDE as usize));
            if i > 1 {
                losses.push(r.loss);
            }
        }
        let after = t.evaluate(&[(0, 0)]).unwrap();
        losses.push(after.loss);
        println!(
            "seed {seed}: loss {losses:.6?}, optimum {:.6} (content {:.1e}, style {:.1e})",
            optimum.loss, optimum.loss_content, optimum.loss_style
        );
        assert!(
            losses.windows(2).all(|w| w[1] < w[0]),
            "seed {seed}: the loss rose: {losses:?}"
        );

        // only the features and the lifter moved
        assert_eq!(geometry_bits(t.scene()), geometry_bits(&geometry));
        assert_eq!(
            net_bits(t.encoder().layers()),
            net_bits(nets.encoder.layers())
        );
        assert_eq!(
            net_bits(t.decoder().layers()),
            net_bits(nets.decoder.layers())
        );
        assert_ne!(bits(&t.scene().features), bits(&features0));
        assert_ne!(lifter_bits(&t), lifter0);
        assert_eq!(t.decoder().resolution(), Resolution::Fullres);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_standard_variant_trains_on_pooled_feature_maps() {
    let mut cfg = config(Variant::Standard);
    cfg.iterations = 10;
    let mut t = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    let before = t.evaluate(&PAIRS).unwrap();
    for _ in 0..cfg.iterations {
        let r = t.train_step().unwrap();
        // 32 x 32 views pool three times to 4 x 4 feature maps, smaller than the crop
        assert_eq!(r.window, CropWindow::full(4, 4));
    }
    let after = t.evaluate(&PAIRS).unwrap();
    println!("standard: loss {:.4} -> {:.4}", before.loss, after.loss);
    assert!(after.loss < 0.99 * before.loss, "{before:?} -> {after:?}");
}

#[test]
fn alignment_only_training_runs_without_the_content_and_style_terms() {
    let mut cfg = config(Variant::Fullres);
    cfg.lambda_content = 0.0;
    cfg.lambda_style = 0.0;
    let mut t = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    let before = t.evaluate(&PAIRS).unwrap();
    for _ in 0..cfg.iterations {
        let r = t.train_step().unwrap();
        assert_eq!((r.loss_content, r.loss_style), (0.0, 0.0));
        assert_eq!(r.loss, r.loss_align);
        assert!(r.loss_align > 0.0);
    }
    let after = t.evaluate(&PAIRS).unwrap();
    println!(
        "align only: loss {:.4} -> {:.4}",
        before.loss_align, after.loss_align
    );
    assert!(after.loss_align < 0.95 * before.loss_align);
    assert_eq!((after.loss_content, after.loss_style), (0.0, 0.0));
}

#[test]
fn the_warm_up_aligns_the_whole_map_then_trains_the_full_loss_on_windows() {
    let mut cfg = config(Variant::Fullres);
    cfg.iterations = 4;
    cfg.align_warmup = 2;
    cfg.crop = Some(16);
    let mut t = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    for it in 1..=4 {
        let r = t.train_step().unwrap();
        if it <= 2 {
            assert_eq!((r.loss_content, r.loss_style), (0.0, 0.0), "iteration {it}");
            assert_eq!(r.loss, r.loss_align);
            // the warm-up aligns the whole 32 x 32 map
            assert_eq!(r.window, CropWindow::full(32, 32));
        } else {
            assert!(r.loss_content > 0.0 && r.loss_style > 0.0, "iteration {it}");
            assert!(r.loss > r.loss_align);
            assert_eq!((r.window.width, r.window.height), (16, 16));
        }
    }
}

#[test]
fn scene_statistics_are_the_mean_of_the_views_unnormalised_statistics() {
    let (enc, _) = fixture_networks();
    let t = FeatureTrainer::new(config(Variant::Standard), inputs()).unwrap();
    let (views, _) = views();
    let mut mean = vec![0.0f64; 64];
    let mut std = vec![0.0f64; 64];
    for v in &views {
        let x = Array4::from_shape_fn((1, 3, 32, 32), |(_, c, y, x)| v.image[(y * 32 + x) * 3 + c]);
        let feats = enc.forward(x.view()).unwrap();
        assert_eq!(feats[3].shape(), [1, 64, 4, 4]);
        let s = channel_stats(&feats[3]).unwrap();
        for c in 0..64 {
            mean[c] += s.mean[[0, c]] as f64 / 3.0;
            std[c] += s.std[[0, c]] as f64 / 3.0;
        }
    }
    let (m, s) = t.scene_stats();
    for c in 0..64 {
        assert!((m[c] as f64 - mean[c]).abs() <= 1e-6 * (1.0 + mean[c].abs()));
        assert!((s[c] as f64 - std[c]).abs() <= 1e-6 * (1.0 + std[c].abs()));
    }
}

#[test]
fn resuming_from_a_checkpoint_is_bit_identical() {
    let mut cfg = config(Variant::Fullres);
    cfg.iterations = 4;
    let mut straight = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    let reports: Vec<_> = (0..4).map(|_| straight.train_step().unwrap()).collect();

    let dir = scratch_dir("feattrain", "resume");
    let mut first = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    first.train_step().unwrap();
    first.train_step().unwrap();
    let ck = dir.join("ck.safetensors");
    first.save_checkpoint(&ck).unwrap();
    drop(first);
    let mut resumed = FeatureTrainer::resume(&ck, cfg.clone(), inputs()).unwrap();
    assert_eq!(resumed.step(), 2);
    let r3 = resumed.train_step().unwrap();
    let r4 = resumed.train_step().unwrap();
    assert_eq!([r3, r4], [reports[2], reports[3]]);
    assert_eq!(
        bits(&resumed.scene().features),
        bits(&straight.scene().features)
    );
    assert_eq!(lifter_bits(&resumed), lifter_bits(&straight));
    assert_eq!(resumed.adam(), straight.adam());
    assert_eq!(resumed.running_averages(), straight.running_averages());

    // a checkpoint of other geometry is refused
    let mut other = inputs();
    other.geometry.means[0][0] += 0.01;
    let msg = FeatureTrainer::resume(&ck, cfg, other)
        .err()
        .unwrap()
        .to_string();
    assert!(
        msg.contains("ck.safetensors") && msg.contains("another geometry"),
        "{msg}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_bundle_saves_loads_and_renders() {
    let dir = scratch_dir("feattrain", "bundle");
    let mut cfg = config(Variant::Fullres);
    cfg.iterations = 3;
    cfg.checkpoint_interval = 2;
    let mut t = FeatureTrainer::new(cfg, inputs()).unwrap();
    let summary = t.train(&Run::into_dir(&dir)).unwrap();
    assert_eq!(summary.run.step, 3);
    assert!(dir.join(FEATURE_CHECKPOINT_FILE).is_file());
    let bundle_dir = summary.run.output.unwrap().1;
    assert_eq!(bundle_dir, dir.join(BUNDLE_DIR));

    let b = SceneBundle::load(&bundle_dir).unwrap();
    assert_eq!(b.info.variant, Variant::Fullres);
    assert_eq!(b.info.feature_dim, 8);
    assert_eq!(b.info.encoder_widths, [8, 16, 32, 64]);
    assert_eq!(b.info.feature_background, vec![0.0; 8]);
    assert_eq!(b.info.cameras.len(), 4);
    let held: Vec<bool> = b.info.cameras.iter().map(|c| c.held_out).collect();
    assert_eq!(held, [false, false, false, true]);
    let (m, s) = t.scene_stats();
    assert_eq!(b.info.scene_mean, m);
    assert_eq!(b.info.scene_std, s);
    assert!(b
        .info
        .provenance
        .contains(&("scene".to_string(), "synthetic".to_string())));
    assert_eq!(bits(&b.scene.features), bits(&t.scene().features));
    assert_eq!(geometry_bits(&b.scene), geometry_bits(&geometry()));
    assert_eq!(net_bits(std::iter::once(b.lifter.layer())), lifter_bits(&t));
    assert_eq!(b.decoder.resolution(), Resolution::Fullres);

    // render the held-out camera, stylized with a style image
    let cam = b.cameras()[3];
    let feats = b.render_features(&cam).unwrap();
    assert_eq!(feats.shape(), [1, 8, 32, 32]);
    assert_eq!(
        feats,
        render_feature_map(t.scene(), &cam, (32, 32), &[0.0; 8], 1).unwrap()
    );
    let style_img = to_tensor(&styles().load(1).unwrap());
    let stats = style::encode_style(&b.encoder, &style_img).unwrap();
    let target = b.target_stats(stats.deepest(), 1.0).unwrap();
    let image = b.decode(&feats, &target, 32, 32).unwrap();
    assert_eq!(image.shape(), [1, 3, 32, 32]);
    assert!(image.iter().all(|v| v.is_finite()));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_inputs_are_refused_with_reasons() {
    let mut cfg = config(Variant::Fullres);
    cfg.feature_dim = 0;
    assert!(FeatureTrainer::new(cfg, inputs())
        .err()
        .unwrap()
        .to_string()
        .contains("feature_dim"));
    let mut no_views = inputs();
    no_views.views.clear();
    assert!(FeatureTrainer::new(config(Variant::Fullres), no_views)
        .err()
        .unwrap()
        .to_string()
        .contains("no training views"));
    let mut short = inputs();
    short.views[1].image.pop();
    let msg = FeatureTrainer::new(config(Variant::Fullres), short)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("view001"), "{msg}");
    let mut shallow = inputs();
    shallow.encoder = shallow.encoder.with_depth(3).unwrap();
    assert!(FeatureTrainer::new(config(Variant::Fullres), shallow).is_err());
}

#[test]
fn the_configuration_reads_from_toml_with_defaults_for_the_rest() {
    let cfg: FeatureTrainConfig =
        toml::from_str("iterations = 10\nvariant = \"fullres\"\nlambda_style = 0.5\n").unwrap();
    assert_eq!(cfg.iterations, 10);
    assert_eq!(cfg.variant, Variant::Fullres);
    assert_eq!(cfg.lambda_style, 0.5);
    assert_eq!(cfg.feature_dim, 32);
    assert_eq!(cfg.crop, None);
    assert_eq!(cfg.crop_side(), 64);
    let cfg: FeatureTrainConfig = toml::from_str("crop = 20").unwrap();
    assert_eq!((cfg.variant, cfg.crop_side()), (Variant::Standard, 20));
    assert_eq!(FeatureTrainConfig::default().crop_side(), 32);
    assert!(toml::from_str::<FeatureTrainConfig>("variant = \"huge\"").is_err());
}

/// The fixed evaluation: reported before the first iteration, every `eval_interval` iterations
/// and at the end; it changes nothing in training; drawn from held-out views and styles by
/// `with_held_out`, which given the training views and styles draws the default samples
/// (`with_held_out_views` draws the same as `with_held_out` with the training styles); a run
/// resumed halfway reports the straight run's later evaluations.
#[test]
fn evaluations_follow_the_schedule_and_leave_training_alone() {
    let mut cfg = config(Variant::Fullres);
    cfg.iterations = 5;
    cfg.eval_pairs = 3;
    cfg.eval_interval = 2;
    cfg.align_warmup = 1;
    let mut plain_cfg = cfg.clone();
    plain_cfg.eval_pairs = 0;
    let mut plain = FeatureTrainer::new(plain_cfg, inputs()).unwrap();
    let none = plain.train(&Run::in_memory()).unwrap();
    assert!(none.evaluations.is_empty());
    assert!(plain.evaluate_fixed().unwrap().is_none());

    let mut t = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    let s = t.train(&Run::in_memory()).unwrap();
    let steps: Vec<u64> = s.evaluations.iter().map(|e| e.step).collect();
    assert_eq!(steps, [0, 2, 4, 5]);
    assert_eq!(bits(&t.scene().features), bits(&plain.scene().features));
    assert_eq!(lifter_bits(&t), lifter_bits(&plain));
    for e in &s.evaluations {
        assert_eq!(e.pairs, 3);
        assert!(e.loss_align > 0.0 && e.loss_content > 0.0 && e.loss_style > 0.0);
        // The full loss weights, also at step 0 (before the warm-up's alignment-only step).
        // Each sample's total is its f64 sum rounded once to f32 (relative error at most
        // 2^-24, about 6e-8) and the terms are positive, so the mean keeps that bound.
        let want =
            e.loss_align + cfg.lambda_content * e.loss_content + cfg.lambda_style * e.loss_style;
        assert!((e.loss - want).abs() <= 1e-7 * want, "{e:?}");
    }
    assert_ne!(s.evaluations[0].loss, s.evaluations[3].loss);

    // Held-out samples given as the training views and styles are the default samples.
    let (train_views, _) = views();
    let same = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out(&train_views, &styles(), &train::Quiet)
        .unwrap();
    let fresh = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    assert_eq!(
        same.evaluate_fixed().unwrap(),
        fresh.evaluate_fixed().unwrap()
    );
    assert_eq!(fresh.evaluate_fixed().unwrap(), Some(s.evaluations[0]));
    // The held-out view (the fourth) gives other values.
    let all = render_views(&geometry(), &sphere_cameras(4, 4.0, 32, 36.0), [0.0; 3]);
    let held = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out(&all[3..], &styles(), &train::Quiet)
        .unwrap();
    let h = held.evaluate_fixed().unwrap().unwrap();
    assert_eq!(h.pairs, 3);
    assert_ne!(h.loss_align, s.evaluations[0].loss_align);
    // With the training paintings reused rather than encoded again: the same samples.
    let reused = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out_views(&all[3..], &train::Quiet)
        .unwrap();
    assert_eq!(reused.evaluate_fixed().unwrap(), Some(h));
    let msg = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out_views(&[], &train::Quiet)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("held-out evaluation needs views"), "{msg}");
    let msg = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out(&[], &styles(), &train::Quiet)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("held-out evaluation needs views"), "{msg}");
    // A held-out image that does not fit its camera is refused, naming the view.
    let mut short = all[3..].to_vec();
    short[0].image.pop();
    let msg = FeatureTrainer::new(cfg.clone(), inputs())
        .unwrap()
        .with_held_out(&short, &styles(), &train::Quiet)
        .err()
        .unwrap()
        .to_string();
    let name = format!("held-out view `{}`", short[0].name);
    assert!(msg.contains(&name) && msg.contains("camera needs"), "{msg}");

    // Stopped after iteration 3 and resumed: the evaluations at 4 and 5 are the straight run's.
    let dir = scratch_dir("feattrain", "eval-resume");
    let mut first_cfg = cfg.clone();
    first_cfg.iterations = 3;
    let mut first = FeatureTrainer::new(first_cfg, inputs()).unwrap();
    first.train(&Run::in_memory()).unwrap();
    let ck = dir.join("ck.safetensors");
    first.save_checkpoint(&ck).unwrap();
    let mut resumed = FeatureTrainer::resume(&ck, cfg, inputs()).unwrap();
    let r = resumed.train(&Run::in_memory()).unwrap();
    assert_eq!(r.evaluations, s.evaluations[2..]);
    let _ = std::fs::remove_dir_all(&dir);
}
