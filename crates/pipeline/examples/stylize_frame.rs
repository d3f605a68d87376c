//! Stylizes one view of a scene bundle with a style image and writes it as a PNG.
//!
//! ```text
//! stylize_frame BUNDLE STYLE OUT.png [CAMERA]
//! ```
//!
//! BUNDLE is a scene bundle directory (`dsgs fit-features` writes one), STYLE any image, CAMERA
//! the index of one of the bundle's cameras (default 0), rendered at the bundle's training
//! resolution. The steps are the ones `dsgs stylize` takes for every frame: encode the style,
//! rasterize the camera's feature map, lift, transform and decode. Each step is reported as an
//! event to a sink that prints it.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Result};
use pipeline::cameras::KnownCameras;
use pipeline::open::load_bundle;
use pipeline::stylize::{load_styles, style_targets, DEFAULT_STYLE_SIDE};
use pipeline::{image_io, Event, Sink, Stage};

const USAGE: &str = "usage: stylize_frame BUNDLE STYLE OUT.png [CAMERA]";

/// Prints the events of the stage.
fn print_event(event: Event) {
    match event {
        Event::StageStarted { stage, total, .. } => {
            println!("{}: {total} steps", stage.name())
        }
        Event::Progress { done, status, .. } => println!("  [{done}] {status}"),
        Event::OutputWritten { what, path, .. } => println!("wrote the {what} {}", path.display()),
        Event::StageFinished { seconds, .. } => println!("done in {seconds:.2} s"),
        _ => {}
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (bundle_dir, style, out, camera) = match args.as_slice() {
        [b, s, o] => (b, s, o, "0"),
        [b, s, o, c] => (b, s, o, c.as_str()),
        _ => bail!("{USAGE}"),
    };
    let Ok(camera) = camera.parse::<usize>() else {
        bail!("CAMERA must be a camera index, got `{camera}`\n{USAGE}");
    };
    let sink = print_event;
    let start = Instant::now();
    let mut done = 0;
    let mut step = |status: String| {
        done += 1;
        sink.emit(Event::Progress {
            stage: Stage::Stylize,
            done,
            status,
        });
    };
    sink.emit(Event::StageStarted {
        stage: Stage::Stylize,
        total: 4,
        done: 0,
    });

    let bundle = load_bundle(Path::new(bundle_dir), None, None)?;
    let known = KnownCameras::from_bundle(&bundle, bundle_dir);
    let Some(cam) = known.cameras.get(camera) else {
        bail!(
            "{bundle_dir} has {} cameras, there is no camera {camera}",
            known.cameras.len()
        );
    };
    step(format!(
        "loaded {} Gaussians ({} variant); camera {camera} `{}` is {}x{}",
        bundle.scene.len(),
        bundle.info.variant.as_str(),
        known.names[camera],
        cam.intrinsics.width,
        cam.intrinsics.height
    ));

    let styles = load_styles(&[PathBuf::from(style)], DEFAULT_STYLE_SIDE)?;
    let targets = style_targets(&bundle, &styles, None, None)?;
    let target = &targets[0];
    step(format!(
        "encoded the style `{}` ({}x{})",
        target.name, styles[0].image.width, styles[0].image.height
    ));

    let view = bundle.feature_view(cam)?;
    let shape = view.features.shape();
    step(format!(
        "rasterized the feature map, {} channels at {}x{}",
        shape[1], shape[3], shape[2]
    ));

    let frame = bundle.stylize(
        &view,
        target.stats.deepest(),
        1.0,
        runtime::DEFAULT_TILE_BUDGET_BYTES,
    )?;
    let (image, seconds) = (frame.image, frame.seconds);
    step(format!(
        "lifted and transformed in {:.2} s, decoded in {:.2} s",
        seconds.lift_transform, seconds.decode
    ));

    let out = PathBuf::from(out);
    image_io::write_png(&out, &image)?;
    sink.emit(Event::OutputWritten {
        stage: Stage::Stylize,
        what: "frame",
        path: out,
    });
    sink.emit(Event::StageFinished {
        stage: Stage::Stylize,
        done: 4,
        seconds: start.elapsed().as_secs_f64(),
        interrupted: false,
    });
    Ok(())
}
