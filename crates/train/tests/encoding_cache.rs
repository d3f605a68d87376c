//! The setup of feature training: its progress events, the encoding cache (reused encodings
//! train bit-identically; unsound, mismatched or stale cache files are never trusted) and the
//! up-front decoding of the style images (a bad file stops the setup before anything is
//! encoded or written). A tiny synthetic scene (300 Gaussians, three 32 x 32 views) with the
//! oracle's networks.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use common::{
    fixture_networks, net_bits, render_views, shared_images, sphere_cameras, synthetic_scene,
};
use dsgs_testkit::{scratch_dir, shared_path};
use runtime::bundle::Variant;
use train::features::{
    FeatureInputs, FeatureSetup, FeatureStepReport, FeatureTrainConfig, FeatureTrainer,
};
use train::image_folder::ImageSet;
use train::{Event, Stage, TrainError};

const VIEWS: usize = 3;
const STYLES: usize = 2;

fn inputs() -> FeatureInputs {
    let (encoder, decoder) = fixture_networks();
    let geometry = synthetic_scene(300, 11);
    let views = render_views(&geometry, &sphere_cameras(VIEWS, 4.0, 32, 36.0), [0.0; 3]);
    FeatureInputs {
        geometry,
        views,
        cameras: Vec::new(),
        styles: shared_images("data/styles", &["brushstrokes.jpg", "mondrian.jpg"], 40),
        encoder,
        decoder,
        background: [0.0; 3],
        provenance: Vec::new(),
    }
}

fn config() -> FeatureTrainConfig {
    FeatureTrainConfig {
        iterations: 3,
        feature_dim: 8,
        variant: Variant::Fullres,
        crop: Some(16),
        style_size: 32,
        lr_features: 0.05,
        lr_lifter: 0.01,
        seed: 5,
        checkpoint_interval: 0,
        ..FeatureTrainConfig::default()
    }
}

/// What a run computes from its setup: three iterations' reports and the bits of the trained
/// features, lifter and scene statistics.
#[derive(Debug, PartialEq)]
struct Trained {
    reports: Vec<FeatureStepReport>,
    features: Vec<u32>,
    lifter: Vec<u32>,
    scene_stats: Vec<u32>,
}

fn train(mut t: FeatureTrainer) -> Trained {
    let reports = (0..3).map(|_| t.train_step().unwrap()).collect();
    let (mean, std) = t.scene_stats();
    Trained {
        reports,
        features: t.scene().features.iter().map(|v| v.to_bits()).collect(),
        lifter: net_bits(std::iter::once(t.lifter().layer())),
        scene_stats: mean.iter().chain(std).map(|v| v.to_bits()).collect(),
    }
}

/// Sets up a run with the cache folder `cache`, collecting the events.
fn set_up(
    config: FeatureTrainConfig,
    inputs: FeatureInputs,
    cache: &Path,
) -> (Result<FeatureTrainer, TrainError>, Vec<Event>) {
    let events = Mutex::new(Vec::new());
    let sink = |e: Event| events.lock().unwrap().push(e);
    let setup = FeatureSetup {
        sink: &sink,
        cache: Some(cache),
    };
    let t = FeatureTrainer::new_with(config, inputs, &setup);
    (t, events.into_inner().unwrap())
}

/// The setup's summary line.
fn summary(events: &[Event]) -> &str {
    events
        .iter()
        .find_map(|e| match e {
            Event::Log {
                stage: Stage::Prepare,
                message,
            } => Some(message.as_str()),
            _ => None,
        })
        .expect("a summary line")
}

/// How many encodings the summary says were read from the cache.
fn reused(events: &[Event]) -> usize {
    let s = summary(events);
    let at = s.find(" reused from ").unwrap_or_else(|| panic!("{s}"));
    let count = s[..at].rsplit('(').next().unwrap();
    count.parse().unwrap_or_else(|_| panic!("{s}"))
}

/// The cache files of a folder, sorted.
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

fn named(dir: &Path, prefix: &str) -> Vec<PathBuf> {
    files(dir)
        .into_iter()
        .filter(|p| p.file_name().unwrap().to_string_lossy().starts_with(prefix))
        .collect()
}

