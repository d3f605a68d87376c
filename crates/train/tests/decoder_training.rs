//! AdaIN decoder training on tiny crops: from a perturbed optimum of networks built in the test
//! the held-out loss falls at every step and only the decoder changes; with the oracle's networks
//! (1/8 of the VGG widths, to relu4_1) the fullres variant trains too, a resumed run is
//! bit-identical to the uninterrupted one, and checkpoints, weights and bad inputs are handled;
//! and the image folders it reads from.

mod common;
#[path = "common/known_optimum.rs"]
mod known_optimum;

use train::{Quiet, Run};

use common::{fixture_networks, net_bits, shared_images};
use dsgs_testkit::{scratch_dir, shared_path};
use known_optimum::{perturb, positive_image, InvertibleNets};
use nets::{Decoder, NetWeights, Resolution};
use rand::rngs::StdRng;
use rand::SeedableRng;
use runtime::bundle::Variant;
use train::decoder_training::{
    init_decoder, DecoderStepReport, DecoderTrainConfig, DecoderTrainer, DECODER_CHECKPOINT_FILE,
    DECODER_WEIGHTS_FILE,
};
use train::image_folder::{
    center_crop, collect_images, random_crop, resize_short_side, stack, to_tensor, ImageSet,
};
use train::TrainError;

/// Four content images, short side 48.
fn contents() -> ImageSet {
    shared_images(
        "data/content",
        &["chicago.jpg", "flowers.jpg", "sailboat.jpg", "cornell.jpg"],
        48,
    )
}

/// Four style images, short side 48.
fn styles() -> ImageSet {
    shared_images(
        "data/styles",
        &[
            "brushstrokes.jpg",
            "mondrian.jpg",
            "sketch.png",
            "woman_with_hat_matisse.jpg",
        ],
        48,
    )
}

fn config(variant: Variant) -> DecoderTrainConfig {
    DecoderTrainConfig {
        iterations: 12,
        batch_size: 2,
        resize: 40,
        crop: 32,
        lr: 1e-3,
        variant,
        seed: 7,
        eval_pairs: 4,
        eval_interval: 0,
        checkpoint_interval: 0,
        ..DecoderTrainConfig::default()
    }
}

fn weights_of(d: &Decoder<f32>) -> Vec<Vec<u32>> {
    d.layers()
        .map(|l| {
            l.weight
                .iter()
                .chain(l.bias.iter())
                .map(|v| v.to_bits())
                .collect()
        })
        .collect()
}

/// Step `i` of `t`, checking its report: the step number, the learning rate of the AdaIN code's
/// inverse-time decay (with the 0-based iteration count), finite positive loss terms and the
/// total `content + style_weight * style`.
fn checked_step(t: &mut DecoderTrainer, cfg: &DecoderTrainConfig, i: u64) -> DecoderStepReport {
    let r = t.train_step().unwrap();
    assert_eq!(r.step, i);
    let lr = cfg.lr / (1.0 + cfg.lr_decay * (i - 1) as f64);
    assert_eq!(r.lr, lr);
    assert!(r.loss.is_finite() && r.loss_content > 0.0 && r.loss_style > 0.0);
    let total = r.loss_content + cfg.style_weight * r.loss_style;
    assert!((r.loss - total).abs() <= 1e-6 * total, "{r:?}");
    r
}

/// Trains `config.iterations` steps and returns the held-out loss before and after.
fn held_out_drop(variant: Variant) -> (f64, f64, DecoderTrainer) {
    let (enc, dec) = fixture_networks();
    let cfg = config(variant);
    let mut t = DecoderTrainer::new(enc, dec, contents(), styles(), cfg.clone()).unwrap();
    let before = t.evaluate().unwrap().unwrap();
    for i in 1..=cfg.iterations {
        checked_step(&mut t, &cfg, i);
    }
    let after = t.evaluate().unwrap().unwrap();
    assert_eq!(after.pairs, 4);
    (before.loss, after.loss, t)
}

