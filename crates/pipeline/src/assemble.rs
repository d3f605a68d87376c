//! Finding a sharded run from its output, for `dsgs assemble`: the shard folders of the
//! sharded commands (stylize, eval, bake) are searched for manifests, which must belong to one
//! run, and the command line they recorded is returned to be run again as the assembly.

use std::path::{Path, PathBuf};

use crate::error::{bail, Context, Result};
use crate::shard::{check_one_run, read_manifests, Invocation};

/// A sharded run found by [`find_run`] from its output.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordedRun {
    /// The run's output, made absolute (the recorded command line may name it relative to
    /// another working directory).
    pub output: PathBuf,
    /// The first manifest found, in name order.
    pub manifest: PathBuf,
    /// The sharded command: `stylize`, `eval` or `bake`.
    pub command: String,
    /// The command line the shards were made with, to run again as their assembly.
    pub invocation: Invocation,
}

/// Finds the shards of the run whose output is `output` (the folder of `dsgs stylize -o`, the
/// report of `dsgs eval -o` or the `.ply` of `dsgs bake -o`): looks for manifests in the shard
/// folder of each sharded command ([`crate::stylize::shard_dir`], [`crate::eval::shard_dir`],
/// [`crate::bake::shard_dir`]), checks that those of the first folder holding any belong to one
/// run ([`check_one_run`]) and returns the command line they recorded. Whether every shard has
/// finished is checked later, by the assembly ([`crate::shard::collect`]). The error names the output and the
/// folders looked in when there are no manifests.
pub fn find_run(output: &Path) -> Result<RecordedRun> {
    let absolute =
        std::path::absolute(output).with_context(|| format!("resolving {}", output.display()))?;
    let places = [
        (
            crate::stylize::shard_dir(&absolute),
            crate::stylize::SHARD_COMMAND,
        ),
        (
            crate::eval::shard_dir(&absolute),
            crate::eval::SHARD_COMMAND,
        ),
        (
            crate::bake::shard_dir(&absolute),
            crate::bake::SHARD_COMMAND,
        ),
    ];
    for (dir, command) in &places {
        if !dir.is_dir() {
            continue;
        }
        let manifests = read_manifests(dir, command)?;
        check_one_run(dir, &manifests)?;
        let Some((path, manifest)) = manifests.into_iter().next() else {
            continue;
        };
        let Some(invocation) = manifest.invocation else {
            bail!(
                "{}: the manifest records no command line to assemble with",
                path.display()
            );
        };
        return Ok(RecordedRun {
            output: absolute,
            manifest: path,
            command: manifest.command,
            invocation,
        });
    }
    // The eval and bake folders are one path: `OUTPUT` with the extension `shards`.
    bail!(
        "{}: no shard manifests in {} (stylize) or {} (eval, bake): run the shards with \
         --shard K/N first",
        output.display(),
        places[0].0.display(),
        places[1].0.display()
    )
}
