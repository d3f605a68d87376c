//! Sharding: one run's frames split over independent processes (`--shard K/N`), each writing
//! its part of the run's files and a manifest, and the checks that come before the parts are
//! merged (`dsgs assemble`).
//!
//! Conventions:
//! * shards are numbered from 1: shard `K` of `N` ([`Shard`]) takes the contiguous block of
//!   items ([`Shard::range`]) `floor((K-1) n / N) .. floor(K n / N)` of the `n` items (frames or
//!   target views), so the blocks cover every item once and differ in size by at most one;
//! * a shard writes exactly the files the whole run writes for its items, each atomically, and
//!   its manifest ([`Manifest`], `SHARDS/{command}-{K}-of-{N}.json`, [`manifest_path`]) last:
//!   a shard without a manifest did not finish, and rerunning it alone rewrites its files;
//! * a manifest records the run's fingerprint (a hash of everything its outputs depend on:
//!   the bundle, the cameras, the style statistics and the settings), the size and FNV-1a hash
//!   of every file it wrote, and, for evaluations, its partial sums ([`Manifest::data`]);
//! * [`collect`] reads the manifests of one output and refuses to go on, naming the shards,
//!   when one is missing, belongs to another split or other inputs, or when one of its files is
//!   gone or changed since it was written.

use std::collections::BTreeMap;
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::error::{bail, Context, Error, Result};

/// The `format` of shard manifests.
pub const MANIFEST_FORMAT: &str = "dsgs-shard-v1";

/// One shard of a split: shard `index` (from 1) of `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Shard {
    /// Which shard, from 1 to `count`.
    pub index: usize,
    /// Shards in the split, at least 1.
    pub count: usize,
}

impl Shard {
    /// Shard `index` (from 1) of `count`; the error says what is wrong.
    pub fn new(index: usize, count: usize) -> Result<Shard> {
        if count == 0 {
            bail!("a run splits into at least 1 shard, not 0");
        }
        if !(1..=count).contains(&index) {
            bail!("shard {index} of {count}: shards are numbered from 1 to {count}");
        }
        Ok(Shard { index, count })
    }

    /// The whole run as one shard.
    pub fn whole() -> Shard {
        Shard { index: 1, count: 1 }
    }

    /// This shard's block of `items`: `floor((K-1) n / N) .. floor(K n / N)` (may be empty when
    /// there are more shards than items).
    pub fn range(&self, items: usize) -> Range<usize> {
        let at = |k: usize| (k as u128 * items as u128 / self.count as u128) as usize;
        at(self.index - 1)..at(self.index)
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl FromStr for Shard {
    type Err = Error;

    /// `K/N`, e.g. `2/8`.
    fn from_str(s: &str) -> Result<Shard> {
        let parse = |part: &str, what: &str| {
            part.trim().parse::<usize>().map_err(|_| {
                Error::msg(format!(
                    "shard `{s}`: {what} `{part}` is not a whole number (expected K/N, e.g. 2/8)"
                ))
            })
        };
        let Some((k, n)) = s.split_once('/') else {
            bail!("shard `{s}`: expected K/N, e.g. 2/8 for the second of eight shards");
        };
        Shard::new(parse(k, "K")?, parse(n, "N")?)
    }
}

/// Which part of a run one call does.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Part {
    /// The whole run in one process.
    #[default]
    Whole,
    /// One shard: its items' files and its manifest, nothing that needs every item.
    Shard {
        /// The shard.
        shard: Shard,
        /// The command line, recorded in the manifest for `dsgs assemble`.
        invocation: Option<Invocation>,
    },
    /// The merge of a finished split ([`collect`]): what needs every item (animations,
    /// contact sheet, report), from the shards' files and partial results.
    Assemble,
}

impl Part {
    /// The items this part computes: all of them, the shard's block, or none when assembling.
    pub fn range(&self, items: usize) -> Range<usize> {
        match self {
            Part::Whole => 0..items,
            Part::Shard { shard, .. } => shard.range(items),
            Part::Assemble => 0..0,
        }
    }
}

/// How a command line can be run again: its arguments (after the program name, without
/// `--shard`) and its working directory. Recorded by the program in each manifest, so that
/// `dsgs assemble` can rebuild the run's settings.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Invocation {
    /// The arguments after the program name, without the shard option.
    pub args: Vec<String>,
    /// The working directory the arguments' relative paths are relative to.
    pub cwd: PathBuf,
}

