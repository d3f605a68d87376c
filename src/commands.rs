//! What each command does with its arguments: builds the pipeline's settings, runs the stage
//! with the terminal front end and the stop flag, and prints the summary the pipeline formats.
//! A training run a stop request ended becomes the [`Interrupted`] outcome.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};
use pipeline::bake::{BakeOverrides, BakeSettings};
use pipeline::cameras::{default_source, KnownCameras};
use pipeline::fit_features::{FeatureOverrides, FitFeaturesSettings};
use pipeline::fit_geometry::{FitSettings, GeometryOverrides};
use pipeline::open::load_bundle;
use pipeline::pretrain_decoder::{DecoderOverrides, NetworkFiles, PretrainSettings};
use pipeline::render::{render_views, SceneInput};
use pipeline::shard::Part;
use pipeline::{Control, RunOutcome};

use crate::args::{
    AssembleArgs, BakeArgs, Command, DemoArgs, EvalArgs, FitFeaturesArgs, FitGeometryArgs,
    PretrainDecoderArgs, RenderArgs, RunPipelineArgs, StylizeArgs, StylizeImageArgs, ViewArgs,
};
use crate::terminal::Terminal;

/// Exit status of a run that a stop request (SIGINT, SIGTERM or SIGHUP) ended early (128 +
/// SIGINT, the shell convention for an interrupted command).
pub const INTERRUPTED_EXIT: u8 = 130;

/// A training run that a signal stopped after writing its checkpoint: not an error, but not a
/// finished run either; the message says how to resume.
#[derive(Debug)]
struct Interrupted(String);

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Interrupted {}

/// Whether a stop request ended the command: a stopped training run, or a stage that stopped
/// with nothing to resume from.
pub fn is_interrupted(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.is::<Interrupted>()
            || matches!(c.downcast_ref(), Some(pipeline::Error::Interrupted(_)))
            || matches!(c.downcast_ref(), Some(train::TrainError::Interrupted(_)))
    })
}

/// The stop flag of the training commands, set by the first Ctrl-C, SIGTERM or SIGHUP: the run
/// ends after the current iteration, writes a checkpoint to resume from and exits with status
/// [`INTERRUPTED_EXIT`]. A second signal exits at once, deleting the temporary files of writes in progress.
fn stop_flag() -> Option<&'static AtomicBool> {
    static STOP: AtomicBool = AtomicBool::new(false);
    let installed = ctrlc::set_handler(|| {
        if STOP.swap(true, Ordering::SeqCst) {
            // A checkpoint or output being written is abandoned: delete its temporary file.
            base::fs::remove_unfinished_writes();
            eprintln!("\ninterrupted again: exiting without a checkpoint");
            std::process::exit(INTERRUPTED_EXIT.into());
        }
        eprintln!("\nstop requested: stopping after this iteration and writing a checkpoint (Ctrl-C again to exit at once)");
    });
    match installed {
        Ok(()) => Some(&STOP),
        Err(e) => {
            eprintln!("warning: no stop-signal handler ({e}); an interrupted run resumes from its last periodic checkpoint");
            None
        }
    }
}

/// Runs `f` with a terminal front end for `command` (bars unless `no_progress`) and the stop
/// flag.
fn with_control<T>(
    command: &'static str,
    no_progress: bool,
    f: impl FnOnce(&Control) -> pipeline::Result<T>,
) -> Result<T> {
    let terminal = Terminal::new(command, !no_progress);
    Ok(f(&Control {
        sink: &terminal,
        stop: stop_flag(),
    })?)
}

/// The closing lines of a training run: iterations and rate, the checkpoint and the output. A
/// run a stop request ended becomes the [`Interrupted`] outcome, which says how to resume.
fn finish(run: &RunOutcome, checkpoint: Option<&Path>) -> Result<()> {
    let done = run.step - run.first_step;
    print!(
        "{done} iterations in {:.1} s ({:.2} it/s)",
        run.seconds,
        run.rate()
    );
    match checkpoint.or(run.stop_checkpoint.as_deref()) {
        Some(p) => println!("; checkpoint {}", p.display()),
        None => println!(),
    }
    if let Some((what, p)) = &run.output {
        println!("{what} written to {}", p.display());
    }
    match (&run.stop_checkpoint, run.interrupted) {
        (Some(p), true) => Err(Interrupted(format!(
            "stopped early at iteration {}; resume with --resume {}",
            run.step,
            p.display()
        ))
        .into()),
        (None, true) => Err(Interrupted(format!("stopped early at iteration {}", run.step)).into()),
        _ => Ok(()),
    }
}