/// Training from a perturbed optimum lowers the loss at every step and changes only the decoder,
/// for networks built from several seeds.
///
/// The networks are built in the test ([`InvertibleNets`]): the decoder inverts the encoder
/// exactly on positive images. Content and style sets are the same single image, taken whole
/// (crop = resize = its side), so the AdaIN target is the image's own deepest feature
/// `t = phi_k(x)`; the inverting decoder gives `g(t) = x`, whose features match `t` and whose
/// statistics match the style's at every level: the loss is zero there (up to rounding), its
/// global minimum. Noise `d` of size `SIGMA` on every decoder weight and bias moves it away;
/// around the minimum the loss is the quadratic `d^T H d / 2` (the fullres networks keep every
/// value positive, so no ReLU switches), whose gradient is `H d`. Adam moves each of the `n`
/// parameters by at most about `lr` per step (its first step is `lr` times the gradient's sign),
/// so `STEPS` steps move the parameters by at most `STEPS lr sqrt(n)`, which the learning rate
/// keeps at a tenth of `SIGMA`, the size of the offset along any direction: the gradient barely
/// changes along the way, and every step lowers the loss by about `lr |H d|_1`, more than its
/// second-order cost `lr^2 s^T H s / 2` (`s` the signs) even along the stiffest direction (all
/// inputs positive: their mean), where the steps of all parameters add up. (With a learning
/// rate 10 times higher the loss still falls at every step for 20 seeds; 20 times higher, the
/// steps overshoot the minimum.) The evaluation pair is the training image, whole, so the
/// evaluated loss is the one the steps descend. The standard variant is left out: at the optimum
/// its max-pools see exact ties (the decoded image is constant on each pooling window), where
/// the loss is not smooth.
#[test]
fn training_lowers_the_held_out_loss_and_changes_only_the_decoder() {
    const SIGMA: f64 = 0.01;
    const STEPS: u64 = 5;
    const SIDE: u32 = 16;
    for seed in 1..=8 {
        let nets = InvertibleNets::new(seed, &[4, 6, 8], &[2, 2, 1]);
        let n: usize = nets
            .decoder
            .layers()
            .map(|l| l.weight.len() + l.bias.len())
            .sum();
        let image = positive_image(seed, SIDE);
        let set = || ImageSet::from_images(vec![("image".into(), image.clone())]).unwrap();
        let cfg = DecoderTrainConfig {
            iterations: STEPS,
            batch_size: 1,
            resize: SIDE,
            crop: SIDE,
            lr: SIGMA / (10.0 * STEPS as f64 * (n as f64).sqrt()),
            variant: Variant::Fullres,
            seed,
            eval_pairs: 1,
            eval_interval: 0,
            checkpoint_interval: 0,
            ..DecoderTrainConfig::default()
        };
        let trainer = |decoder: &Decoder<f32>| {
            DecoderTrainer::new(
                nets.encoder.clone(),
                decoder.clone(),
                set(),
                set(),
                cfg.clone(),
            )
            .unwrap()
        };
        let held_out = |t: &DecoderTrainer| t.evaluate().unwrap().unwrap().loss;
        let optimum = held_out(&trainer(&nets.decoder));
        let mut noisy = nets.decoder.clone();
        perturb(noisy.layers_mut(), seed + 1000, SIGMA);
        let mut t = trainer(&noisy);
        let before = held_out(&t);
        // the construction is a minimum: the perturbed loss is far above it
        assert!(
            optimum < 1e-6 * before,
            "seed {seed}: {optimum} vs {before}"
        );
        // each report carries the loss at the parameters its step started from
        let mut losses = vec![before];
        for i in 1..=cfg.iterations {
            let r = checked_step(&mut t, &cfg, i);
            if i > 1 {
                losses.push(r.loss);
            }
        }
        let after = held_out(&t);
        losses.push(after);
        println!("seed {seed}: held-out loss {losses:.4?}");
        assert!(
            losses.windows(2).all(|w| w[1] < w[0]),
            "seed {seed}: the loss rose: {losses:?}"
        );

        assert_eq!(
            net_bits(t.encoder().layers()),
            net_bits(nets.encoder.layers())
        );
        let (w0, w1) = (weights_of(&noisy), weights_of(t.decoder()));
        for (k, (a, b)) in w0.iter().zip(&w1).enumerate() {
            assert_ne!(a, b, "seed {seed}: decoder layer {k} did not change");
        }
        assert_eq!(t.decoder().resolution(), Resolution::Fullres);
    }
}