/// The arguments of a command line (after the program name) for an [`Invocation`]: all but the
/// shard option (`--shard K/N` or `--shard=K/N`). They must be UTF-8, to be recorded in a
/// manifest.
pub fn args_without_shard(
    args: impl IntoIterator<Item = std::ffi::OsString>,
) -> Result<Vec<String>> {
    let mut kept = Vec::new();
    let mut args = args.into_iter();
    while let Some(a) = args.next() {
        let Some(a) = a.to_str().map(str::to_string) else {
            bail!("an argument is not valid UTF-8, so the shard's command line cannot be recorded for `dsgs assemble`: {a:?}");
        };
        if a == "--shard" {
            args.next();
        } else if !a.starts_with("--shard=") {
            kept.push(a);
        }
    }
    Ok(kept)
}

/// A file a shard wrote, as it was when the shard finished.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileRecord {
    /// The path relative to the run's output (`/`-separated).
    pub path: String,
    /// Size in bytes.
    pub bytes: u64,
    /// FNV-1a (64-bit) of the contents, 16 hexadecimal digits.
    pub fnv1a: String,
}

/// What one shard did: its place in the split, the run it belongs to, the files it wrote and
/// its partial results.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_FORMAT`].
    pub format: String,
    /// The sharded command: `stylize`, `eval` or `bake`.
    pub command: String,
    /// The shard.
    pub shard: Shard,
    /// Items (frames, target views) in the whole run.
    pub items: usize,
    /// The shard's block of items.
    pub range: Range<usize>,
    /// Hash of everything the run's outputs depend on; equal in every shard of one run.
    pub fingerprint: String,
    /// The command line, when the program recorded it (for `dsgs assemble`).
    pub invocation: Option<Invocation>,
    /// The files the shard wrote.
    pub files: Vec<FileRecord>,
    /// Wall time of the shard, in seconds.
    pub seconds: f64,
    /// The command's partial results (an evaluation's per-view losses and per-pair sums).
    pub data: serde_json::Value,
}

/// The manifest file of a shard: `{dir}/{command}-{K}-of-{N}.json`.
pub fn manifest_path(dir: &Path, command: &str, shard: Shard) -> PathBuf {
    dir.join(format!("{command}-{}-of-{}.json", shard.index, shard.count))
}

/// The record of a file `path` written under `root`: its relative path, size and hash, read
/// back from the disk.
pub fn record_file(root: &Path, path: &Path) -> Result<FileRecord> {
    let bytes = std::fs::read(path).with_context(|| format!("reading back {}", path.display()))?;
    let rel = path.strip_prefix(root).map_err(|_| {
        Error::msg(format!(
            "{} is not inside the output {}",
            path.display(),
            root.display()
        ))
    })?;
    let rel: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    Ok(FileRecord {
        path: rel.join("/"),
        bytes: bytes.len() as u64,
        fnv1a: base::fnv1a_hex(&bytes),
    })
}

/// Writes a shard's manifest into `dir` (atomically) and returns its path.
pub fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<PathBuf> {
    let path = manifest_path(dir, &manifest.command, manifest.shard);
    let json = serde_json::to_vec_pretty(manifest).context("serialising a shard manifest")?;
    base::write_atomic(&path, &json).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// Reads one manifest file.
pub fn read_manifest(path: &Path) -> Result<Manifest> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let m: Manifest = serde_json::from_slice(&bytes)
        .with_context(|| format!("{}: not a shard manifest", path.display()))?;
    if m.format != MANIFEST_FORMAT {
        bail!(
            "{}: format `{}`, expected `{MANIFEST_FORMAT}`",
            path.display(),
            m.format
        );
    }
    Ok(m)
}