/// The last line of a shard: how to merge the shards of `output`.
fn assemble_hint(output: &Path) {
    println!(
        "when every shard has finished: dsgs assemble {}",
        output.display()
    );
}

pub fn fit_geometry(a: FitGeometryArgs) -> Result<()> {
    let settings = FitSettings {
        resume: a.run.resume,
        overrides: GeometryOverrides {
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            ..a.settings.overrides
        },
        ..a.settings
    };
    let r = with_control("fit-geometry", a.run.no_progress, |c| {
        pipeline::fit_geometry::run(&settings, c)
    })?;
    print!("{r}");
    finish(&r.run, None)
}

pub fn pretrain_decoder(a: PretrainDecoderArgs) -> Result<()> {
    let settings = PretrainSettings {
        content: a.content,
        styles: a.styles,
        recursive: a.recursive,
        eval_content: a.eval_content,
        eval_styles: a.eval_styles,
        networks: NetworkFiles {
            weights: a.weights,
            encoder: a.encoder,
            decoder: a.decoder,
        },
        from_scratch: a.from_scratch,
        style_network: a.style_network,
        out_dir: a.output,
        config: a.config,
        resume: a.run.resume,
        overrides: DecoderOverrides {
            variant: a.variant,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            ..a.overrides
        },
    };
    let r = with_control("pretrain-decoder", a.run.no_progress, |c| {
        pipeline::pretrain_decoder::run(&settings, c)
    })?;
    print!("{r}");
    finish(&r.run, Some(&r.checkpoint))
}

pub fn fit_features(a: FitFeaturesArgs) -> Result<()> {
    let settings = FitFeaturesSettings {
        geometry: a.geometry,
        dataset: a.dataset.path()?,
        styles: a.styles,
        eval_styles: a.eval_styles,
        networks: NetworkFiles {
            weights: Some(a.weights),
            encoder: None,
            decoder: a.decoder,
        },
        out_dir: a.output,
        config: a.config,
        resume: a.run.resume,
        overrides: FeatureOverrides {
            variant: a.variant,
            decoder_mode: a.decoder_mode,
            lr_decoder: a.lr_decoder,
            normalize: a.normalize,
            eval_every: a.eval_every,
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            ..a.overrides
        },
        encoding_cache: !a.no_encoding_cache,
    };
    let r = with_control("fit-features", a.run.no_progress, |c| {
        pipeline::fit_features::run(&settings, c)
    })?;
    print!("{r}");
    finish(&r.run, Some(&r.checkpoint))
}

pub fn bake(a: BakeArgs, part: Part) -> Result<()> {
    let settings = BakeSettings {
        bundle: a.bundle,
        styles: a.styles,
        weights: a.mix,
        alpha: a.alpha,
        style_side: a.style.style_size,
        variant: a.style.variant,
        decoder: a.style.decoder,
        config: a.config,
        overrides: BakeOverrides {
            log_every: a.run.log_every,
            checkpoint_every: a.run.checkpoint_every,
            ..a.overrides
        },
        output: a.output,
        resume: a.run.resume,
        part: if part == Part::Assemble {
            Part::Assemble
        } else {
            Part::Whole
        },
    };
    if let Part::Shard { shard, invocation } = part {
        let done = with_control("bake", a.run.no_progress, |c| {
            pipeline::bake::render_target_shard(&settings, shard, invocation, c)
        })?;
        print!("{done}");
        assemble_hint(&settings.output);
        return Ok(());
    }
    let out = with_control("bake", a.run.no_progress, |c| {
        pipeline::bake::run(&settings, c)
    })?;
    print!("{out}");
    finish(&out.run, None)
}

