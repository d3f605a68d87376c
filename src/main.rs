//! The `dsgs` command-line program: parses the arguments ([`args`]), runs the command
//! ([`commands`]) with the terminal front end of its events ([`terminal`]), and maps the outcome
//! to the exit status.
//!
//! Flag conventions, the same in every command:
//! * a flag naming several paths (`--style`, `--content`) takes one path per occurrence and is
//!   repeated (`--style a.jpg --style b.jpg`);
//! * `--weights` always names a network weights file; the weights of a style mixture are `--mix`;
//! * `--help` shows every flag's default (for flags overriding a `--config` file, the
//!   configuration's default, taken from its `Default`) and its allowed values; out-of-range
//!   numbers are refused while the arguments are parsed, naming the flag and the range;
//! * every long-running command takes `--no-progress`.

use std::process::ExitCode;

use anyhow::{Context, Result};

use args::{Cli, Command, WeightsCommand};
use commands::{is_interrupted, INTERRUPTED_EXIT};

mod args;
mod commands;
mod terminal;

/// Large blocks advised for huge pages (`memory`).
#[global_allocator]
static ALLOCATOR: base::memory::HugePageAdvice = base::memory::HugePageAdvice;

fn main() -> ExitCode {
    base::memory::keep_freed_memory();
    let cli = args::parse();
    // The viewer's server blocks on its socket: it keeps the calling thread. Every other command
    // runs on a thread of rayon's pool, so that its parallel loops start from a worker (a join
    // on the worker's own queue) rather than from outside the pool (a job handed to the pool
    // and the calling thread put to sleep until it is done, at every loop), with the pool's
    // other workers polling for work rather than sleeping between loops.
    let outcome = if matches!(cli.command, Command::View(_)) {
        run(cli)
    } else {
        base::pool::with_workers_awake(|| run(cli))
    };
    match outcome {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if is_interrupted(&e) => {
            eprintln!("{e}");
            ExitCode::from(INTERRUPTED_EXIT)
        }
        Err(e) => {
            eprintln!("error: {}", base::error::chain(&*e));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Weights(WeightsCommand::Import {
            encoder,
            decoder,
            output,
        }) => {
            let w = pipeline::weights::import(encoder.as_deref(), decoder.as_deref())?;
            w.save(&output)
                .with_context(|| format!("writing {}", output.display()))?;
            print!("{}", pipeline::weights::describe(&output)?);
        }
        Command::Weights(WeightsCommand::Info { path }) => {
            print!("{}", pipeline::weights::describe(&path)?);
        }
        Command::FitGeometry(a) => commands::fit_geometry(a)?,
        Command::PretrainDecoder(a) => commands::pretrain_decoder(a)?,
        Command::FitFeatures(a) => commands::fit_features(a)?,
        Command::Bake(a) => {
            let part = a.shard.part()?;
            commands::bake(a, part)?
        }
        Command::Render(a) => commands::render(a)?,
        Command::Stylize(a) => {
            let part = a.shard.part()?;
            commands::stylize(a, part)?
        }
        Command::Eval(a) => {
            let part = a.shard.part()?;
            commands::eval(a, part)?
        }
        Command::Run(a) => commands::run(a)?,
        Command::Demo(a) => commands::demo(a)?,
        Command::Assemble(a) => commands::assemble(a)?,
        Command::View(a) => commands::view(a)?,
        Command::StylizeImage(a) => commands::stylize_image(a)?,
    }
    Ok(())
}