/// The manifests of `command` in `dir`, keyed by their file name, sorted by name.
pub fn read_manifests(dir: &Path, command: &str) -> Result<Vec<(PathBuf, Manifest)>> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!(
                "{}: no shard manifests (the folder is missing): run the shards first with \
                 `--shard K/N`",
                dir.display()
            )
        }
        Err(e) => return Err(e).with_context(|| format!("reading {}", dir.display())),
    };
    let prefix = format!("{command}-");
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&prefix) && n.ends_with(".json"))
        })
        .collect();
    paths.sort();
    paths
        .into_iter()
        .map(|p| read_manifest(&p).map(|m| (p, m)))
        .collect()
}

/// Checks that manifests (of one command, from [`read_manifests`]) belong to one run: the same
/// fingerprint. The error names the shards made with other inputs or settings than the most
/// common ones.
pub fn check_one_run(dir: &Path, manifests: &[(PathBuf, Manifest)]) -> Result<()> {
    let mut groups: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for (_, m) in manifests {
        groups
            .entry(&m.fingerprint)
            .or_default()
            .push(m.shard.to_string());
    }
    if groups.len() <= 1 {
        return Ok(());
    }
    let mut groups: Vec<(&str, Vec<String>)> = groups.into_iter().collect();
    groups.sort_by_key(|(_, shards)| std::cmp::Reverse(shards.len()));
    let (main_fp, main) = &groups[0];
    let mut msg = format!(
        "{}: the shards were not all made with the same inputs and settings",
        dir.display()
    );
    for (fp, shards) in &groups[1..] {
        msg += &format!(
            "\n  shard{} {} (fingerprint {fp}) against {} (fingerprint {main_fp})",
            if shards.len() == 1 { "" } else { "s" },
            and_list(shards),
            and_list(main)
        );
    }
    msg += "\nrerun the odd shards with the arguments of the others, or remove their manifests";
    bail!("{msg}")
}

/// Checks one record against the file on disk under `root`.
fn check_file(root: &Path, rec: &FileRecord) -> std::result::Result<(), String> {
    let path = root.join(&rec.path);
    match std::fs::read(&path) {
        Err(e) => Err(format!("{}: {e}", path.display())),
        Ok(b) if b.len() as u64 != rec.bytes || base::fnv1a_hex(&b) != rec.fnv1a => Err(format!(
            "{} has changed since the shard wrote it",
            path.display()
        )),
        Ok(_) => Ok(()),
    }
}

/// What every shard of a run must agree on, checked by [`collect`].
#[derive(Clone, Debug)]
pub struct Expected<'a> {
    /// The sharded command.
    pub command: &'a str,
    /// The fingerprint of the run being assembled.
    pub fingerprint: &'a str,
    /// Items of the whole run.
    pub items: usize,
    /// The run's output, which the file records are relative to.
    pub root: &'a Path,
}

/// `1, 3 and 4`.
fn and_list(items: &[String]) -> String {
    match items {
        [] => String::new(),
        [one] => one.clone(),
        [init @ .., last] => format!("{} and {last}", init.join(", ")),
    }
}