pub fn render(a: RenderArgs) -> Result<()> {
    let scene = SceneInput::open(&a.scene.path()?)?;
    let source = default_source("render");
    let cams = (a.cameras).select(source, scene.known_cameras(), scene.gaussians())?;
    let terminal = Terminal::new("render", !a.no_progress);
    let look = (a.what, a.depth_style);
    let written = render_views(&scene, &cams, look, a.background, &a.output, &terminal)?;
    println!("{} images written to {}", written.len(), a.output.display());
    Ok(())
}

pub fn run(a: RunPipelineArgs) -> Result<()> {
    let plan = pipeline::run::plan(&a.settings)?;
    print!("{}", pipeline::run::describe(&plan));
    let r = with_control("run", a.no_progress, |c| match a.no_estimate {
        true => pipeline::run::execute(&plan, c),
        false => pipeline::estimate::execute_estimated(&plan, c),
    })?;
    print!("{r}");
    Ok(())
}

pub fn demo(a: DemoArgs) -> Result<()> {
    let r = with_control("demo", a.no_progress, |c| {
        pipeline::demo::run(&a.settings, c)
    })?;
    print!("{r}");
    Ok(())
}

pub fn stylize(a: StylizeArgs, part: Part) -> Result<()> {
    let style = a.style;
    let bundle = load_bundle(
        &a.bundle,
        style.bundle.variant,
        style.bundle.decoder.as_deref(),
    )?;
    let known = KnownCameras::from_bundle(&bundle, &a.bundle.display().to_string());
    let cams = a
        .cameras
        .select(default_source("stylize"), known, &bundle.scene)?;
    let settings = pipeline::stylize::StylizeSettings {
        styles: style.styles,
        weights: style.mix,
        alpha: style.alpha,
        preserve_colour: style.preserve_colour,
        style_side: style.bundle.style_size,
        out_dir: a.output.clone(),
        gif: a.gif,
        mp4: a.mp4,
        fps: a.fps,
        sheet_views: a.sheet_views,
        tile_budget: style.tile_budget << 20,
        part,
    };
    let terminal = Terminal::new("stylize", !a.no_progress);
    let out = pipeline::stylize::run(&bundle, &cams, &settings, &terminal)?;
    print!("{}", out.summary(cams.len(), &settings));
    Ok(())
}

pub fn eval(a: EvalArgs, part: Part) -> Result<()> {
    let terminal = Terminal::new("eval", !a.no_progress);
    if part != Part::Whole && a.frames_dir.is_some() {
        bail!("--shard splits the evaluation of a bundle's stylized frames, not of --frames-dir");
    }
    let report = if let Some(frames_dir) = &a.frames_dir {
        let scene_path = a
            .scene
            .as_ref()
            .or(a.bundle.as_ref())
            .context("--frames-dir needs the geometry: --scene PLY_OR_BUNDLE")?;
        let scene = SceneInput::open(scene_path)?;
        let known = scene.known_cameras();
        let cams = a
            .cameras
            .select(default_source("eval"), known, scene.gaussians())?;
        pipeline::eval::evaluate_frames(
            &scene,
            &cams,
            frames_dir,
            &a.warp,
            a.measure_with.as_deref(),
            &terminal,
        )?
    } else {
        let Some(dir) = &a.bundle else {
            bail!("give a scene bundle to evaluate (or --frames-dir DIR --scene SCENE)");
        };
        let style = a.style;
        let bundle = load_bundle(dir, style.bundle.variant, style.bundle.decoder.as_deref())?;
        let known = KnownCameras::from_bundle(&bundle, &dir.display().to_string());
        let cams = a
            .cameras
            .select(default_source("eval"), known, &bundle.scene)?;
        let settings = pipeline::eval::EvalSettings {
            styles: style.styles,
            weights: style.mix,
            alpha: style.alpha,
            preserve_colour: style.preserve_colour,
            style_side: style.bundle.style_size,
            warp: a.warp,
            tile_budget: style.tile_budget << 20,
            baseline: !a.no_baseline,
            frames_out: a.frames_out.clone(),
            measure_with: a.measure_with.clone(),
            part: part.clone(),
        };
        let name = dir.display().to_string();
        if part == Part::Whole {
            pipeline::eval::evaluate_bundle(&bundle, &name, &cams, &settings, &terminal)?
        } else {
            let Some(report) = &a.output else {
                bail!("--shard needs the report path (-o REPORT.json): the shards' partial results go beside it");
            };
            let done = pipeline::eval::evaluate_sharded(
                &bundle, &name, &cams, &settings, report, &terminal,
            )?;
            let Some(done) = done else {
                let Part::Shard { shard, .. } = part else {
                    unreachable!("only a shard returns no report")
                };
                print!("{}", pipeline::eval::shard_line(shard, cams.len(), report));
                assemble_hint(report);
                return Ok(());
            };
            done
        }
    };
    print!("{}", pipeline::eval::table(&report));
    if let Some(p) = &a.output {
        pipeline::eval::write_report(p, &report)?;
        println!("report written to {}", p.display());
    }
    Ok(())
}

