//! Robustness: corrupted scene-bundle descriptions (`bundle.json`) and training checkpoints must
//! produce `Ok` or `Err`, never a panic, a hang or an absurd allocation; and whatever loads must
//! work.
//!
//! Each test is a fuzz target of the testkit's harness ([`dsgs_testkit::fuzz`]), seeded from files
//! the code itself writes:
//! * `bundle.json` of a small valid bundle (the oracle's networks, a synthetic scene, four
//!   cameras) saved by `SceneBundle::save`. Mutated copies replace it in the bundle folder;
//!   `BundleInfo::load` must give `Ok` or `Err`, and when the whole bundle then loads
//!   (`SceneBundle::load`), its first camera, shrunk to 16x16, must render features and decode
//!   a stylized image with a style's statistics. Besides the byte and text mutations, values of
//!   the parsed JSON are replaced (by `null`, other types, huge, negative or fractional numbers),
//!   arrays shortened, emptied or lengthened and object keys removed or added, so that the
//!   checks past the syntax (camera checks, statistics and background sizes, the format tag) are
//!   reached.
//! * A geometry checkpoint (`GeometryCheckpoint::to_bytes` of a small model): whatever
//!   `GeometryCheckpoint::from_bytes` accepts must serialise and read back to the same bytes,
//!   and `checkpoint_step` must read the same step from the file.
//! * A decoder-training checkpoint (`DecoderTrainer::save_checkpoint` after one step): a
//!   checkpoint `DecoderTrainer::resume` accepts must save and resume to the same bytes.
//!
//! The safetensors targets also get the header mutations of
//! [`dsgs_testkit::fuzz::safetensors_header`] (dtypes, shapes, offsets and metadata changed with
//! the length prefix kept consistent). `DSGS_FUZZ_CASES=N` (or `unbounded`) and
//! `DSGS_FUZZ_SEED` change the number of mutated inputs per target, e.g.
//! `DSGS_FUZZ_CASES=100000 cargo test --release -p dsgs-train --test fuzz -- --nocapture`
//! (see `docs/robustness.md`).

mod common;

use std::path::Path;

use common::{fixture_networks, shared_images, synthetic_scene};
use dsgs_testkit::fuzz::{
    below, byte_mutators, pick, safetensors_header, text_mutators, write_input, CappedAlloc,
    Mutator, Target,
};
use dsgs_testkit::scratch_dir;
use glam::DVec3;
use ndarray::Array2;
use runtime::bundle::{BundleInfo, SceneBundle, INFO_FILE};
use serde_json::{json, Value};
use style::ChannelStats;
use train::checkpoint::{checkpoint_step, GeometryCheckpoint};
use train::{AdamConfig, DecoderTrainConfig, DecoderTrainer, GaussianModel, LearningRates};

#[global_allocator]
static ALLOC: CappedAlloc = CappedAlloc;

/// The JSON pointers of every value of `v`, the root included.
fn pointers(v: &Value, at: String, out: &mut Vec<String>) {
    match v {
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                pointers(x, format!("{at}/{i}"), out);
            }
        }
        Value::Object(o) => {
            for (k, x) in o {
                let k = k.replace('~', "~0").replace('/', "~1");
                pointers(x, format!("{at}/{k}"), out);
            }
        }
        _ => {}
    }
    out.push(at);
}

/// Changes one value of a JSON document (the input unchanged if it is not JSON): `null`, a value
/// of another type, a boundary number, an array shortened, emptied or lengthened, an object key
/// removed or added.
fn json_value() -> Mutator {
    Mutator::new("JSON value", |rng, input| {
        let Ok(mut doc) = serde_json::from_slice::<Value>(input) else {
            return input.to_vec();
        };
        let mut all = Vec::new();
        pointers(&doc, String::new(), &mut all);
        let at = pick(rng, &all).clone();
        let node = doc.pointer_mut(&at).expect("a pointer of this document");
        let numbers = [
            json!(0),
            json!(-1),
            json!(0.5),
            json!(-0.0),
            json!(1e308),
            json!(-1e308),
            json!(5e-324),
            json!(u64::MAX),
            json!(i64::MIN),
            json!(4294967296u64),
            json!(9007199254740993u64),
        ];
        match (below(rng, 4), &mut *node) {
            (0, _) => *node = Value::Null,
            (1, _) => {
                *node = pick(
                    rng,
                    &[json!("x"), json!([]), json!({}), json!(true), json!([1, 2])],
                )
                .clone()
            }
            (_, Value::Array(a)) if !a.is_empty() => {
                let i = below(rng, a.len());
                match below(rng, 4) {
                    0 => {
                        a.remove(i);
                    }
                    1 => a.clear(),
                    2 => a.truncate(i),
                    _ => {
                        let copy = a[i].clone();
                        for _ in 0..1 + below(rng, 64) {
                            a.push(copy.clone());
                        }
                    }
                }
            }
            (_, Value::Object(o)) if !o.is_empty() => {
                let keys: Vec<String> = o.keys().cloned().collect();
                if below(rng, 2) == 0 {
                    o.remove(pick(rng, &keys));
                } else {
                    o.insert("unknown_key".into(), json!(1));
                }
            }
            (_, Value::Number(_)) => *node = pick(rng, &numbers).clone(),
            (_, Value::String(s)) => *s = pick(rng, &["", "..", "../../x", "standard"]).to_string(),
            _ => *node = pick(rng, &numbers).clone(),
        }
        serde_json::to_vec_pretty(&doc).expect("a JSON value serialises")
    })
}

/// A small valid bundle saved in `dir` ([`common::small_bundle`] with 4 feature channels).
fn save_bundle(dir: &Path) {
    common::small_bundle(4).save(dir).unwrap();
}