/// Reads and checks the manifests of one sharded run in `dir`: one split (the same `N` in
/// every manifest), every shard `1..=N` present once, each with the expected fingerprint, item
/// count and block, and every file it recorded still as it was. Returns the manifests in shard
/// order; the error names every shard that is missing or unsound and how to redo it.
pub fn collect(dir: &Path, expected: &Expected) -> Result<Vec<Manifest>> {
    let command = expected.command;
    let found = read_manifests(dir, command)?;
    if found.is_empty() {
        bail!(
            "{}: no manifests of `dsgs {command} --shard K/N`: run the shards first",
            dir.display()
        );
    }
    let mut splits: BTreeMap<usize, Vec<&Path>> = BTreeMap::new();
    for (p, m) in &found {
        splits.entry(m.shard.count).or_default().push(p);
    }
    if splits.len() > 1 {
        let list: Vec<String> = splits
            .iter()
            .map(|(n, ps)| format!("{} of {n} shards", ps.len()))
            .collect();
        bail!(
            "{}: manifests of different splits ({}): remove those of the other split, or rerun \
             them in one split",
            dir.display(),
            and_list(&list)
        );
    }
    let count = found[0].1.shard.count;
    let mut problems = Vec::new();
    let mut by_index: BTreeMap<usize, Manifest> = BTreeMap::new();
    for (p, m) in found {
        let k = m.shard.index;
        let mut wrong = Vec::new();
        if m.command != command {
            wrong.push(format!("it is a manifest of `{}`", m.command));
        }
        if m.fingerprint != expected.fingerprint {
            wrong.push(format!(
                "it was made with other inputs or settings (fingerprint {}, this run's is {})",
                m.fingerprint, expected.fingerprint
            ));
        }
        if m.items != expected.items {
            wrong.push(format!(
                "it splits {} items, this run has {}",
                m.items, expected.items
            ));
        } else if m.range != m.shard.range(m.items) {
            wrong.push(format!(
                "its block {:?} is not that of shard {}",
                m.range, m.shard
            ));
        }
        if wrong.is_empty() {
            wrong.extend(
                m.files
                    .iter()
                    .filter_map(|r| check_file(expected.root, r).err()),
            );
        }
        if !wrong.is_empty() {
            problems.push(format!(
                "shard {} ({}): {}",
                m.shard,
                p.display(),
                wrong.join("; ")
            ));
        } else {
            by_index.insert(k, m);
        }
    }
    let missing: Vec<String> = (1..=count)
        .filter(|k| !by_index.contains_key(k))
        .map(|k| k.to_string())
        .collect();
    if !missing.is_empty() {
        let which = if missing.len() == 1 {
            format!("shard {} of {count} is", missing[0])
        } else {
            format!("shards {} of {count} are", and_list(&missing))
        };
        let mut msg = format!(
            "{which} missing or unsound; rerun {} with `--shard K/{count}` and the same \
             arguments, then assemble again",
            if missing.len() == 1 { "it" } else { "each" }
        );
        for p in &problems {
            msg += &format!("\n  {p}");
        }
        let absent: Vec<String> = missing
            .iter()
            .filter(|k| {
                !problems
                    .iter()
                    .any(|p| p.starts_with(&format!("shard {k}/")))
            })
            .cloned()
            .collect();
        if !absent.is_empty() {
            msg += &format!(
                "\n  no manifest for shard{} {} in {} (a shard writes it last, when it has \
                 finished)",
                if absent.len() == 1 { "" } else { "s" },
                and_list(&absent),
                dir.display()
            );
        }
        bail!("{msg}");
    }
    Ok(by_index.into_values().collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The blocks of a split cover `0..n` once, in order, and differ in size by at most one.
        #[test]
        fn blocks_partition_the_items(n in 0usize..500, count in 1usize..40) {
            let mut next = 0;
            let mut sizes = Vec::new();
            for k in 1..=count {
                let r = Shard::new(k, count).unwrap().range(n);
                prop_assert_eq!(r.start, next);
                next = r.end;
                sizes.push(r.len());
            }
            prop_assert_eq!(next, n);
            let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
            prop_assert!(hi - lo <= 1);
        }
    }

    #[test]
    fn shard_text_is_checked() {
        assert_eq!("2/8".parse::<Shard>().unwrap(), Shard::new(2, 8).unwrap());
        assert_eq!(Shard::new(3, 5).unwrap().to_string(), "3/5");
        for bad in ["0/3", "4/3", "1/0", "x/3", "3", "1/2/3", ""] {
            let e = bad.parse::<Shard>().unwrap_err().to_string();
            assert!(e.contains("shard"), "{bad}: {e}");
        }
    }

    fn manifest(shard: Shard, items: usize, files: Vec<FileRecord>) -> Manifest {
        Manifest {
            format: MANIFEST_FORMAT.into(),
            command: "stylize".into(),
            shard,
            items,
            range: shard.range(items),
            fingerprint: "f".into(),
            invocation: None,
            files,
            seconds: 0.0,
            data: serde_json::Value::Null,
        }
    }

    #[test]
    fn collect_names_missing_changed_and_foreign_shards() {
        let root = dsgs_testkit::scratch_dir("pipeline-shard", "collect");
        let dir = root.join("shards");
        let expected = Expected {
            command: "stylize",
            fingerprint: "f",
            items: 7,
            root: &root,
        };
        let mut records = Vec::new();
        for k in 1..=3 {
            let f = root.join(format!("part{k}.bin"));
            base::write_atomic(&f, format!("shard {k}").as_bytes()).unwrap();
            records.push(record_file(&root, &f).unwrap());
        }
        let s = |k| Shard::new(k, 3).unwrap();
        write_manifest(&dir, &manifest(s(1), 7, vec![records[0].clone()])).unwrap();
        write_manifest(&dir, &manifest(s(3), 7, vec![records[2].clone()])).unwrap();
        let e = collect(&dir, &expected).unwrap_err().to_string();
        assert!(e.contains("shard 2 of 3 is missing"), "{e}");

        write_manifest(&dir, &manifest(s(2), 7, vec![records[1].clone()])).unwrap();
        let all = collect(&dir, &expected).unwrap();
        let ranges: Vec<_> = all.iter().map(|m| m.range.clone()).collect();
        assert_eq!(ranges, vec![0..2, 2..4, 4..7]);

        // A file changed after its shard finished.
        base::write_atomic(&root.join("part3.bin"), b"other").unwrap();
        let e = collect(&dir, &expected).unwrap_err().to_string();
        assert!(e.contains("shard 3 of 3") && e.contains("part3.bin"), "{e}");
        base::write_atomic(&root.join("part3.bin"), b"shard 3").unwrap();

        // Another run's fingerprint.
        let other = Expected {
            fingerprint: "g",
            ..expected.clone()
        };
        let e = collect(&dir, &other).unwrap_err().to_string();
        assert!(
            e.contains("shards 1, 2 and 3 of 3") && e.contains("fingerprint"),
            "{e}"
        );

        // A manifest of another split.
        write_manifest(&dir, &manifest(Shard::new(1, 2).unwrap(), 7, vec![])).unwrap();
        let e = collect(&dir, &expected).unwrap_err().to_string();
        assert!(e.contains("different splits"), "{e}");
        std::fs::remove_dir_all(&root).ok();
    }

    #[test]
    fn find_run_names_the_folders_it_looked_in_and_returns_the_recorded_command_line() {
        let root = dsgs_testkit::scratch_dir("pipeline-shard", "find-run");
        let report = root.join("report.json");
        let e = crate::assemble::find_run(&report).unwrap_err().to_string();
        assert!(
            e.contains("report.json: no shard manifests")
                && e.contains(&crate::eval::shard_dir(&report).display().to_string()),
            "{e}"
        );

        let dir = crate::eval::shard_dir(&report);
        let mut m = manifest(Shard::new(1, 2).unwrap(), 5, vec![]);
        m.command = crate::eval::SHARD_COMMAND.into();
        write_manifest(&dir, &m).unwrap();
        let e = crate::assemble::find_run(&report).unwrap_err().to_string();
        assert!(e.contains("records no command line"), "{e}");

        let invocation = Invocation {
            args: vec!["eval".into(), "bundle".into()],
            cwd: root.clone(),
        };
        m.invocation = Some(invocation.clone());
        write_manifest(&dir, &m).unwrap();
        let run = crate::assemble::find_run(&report).unwrap();
        assert_eq!(run.command, "eval");
        assert_eq!(run.invocation, invocation);
        assert_eq!(run.output, report);
        std::fs::remove_dir_all(&root).ok();
    }

    #[test]
    fn the_recorded_arguments_leave_out_the_shard_option() {
        let args = [
            "eval",
            "b",
            "--shard",
            "2/3",
            "-o",
            "r.json",
            "--shard=1/3",
            "--no-progress",
        ];
        let kept = args_without_shard(args.map(Into::into)).unwrap();
        assert_eq!(kept, ["eval", "b", "-o", "r.json", "--no-progress"]);
    }
}
