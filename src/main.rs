//! The `dsgs` command-line program.

use clap::Parser;

/// Zero-shot 3D style transfer on Gaussian splatting.
#[derive(Parser)]
#[command(name = "dsgs", version, about)]
struct Cli {}

fn main() -> anyhow::Result<()> {
    let _cli = Cli::parse();
    Ok(())
}