/// What a bundle that loads must allow: rendering the features of its first camera (shrunk to
/// 16x16) and decoding them with a style's statistics.
fn stylize_first_view(bundle: &SceneBundle) {
    let Some(camera) = bundle.cameras().first().map(|c| c.resized(16, 16)) else {
        return;
    };
    let features = bundle
        .render_features(&camera)
        .expect("a loaded bundle renders its features");
    let c = bundle.lifter.out_channels();
    let style = ChannelStats::new(
        Array2::from_elem((1, c), 0.1f32),
        Array2::from_elem((1, c), 0.5f32),
    )
    .unwrap();
    let stats = bundle
        .target_stats(&style, 0.7)
        .expect("a loaded bundle mixes statistics");
    bundle
        .decode(&features, &stats, 16, 16)
        .expect("a loaded bundle decodes");
}

#[test]
fn bundle_json_never_panics() {
    let dir = scratch_dir("fuzz", "bundle");
    save_bundle(&dir);
    let info_path = dir.join(INFO_FILE);
    let seed = std::fs::read(&info_path).unwrap();
    let folder = dir.clone();
    Target::new("bundle.json", 5_000)
        .seed(seed)
        .mutators(text_mutators())
        .mutators([json_value()])
        .run(move |bytes| {
            write_input(&info_path, bytes);
            let Ok(info) = BundleInfo::load(&folder) else {
                return false;
            };
            for camera in info.cameras() {
                let _ = camera.project_point(DVec3::ZERO);
                let _ = camera.resized(8, 8).project_point(DVec3::ONE);
            }
            if let Ok(bundle) = SceneBundle::load(&folder) {
                stylize_first_view(&bundle);
            }
            true
        });
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A geometry checkpoint of 8 Gaussians of SH degree 1, with non-trivial training state.
fn geometry_checkpoint() -> Vec<u8> {
    let mut scene = synthetic_scene(8, 5);
    scene.sh_degree = 1;
    scene.sh = (0..scene.len() * 4)
        .map(|i| [0.1 * i as f32, -0.2, 0.3])
        .collect();
    let mut model =
        GaussianModel::new(scene, &LearningRates::default(), AdamConfig::default(), 1.5).unwrap();
    model.active_sh_degree = 1;
    model.stats.visible_count = (0..8).collect();
    model.stats.grad_norm_sum = (0..8).map(|i| i as f64 * 0.25).collect();
    GeometryCheckpoint {
        step: 120,
        model,
        view_stack: vec![3, 0, 2],
        ema_loss: 0.125,
        ema_psnr: 21.5,
        seed: 9,
        extent: 1.5,
        config_json: "{\"iterations\":30000}".into(),
    }
    .to_bytes()
    .unwrap()
}

#[test]
fn geometry_checkpoints_never_panic() {
    let dir = scratch_dir("fuzz", "geometry-checkpoint");
    let file = dir.join("checkpoint.safetensors");
    Target::new("geometry checkpoint", 5_000)
        .seed(geometry_checkpoint())
        .mutators(safetensors_header(
            [byte_mutators(), text_mutators()].concat(),
        ))
        .run(move |bytes| {
            write_input(&file, bytes);
            let step = checkpoint_step(&file);
            let Ok(ck) = GeometryCheckpoint::from_bytes(bytes, &file) else {
                return false;
            };
            let saved = ck.to_bytes().expect("a loaded checkpoint serialises");
            let back = GeometryCheckpoint::from_bytes(&saved, &file).expect("and reads back");
            assert_eq!(back.to_bytes().unwrap(), saved, "a save/load round trip");
            assert_eq!(
                step.ok(),
                Some(ck.step),
                "checkpoint_step reads the step of a checkpoint that loads"
            );
            true
        });
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn decoder_checkpoints_never_panic() {
    let (encoder, decoder) = fixture_networks();
    let contents = shared_images("data/content", &["chicago.jpg", "flowers.jpg"], 40);
    let styles = shared_images("data/styles", &["mondrian.jpg", "sketch.png"], 40);
    let config = DecoderTrainConfig {
        iterations: 1,
        batch_size: 1,
        resize: 40,
        crop: 32,
        eval_pairs: 1,
        eval_interval: 0,
        checkpoint_interval: 0,
        ..DecoderTrainConfig::default()
    };
    let mut trainer = DecoderTrainer::new(
        encoder.clone(),
        decoder,
        contents.clone(),
        styles.clone(),
        config.clone(),
    )
    .unwrap();
    trainer.train_step().unwrap();
    let seed = trainer.checkpoint_bytes().unwrap();
    let dir = scratch_dir("fuzz", "decoder-checkpoint");
    let file = dir.join("checkpoint.safetensors");
    let again = dir.join("again.safetensors");
    Target::new("decoder checkpoint", 1_000)
        .seed(seed)
        .mutators(safetensors_header(
            [byte_mutators(), text_mutators()].concat(),
        ))
        .run(move |bytes| {
            write_input(&file, bytes);
            let resume = |path: &Path| {
                DecoderTrainer::resume(
                    path,
                    encoder.clone(),
                    contents.clone(),
                    styles.clone(),
                    config.clone(),
                )
            };
            let Ok(t) = resume(&file) else {
                return false;
            };
            let saved = t.checkpoint_bytes().expect("a resumed run saves");
            write_input(&again, &saved);
            let back = resume(&again).expect("and resumes from what it saved");
            assert_eq!(
                back.checkpoint_bytes().unwrap(),
                saved,
                "a save/resume round trip"
            );
            true
        });
    std::fs::remove_dir_all(&dir).unwrap();
}