#[test]
fn the_fullres_variant_trains_too() {
    let (before, after, t) = held_out_drop(Variant::Fullres);
    println!("fullres: held-out loss {before:.5} -> {after:.5}");
    assert!(after < 0.95 * before, "{before} -> {after}");
    assert_eq!(t.decoder().resolution(), Resolution::Fullres);
    assert_eq!(t.encoder().resolution(), Resolution::Fullres);
}

#[test]
fn resuming_from_a_checkpoint_is_bit_identical() {
    let (enc, dec) = fixture_networks();
    let mut cfg = config(Variant::Standard);
    cfg.iterations = 4;
    let mut straight =
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg.clone()).unwrap();
    let reports: Vec<_> = (0..4).map(|_| straight.train_step().unwrap()).collect();

    let dir = scratch_dir("dectrain", "resume");
    let mut first =
        DecoderTrainer::new(enc.clone(), dec, contents(), styles(), cfg.clone()).unwrap();
    first.train_step().unwrap();
    first.train_step().unwrap();
    let ck = dir.join("ck.safetensors");
    first.save_checkpoint(&ck).unwrap();
    drop(first);
    let mut resumed = DecoderTrainer::resume(&ck, enc, contents(), styles(), cfg).unwrap();
    assert_eq!(resumed.step(), 2);
    let r3 = resumed.train_step().unwrap();
    let r4 = resumed.train_step().unwrap();
    assert_eq!([r3, r4], [reports[2], reports[3]]);
    assert_eq!(
        weights_of(resumed.decoder()),
        weights_of(straight.decoder())
    );
    assert_eq!(resumed.adam(), straight.adam());
    assert_eq!(resumed.running_averages(), straight.running_averages());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A style network measures the style term (its own levels and statistics) while the content
