//! The `dsgs` command-line program.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

/// Zero-shot 3D style transfer on Gaussian splatting (DS-StyleGaussian), exact and CPU-only.
#[derive(Parser)]
#[command(name = "dsgs", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Import PyTorch checkpoints into the canonical weights format, or describe a weights file.
    #[command(subcommand)]
    Weights(WeightsCommand),
}

#[derive(Subcommand)]
enum WeightsCommand {
    /// Convert PyTorch checkpoints (legacy pickle or zip) to one canonical safetensors file.
    Import {
        /// Encoder checkpoint (e.g. vgg_normalised.pth, vgg_normalised_conv3_1.pth, 4SE.pth).
        #[arg(long)]
        encoder: Option<PathBuf>,
        /// Decoder checkpoint (e.g. decoder.pth, feature_invertor_conv3_1.pth, 4SD.pth).
        #[arg(long)]
        decoder: Option<PathBuf>,
        /// Output file (.safetensors).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Print the layout of a weights file (canonical .safetensors or PyTorch .pth).
    Info {
        /// The weights file.
        path: PathBuf,
    },
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
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
            let w = dsgs::weights::import(encoder.as_deref(), decoder.as_deref())?;
            w.save(&output)
                .with_context(|| format!("writing {}", output.display()))?;
            print!("{}", dsgs::weights::describe(&output)?);
        }
        Command::Weights(WeightsCommand::Info { path }) => {
            print!("{}", dsgs::weights::describe(&path)?);
        }
    }
    Ok(())
}