#[test]
fn the_setup_reports_progress_and_reused_encodings_train_bit_identically() {
    let dir = scratch_dir("enccache", "reuse");
    let cache = dir.join("encodings");
    let reference = train(FeatureTrainer::new(config(), inputs()).unwrap());

    let (t, events) = set_up(config(), inputs(), &cache);
    assert_eq!(train(t.unwrap()), reference);
    assert_eq!(reused(&events), 0);
    assert_eq!(named(&cache, "view-").len(), VIEWS);
    assert_eq!(named(&cache, "style-").len(), STYLES);
    // One Prepare stage: every style decoded, then every view and style encoded.
    let total = (2 * STYLES + VIEWS) as u64;
    assert!(matches!(
        events.first(),
        Some(Event::StageStarted { stage: Stage::Prepare, total: t, done: 0 }) if *t == total
    ));
    let progress: Vec<(u64, &str)> = events
        .iter()
        .filter_map(|e| match e {
            Event::Progress {
                stage: Stage::Prepare,
                done,
                status,
            } => Some((*done, status.as_str())),
            _ => None,
        })
        .collect();
    assert!(progress.windows(2).all(|w| w[0].0 < w[1].0), "{progress:?}");
    assert_eq!(progress.last().map(|p| p.0), Some(total));
    let mut steps: Vec<&str> = progress.iter().map(|p| p.1).collect();
    steps.dedup();
    assert_eq!(steps, ["decode styles", "encode views", "encode styles"]);
    assert!(events.iter().any(|e| matches!(
        e,
        Event::StageFinished { stage: Stage::Prepare, done, .. } if *done == total
    )));

    // Again with the filled cache: everything is read back and trains the same, bit for bit.
    let (t, events) = set_up(config(), inputs(), &cache);
    assert_eq!(reused(&events), VIEWS + STYLES);
    assert_eq!(train(t.unwrap()), reference);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn unsound_mismatched_and_stale_cache_files_are_never_trusted() {
    let dir = scratch_dir("enccache", "unsound");
    let cache = dir.join("encodings");
    let reference = train(FeatureTrainer::new(config(), inputs()).unwrap());
    let (t, _) = set_up(config(), inputs(), &cache);
    drop(t.unwrap());
    let views = named(&cache, "view-");
    let styles = named(&cache, "style-");
    let view0 = std::fs::read(&views[0]).unwrap();
    // A flipped bit inside view 0's values.
    let mut flipped = view0.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x10;
    std::fs::write(&views[0], &flipped).unwrap();
    // View 1's file holding view 0's (sound) encoding: same length, another key.
    std::fs::write(&views[1], &view0).unwrap();
    // A truncated style file.
    let style0 = std::fs::read(&styles[0]).unwrap();
    std::fs::write(&styles[0], &style0[..style0.len() - 9]).unwrap();
    // A file of another run.
    let stale = cache.join("view-0123456789abcdef.bin");
    std::fs::write(&stale, b"DSGSENC2 of another image").unwrap();

    let (t, events) = set_up(config(), inputs(), &cache);
    assert_eq!(train(t.unwrap()), reference);
    assert_eq!(reused(&events), VIEWS + STYLES - 3, "{}", summary(&events));
    assert!(
        summary(&events).contains("3 unsound cache files encoded again"),
        "{}",
        summary(&events)
    );
    assert!(!stale.exists(), "a file no longer used is removed");
    // The unsound files were rewritten.
    let (t, events) = set_up(config(), inputs(), &cache);
    assert_eq!(reused(&events), VIEWS + STYLES);
    assert_eq!(train(t.unwrap()), reference);

    // Another style size: the views are reused, the styles encoded again, and the run is the
    // uncached one of that configuration; the old style files are removed.
    let mut small = config();
    small.style_size = 24;
    let (t, events) = set_up(small.clone(), inputs(), &cache);
    assert_eq!(reused(&events), VIEWS);
    assert_eq!(
        train(t.unwrap()),
        train(FeatureTrainer::new(small, inputs()).unwrap())
    );
    assert_eq!(files(&cache).len(), VIEWS + STYLES);

    // Another encoder: nothing is reused.
    let other = || {
        let mut i = inputs();
        let layer = i.encoder.layers_mut().next().unwrap();
        layer.bias[0] += 0.01;
        i
    };
    let (t, events) = set_up(config(), other(), &cache);
    assert_eq!(reused(&events), 0);
    assert_eq!(
        train(t.unwrap()),
        train(FeatureTrainer::new(config(), other()).unwrap())
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_style_image_that_does_not_decode_stops_the_setup_before_anything_is_encoded() {
    let dir = scratch_dir("enccache", "bad-style");
    // A PNG cut short: its header is sound, its pixels are not.
    let png = std::fs::read(shared_path("data/styles/sketch.png")).unwrap();
    let bad = dir.join("cut.png");
    std::fs::write(&bad, &png[..png.len() / 3]).unwrap();
    let styles =
        ImageSet::from_files(vec![shared_path("data/styles/mondrian.jpg"), bad.clone()]).unwrap();
    let e = styles.check_decodes(&mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("cut.png"), "{e}");

    let cache = dir.join("encodings");
    let (t, events) = set_up(config(), FeatureInputs { styles, ..inputs() }, &cache);
    let e = t.err().expect("the setup fails").to_string();
    assert!(e.contains("cut.png"), "{e}");
    let encoded = events
        .iter()
        .any(|e| matches!(e, Event::Progress { status, .. } if status.starts_with("encode")));
    assert!(!encoded, "encoding started before the styles were decoded");
    assert!(!cache.exists(), "the failed setup wrote into its cache");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_cache_that_cannot_be_written_warns_once_and_trains_as_without_it() {
    let dir = scratch_dir("enccache", "unwritable");
    // The cache path is a file: nothing can be read from it or written under it.
    let cache = dir.join("encodings");
    std::fs::write(&cache, b"not a folder").unwrap();
    let (t, events) = set_up(config(), inputs(), &cache);
    assert_eq!(
        train(t.unwrap()),
        train(FeatureTrainer::new(config(), inputs()).unwrap())
    );
    assert_eq!(reused(&events), 0, "{}", summary(&events));
    let warnings: Vec<&String> = events
        .iter()
        .filter_map(|e| match e {
            Event::Warning(w) => Some(w),
            _ => None,
        })
        .collect();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(
        warnings[0].starts_with("encodings not cached: ")
            && warnings[0].contains(&*cache.to_string_lossy()),
        "{}",
        warnings[0]
    );
    assert_eq!(std::fs::read(&cache).unwrap(), b"not a folder");
    std::fs::remove_dir_all(&dir).ok();
}
