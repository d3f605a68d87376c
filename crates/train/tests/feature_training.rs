//! Feature training on a tiny synthetic scene (300 Gaussians, 32 x 32 views) with the oracle's
//! networks (1/8 of the VGG widths, to relu4_1): the loss falls, gradients reach the features
//! and the lifter while geometry and networks stay untouched, the alignment-only ablation
//! works, a resumed run is bit-identical, and the bundle saves, loads and renders.

mod common;

use train::Run;

use common::{
    fixture_networks, net_bits, render_views, shared_images, sphere_cameras, synthetic_scene,
};
use dsgs_testkit::scratch_dir;
use gaussian::FeatureGaussians;
use ndarray::Array4;
use nets::Resolution;
use style::channel_stats;
use train::bundle::{render_feature_map, CameraRecord, SceneBundle, Variant};
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

#[test]
fn a_few_steps_lower_the_loss_and_change_only_features_and_lifter() {
    let (enc, dec) = fixture_networks();
    let cfg = config(Variant::Fullres);
    let mut t = FeatureTrainer::new(cfg.clone(), inputs()).unwrap();
    assert_eq!(t.counts(), (3, 2));
    let features0 = t.scene().features.clone();
    let lifter0 = lifter_bits(&t);

    // gradients reach the features of the Gaussians in view and the lifter
    let g = t.sample_gradients(0, 0, None).unwrap();
    let f = cfg.feature_dim;
    let touched = g
        .features
        .chunks_exact(f)
        .filter(|row| row.iter().any(|&v| v != 0.0))
        .count();
    println!("Gaussians with a feature gradient in view 0: {touched} of 300");
    assert!(touched > 50, "{touched}");
    assert!(g.lifter.weight.iter().any(|&v| v != 0.0));
    assert!(g.lifter.bias.iter().any(|&v| v != 0.0));
    assert!(g.loss_align > 0.0 && g.loss_content > 0.0 && g.loss_style > 0.0);
    // the terms and the total are each rounded to f32 once (relative error 2^-24 each)
    let total = g.loss_align + g.loss_content + g.loss_style;
    assert!((g.loss - total).abs() <= 2.5e-7 * total);

    let before = t.evaluate(&PAIRS).unwrap();
    for i in 1..=cfg.iterations {
        let r = t.train_step().unwrap();
        assert_eq!(r.step, i);
        assert!(r.window.width == 16 && r.window.height == 16);
        assert!(r.window.x + 16 <= 32 && r.window.y + 16 <= 32);
        assert!(r.loss.is_finite());
    }
    let after = t.evaluate(&PAIRS).unwrap();
    println!(
        "fullres: loss {:.4} -> {:.4} (align {:.4} -> {:.4}, content {:.4} -> {:.4}, style {:.4} -> {:.4})",
        before.loss,
        after.loss,
        before.loss_align,
        after.loss_align,
        before.loss_content,
        after.loss_content,
        before.loss_style,
        after.loss_style
    );
    // every term falls; the style term, which the features reach only through the lifter and the
    // style transform of a fixed decoder, falls least
    assert!(after.loss < 0.99 * before.loss, "{before:?} -> {after:?}");
    assert!(after.loss_align < 0.95 * before.loss_align);
    assert!(after.loss_content < before.loss_content);
    assert!(after.loss_style < before.loss_style);

    // only the features and the lifter moved
    assert_eq!(geometry_bits(t.scene()), geometry_bits(&geometry()));
    assert_eq!(net_bits(t.encoder().layers()), net_bits(enc.layers()));
    assert_eq!(net_bits(t.decoder().layers()), net_bits(dec.layers()));
    assert_ne!(bits(&t.scene().features), bits(&features0));
    assert_ne!(lifter_bits(&t), lifter0);
    assert_eq!(t.decoder().resolution(), Resolution::Fullres);
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
        render_feature_map(t.scene(), &cam, (32, 32), &[0.0; 8]).unwrap()
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