/// term stays on the encoder; the run resumes bit-identically only with the same network.
#[test]
fn a_style_network_measures_the_style_and_resumes_only_with_itself() {
    let (enc, dec) = fixture_networks();
    // Another encoder: the fixture's to relu2_1 with its weights halved past the first conv.
    let mut psi = enc.clone().with_depth(2).unwrap();
    for l in psi.layers_mut().skip(1) {
        l.weight.mapv_inplace(|w| 0.5 * w);
    }
    let mut cfg = config(Variant::Standard);
    cfg.iterations = 4;
    let mut own =
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg.clone()).unwrap();
    let mut straight =
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg.clone())
            .unwrap()
            .with_style_network(psi.clone())
            .unwrap();
    let (a, b) = (own.train_step().unwrap(), straight.train_step().unwrap());
    // The same decoder and batch at step 1: the same content term, another style term.
    assert_eq!(a.loss_content.to_bits(), b.loss_content.to_bits());
    assert_ne!(a.loss_style, b.loss_style);
    let reports: Vec<_> = (0..3).map(|_| straight.train_step().unwrap()).collect();
    // The held-out evaluation measures the style with the network too.
    let (e_own, e_psi) = (
        own.evaluate().unwrap().unwrap(),
        straight.evaluate().unwrap().unwrap(),
    );
    assert_ne!(e_own.loss_style, e_psi.loss_style);

    let dir = scratch_dir("dectrain", "style-network");
    let mut first =
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg.clone())
            .unwrap()
            .with_style_network(psi.clone())
            .unwrap();
    first.train_step().unwrap();
    let ck = dir.join("ck.safetensors");
    first.save_checkpoint(&ck).unwrap();
    // A started run cannot change its style network.
    assert!(matches!(
        first.with_style_network(psi.clone()),
        Err(TrainError::Config(_))
    ));
    // Resuming without the network, or with another one, is refused with the reason.
    let refused = |n: Option<nets::Encoder<f32>>| {
        let e = DecoderTrainer::resume_with_style_network(
            &ck,
            enc.clone(),
            n,
            contents(),
            styles(),
            cfg.clone(),
        )
        .err()
        .expect("refused")
        .to_string();
        assert!(e.contains("ck.safetensors") && e.contains("style"), "{e}");
    };
    refused(None);
    refused(Some(enc.clone().with_depth(2).unwrap()));
    let mut resumed = DecoderTrainer::resume_with_style_network(
        &ck,
        enc.clone(),
        Some(psi),
        contents(),
        styles(),
        cfg.clone(),
    )
    .unwrap();
    let again: Vec<_> = (0..3).map(|_| resumed.train_step().unwrap()).collect();
    assert_eq!(again, reports);
    assert_eq!(
        weights_of(resumed.decoder()),
        weights_of(straight.decoder())
    );
    assert_eq!(resumed.adam(), straight.adam());
    // A run without a style network does not resume with one.
    own.save_checkpoint(&ck).unwrap();
    let e = DecoderTrainer::resume_with_style_network(
        &ck,
        enc.clone(),
        Some(enc.clone()),
        contents(),
        styles(),
        cfg,
    )
    .err()
    .expect("refused")
    .to_string();
    assert!(e.contains("its own encoder"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn train_writes_checkpoints_and_the_final_weights_and_stops_on_request() {
    let (enc, dec) = fixture_networks();
    let dir = scratch_dir("dectrain", "train");
    let mut cfg = config(Variant::Standard);
    cfg.iterations = 3;
    cfg.checkpoint_interval = 2;
    cfg.eval_interval = 2;
    let mut t =
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg.clone()).unwrap();
    let summary = t.train(&Run::into_dir(&dir)).unwrap();
    assert_eq!(summary.run.step, 3);
    assert!(!summary.run.interrupted);
    // evaluations before the first iteration, at 2 (interval) and at 3 (the end)
    let steps: Vec<u64> = summary.evaluations.iter().map(|e| e.step).collect();
    assert_eq!(steps, [0, 2, 3]);
    let weights = summary.run.output.unwrap().1;
    assert_eq!(weights, dir.join(DECODER_WEIGHTS_FILE));
    let saved = NetWeights::load(&weights).unwrap();
    assert_eq!(
        weights_of(saved.decoder.as_ref().unwrap()),
        weights_of(t.decoder())
    );
    assert_eq!(
        net_bits(saved.encoder.as_ref().unwrap().layers()),
        net_bits(enc.layers())
    );
    // the checkpoint of iteration 2 resumes to the same end point
    let ck = dir.join(DECODER_CHECKPOINT_FILE);
    let mut resumed =
        DecoderTrainer::resume(&ck, enc.clone(), contents(), styles(), cfg.clone()).unwrap();
    assert_eq!(resumed.step(), 2);
    resumed.train(&Run::in_memory()).unwrap();
    assert_eq!(weights_of(resumed.decoder()), weights_of(t.decoder()));

    // a raised stop flag ends the run before its first iteration and leaves a checkpoint
    std::fs::remove_file(&ck).unwrap();
    let stop = std::sync::atomic::AtomicBool::new(true);
    let mut s = DecoderTrainer::new(enc, dec, contents(), styles(), cfg).unwrap();
    let summary = s
        .train(&Run {
            out_dir: Some(&dir),
            stop: Some(&stop),
            sink: &Quiet,
        })
        .unwrap();
    assert!(summary.run.interrupted);
    assert_eq!(summary.run.step, 0);
    assert!(summary.run.output.is_none());
    assert!(ck.is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_checkpoints_and_configurations_are_refused_with_reasons() {
    let (enc, dec) = fixture_networks();
    let dir = scratch_dir("dectrain", "bad");
    let junk = dir.join("junk.safetensors");
    std::fs::write(&junk, b"not a checkpoint").unwrap();
    let e = DecoderTrainer::resume(
        &junk,
        enc.clone(),
        contents(),
        styles(),
        config(Variant::Standard),
    )
    .err()
    .unwrap();
    let msg = e.to_string();
    assert!(msg.contains("junk.safetensors"), "{msg}");

    // a checkpoint made against another encoder
    let t = DecoderTrainer::new(
        enc.clone(),
        dec.clone(),
        contents(),
        styles(),
        config(Variant::Standard),
    )
    .unwrap();
    let ck = dir.join("ck.safetensors");
    t.save_checkpoint(&ck).unwrap();
    let mut other = enc.clone();
    other.layers_mut().next().unwrap().bias[0] += 1.0;
    let msg = DecoderTrainer::resume(&ck, other, contents(), styles(), config(Variant::Standard))
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("another encoder"), "{msg}");

    let mut cfg = config(Variant::Standard);
    cfg.crop = 64;
    let msg = DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("crop 64"), "{msg}");
    let mut cfg = config(Variant::Standard);
    cfg.batch_size = 0;
    assert!(matches!(
        DecoderTrainer::new(enc.clone(), dec.clone(), contents(), styles(), cfg),
        Err(TrainError::Config(_))
    ));
    // a decoder of the wrong width
    let shallow = enc.clone().with_depth(3).unwrap();
    let msg = DecoderTrainer::new(
        shallow,
        dec,
        contents(),
        styles(),
        config(Variant::Standard),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(msg.contains("decoder maps 64 channels"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_decoder_initialised_from_the_encoder_mirrors_it_and_trains() {
    let (enc, _) = fixture_networks();
    let dec = init_decoder(&enc, 5).unwrap();
    assert_eq!(dec.in_channels(), 64);
    assert_eq!(dec.out_channels(), 3);
    assert!(!dec.final_relu());
    let mut per_level = enc.convs_per_level();
    per_level.reverse();
    assert_eq!(dec.convs_per_level(), per_level);
    // decoder conv{K}_{J} maps encoder conv{K}_{J}'s output width back to its input width
    for l in dec.layers() {
        let e = enc.layers().find(|x| x.name == l.name).unwrap();
        assert_eq!(
            l.weight.shape(),
            [e.in_channels(), e.out_channels(), 3, 3],
            "{}",
            l.name
        );
        let bound = 1.0 / ((e.out_channels() * 9) as f32).sqrt();
        assert!(l.weight.iter().chain(&l.bias).all(|v| v.abs() <= bound));
        let spread = l.weight.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(spread > 0.9 * bound, "{}: {spread} vs {bound}", l.name);
    }
    assert_eq!(
        weights_of(&init_decoder(&enc, 5).unwrap()),
        weights_of(&dec)
    );
    assert_ne!(
        weights_of(&init_decoder(&enc, 6).unwrap()),
        weights_of(&dec)
    );
    let mut cfg = config(Variant::Standard);
    cfg.iterations = 2;
    let mut t = DecoderTrainer::new(enc, dec, contents(), styles(), cfg).unwrap();
    assert!(t.train_step().unwrap().loss.is_finite());
}

#[test]
fn image_folders_are_listed_sorted_and_bad_files_are_named() {
    let styles_dir = shared_path("data/styles");
    let flat = collect_images(&[&styles_dir], false).unwrap();
    assert_eq!(flat.len(), 15);
    assert!(flat.windows(2).all(|w| w[0] < w[1]));
    assert!(flat
        .iter()
        .all(|p| p.parent() == Some(styles_dir.as_path())));
    let deep = collect_images(&[&styles_dir], true).unwrap();
    assert_eq!(deep.len(), 15 + 55);
    assert_eq!(&deep[..15], flat.as_slice());
    // files and folders mixed, in the order given
    let one = shared_path("data/content/sailboat.jpg");
    let mixed = collect_images(&[one.clone(), shared_path("data/content")], false).unwrap();
    assert_eq!(mixed[0], one);
    assert_eq!(mixed.len(), 8);

    let dir = scratch_dir("dectrain", "folders");
    let empty = dir.join("empty");
    std::fs::create_dir_all(empty.join("sub")).unwrap();
    let msg = collect_images(&[&empty], false).unwrap_err().to_string();
    assert!(
        msg.contains(&empty.display().to_string()) && msg.contains("no jpg"),
        "{msg}"
    );
    let notes = dir.join("notes.txt");
    std::fs::write(&notes, "text").unwrap();
    let msg = collect_images(&[&notes], false).unwrap_err().to_string();
    assert!(
        msg.contains("notes.txt") && msg.contains("not an image"),
        "{msg}"
    );
    let missing = dir.join("missing");
    let msg = collect_images(&[&missing], false).unwrap_err().to_string();
    assert!(msg.contains("missing"), "{msg}");
    let broken = dir.join("broken.jpg");
    std::fs::write(&broken, b"\xff\xd8 this is no jpeg").unwrap();
    let msg = ImageSet::open(&[&dir], false).unwrap_err().to_string();
    assert!(msg.contains("broken.jpg"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn crops_are_deterministic_given_the_generator_and_laid_out_nchw() {
    let set = ImageSet::open(&[shared_path("data/content/flowers.jpg")], false).unwrap();
    let img = set.load(0).unwrap();
    let small = resize_short_side(&img, 40);
    let short = small.width.min(small.height);
    let long = small.width.max(small.height);
    assert_eq!(short, 40);
    let (ow, oh) = (img.width as u64, img.height as u64);
    let expect_long = ow.max(oh) * 40 / ow.min(oh);
    assert_eq!(long as u64, expect_long);

    let a = random_crop(&small, 24, &mut StdRng::seed_from_u64(1)).unwrap();
    let b = random_crop(&small, 24, &mut StdRng::seed_from_u64(1)).unwrap();
    assert_eq!(a, b);
    let c = center_crop(&small, 24).unwrap();
    let (x0, y0) = ((small.width - 24) / 2, (small.height - 24) / 2);
    assert_eq!(c.pixel(3, 5), small.pixel(x0 + 3, y0 + 5));
    let t = to_tensor(&c);
    assert_eq!(t.shape(), [1, 3, 24, 24]);
    let p = c.pixel(7, 2);
    for ch in 0..3 {
        assert_eq!(t[[0, ch, 2, 7]], p[ch]);
    }
    let batch = stack(&[t.clone(), to_tensor(&a)]).unwrap();
    assert_eq!(batch.shape(), [2, 3, 24, 24]);
    assert!(stack(&[t, to_tensor(&small)]).is_err());
    assert!(random_crop(&small, 41, &mut StdRng::seed_from_u64(1)).is_err());
    // the set's own crop is the same pipeline
    let via_set = set
        .random_crop(0, 40, 24, &mut StdRng::seed_from_u64(1))
        .unwrap();
    assert_eq!(via_set, to_tensor(&a));
}

#[test]
fn the_configuration_reads_from_toml_with_defaults_for_the_rest() {
    let cfg: DecoderTrainConfig =
        toml::from_str("iterations = 100\nvariant = \"fullres\"\nbatch_size = 4\n").unwrap();
    assert_eq!(cfg.iterations, 100);
    assert_eq!(cfg.variant, Variant::Fullres);
    assert_eq!(cfg.batch_size, 4);
    let d = DecoderTrainConfig::default();
    assert_eq!(
        (d.resize, d.crop, d.style_weight, d.lr, d.lr_decay),
        (256, 128, 10.0, 1e-4, 5e-5)
    );
    assert_eq!(cfg.crop, d.crop);
    assert_eq!(d.lr_at(1), 1e-4);
    assert_eq!(d.lr_at(20_001), 1e-4 / 2.0);
}