/// `dsgs stylize-image PHOTO... --style STYLE... -o OUT`.
pub fn stylize_image(a: StylizeImageArgs) -> Result<()> {
    let settings = pipeline::stylize_image::StylizeImageSettings {
        out_dir: a.output.clone(),
        ..a.settings
    };
    let r = with_control("stylize-image", a.no_progress, |c| {
        pipeline::stylize_image::run(&settings, c)
    })?;
    print!("{}", r.summary(&a.output));
    Ok(())
}

/// `dsgs view SCENE`: serves until the process is stopped.
pub fn view(a: ViewArgs) -> Result<()> {
    let (tx, rx) = std::sync::mpsc::channel::<viewer::Activity>();
    let config = viewer::ViewerConfig {
        styles: a.styles,
        bind: a.bind,
        port: a.port,
        style_side: a.style_size,
        tile_budget: a.tile_budget << 20,
        max_upload_pixels: a.max_upload_pixels,
        memory_budget: a.memory_budget << 20,
        activity: Some(tx),
        ..viewer::ViewerConfig::new(&a.scene)
    };
    let running = viewer::start(config)
        .with_context(|| format!("starting the viewer of {}", a.scene.display()))?;
    say(&running.banner(&a.scene));
    std::thread::spawn(move || rx.iter().for_each(|e| say(&format!("{e}\n"))));
    running.wait();
    Ok(())
}

/// Prints `text` and flushes; a closed standard output (the reader went away) must not stop
/// the server.
fn say(text: &str) {
    use std::io::Write;
    let mut out = std::io::stdout();
    let _ = out.write_all(text.as_bytes()).and_then(|()| out.flush());
}

/// `dsgs assemble OUTPUT`: finds the shards of OUTPUT ([`pipeline::assemble::find_run`]) and runs
/// their recorded command line again, in its working directory, as the assembly of the shards,
/// writing to OUTPUT.
pub fn assemble(a: AssembleArgs) -> Result<()> {
    let run = pipeline::assemble::find_run(&a.output)?;
    let (manifest, inv) = (&run.manifest, run.invocation);
    std::env::set_current_dir(&inv.cwd).with_context(|| {
        format!(
            "entering {}, the working directory of the shards (recorded in {})",
            inv.cwd.display(),
            manifest.display()
        )
    })?;
    let cli = crate::args::parse_recorded(inv.args).map_err(|e| {
        anyhow::anyhow!(
            "{}: the recorded command line does not parse any more: {}",
            manifest.display(),
            e.render()
        )
    })?;
    match cli.command {
        Command::Stylize(mut s) => {
            s.output = run.output;
            s.no_progress = a.no_progress;
            stylize(s, Part::Assemble)
        }
        Command::Eval(mut e) => {
            e.output = Some(run.output);
            e.no_progress = a.no_progress;
            eval(e, Part::Assemble)
        }
        Command::Bake(mut b) => {
            b.output = run.output;
            b.run.no_progress = a.no_progress;
            if a.resume.is_some() {
                b.run.resume = a.resume;
            }
            bake(b, Part::Assemble)
        }
        _ => bail!(
            "{}: a manifest of `{}`, which is not sharded",
            manifest.display(),
            run.command
        ),
    }
}
