//! `dsgs stylize` sharded over a Slurm job array with the shipped
//! `docs/slurm/dsgs-array.sbatch`: one shard is cancelled while it runs, `dsgs assemble`
//! names it missing, the shard is rerun alone, and the assembled output holds the files of a
//! single process, byte for byte. Needs a Slurm cluster (`.ci/slurm-up` starts one on this
//! machine); without one the test is skipped with a loud message, except under CI.

#![cfg(unix)]

mod common;

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{assert_same_files_except, dsgs, fails, ok, save_tiny_bundle, scratch};
use dsgs_testkit::shared_path;

/// `sbatch` is on PATH and `sinfo` reaches a controller within 15 s (without a slurm.conf it
/// would retry for a minute).
fn slurm_available() -> bool {
    let succeeds = |cmd: &mut Command| {
        let Ok(mut child) = cmd.stdout(Stdio::null()).stderr(Stdio::null()).spawn() else {
            return false;
        };
        let until = Instant::now() + Duration::from_secs(15);
        loop {
            match child.try_wait() {
                Ok(Some(status)) => return status.success(),
                Ok(None) if Instant::now() < until => {
                    std::thread::sleep(Duration::from_millis(100))
                }
                _ => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return false;
                }
            }
        }
    };
    succeeds(Command::new("sbatch").arg("--version")) && succeeds(&mut Command::new("sinfo"))
}

/// The test's wrapper around dsgs, run by the array script as `$DSGS`: task 2 of the first
/// submission records the array's job id in `$TEST_STARTED` and sleeps until it is cancelled;
/// every other run (the rerun of task 2 finds `$TEST_STARTED`) is `$TEST_DSGS` itself.
const WRAPPER: &str = r#"#!/bin/sh
if [ "$SLURM_ARRAY_TASK_ID" = 2 ] && [ ! -e "$TEST_STARTED" ]; then
  echo "$SLURM_ARRAY_JOB_ID" >"$TEST_STARTED.tmp" && mv "$TEST_STARTED.tmp" "$TEST_STARTED"
  exec sleep 600
fi
exec "$TEST_DSGS" "$@"
"#;

/// Array jobs to cancel should the test fail while they may still run.
struct Jobs(Vec<String>);

impl Drop for Jobs {
    fn drop(&mut self) {
        if std::thread::panicking() && !self.0.is_empty() {
            let _ = Command::new("scancel").args(&self.0).status();
        }
    }
}

/// Every `slurm-*.out` of `dir`, for failure messages.
fn job_logs(dir: &Path) -> String {
    let mut names: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("slurm-"))
        })
        .collect();
    names.sort();
    names
        .iter()
        .map(|p| {
            let text = std::fs::read_to_string(p).unwrap_or_default();
            format!("--- {}\n{text}", p.display())
        })
        .collect()
}

/// Starts `sbatch --parsable --wait` (built by `cmd`) and returns it with the job id it prints
/// on submission; the id joins `jobs` before anything else can fail.
fn submit(cmd: &mut Command, jobs: &mut Jobs) -> (Child, String) {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("sbatch runs");
    let mut line = String::new();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    stdout.read_line(&mut line).unwrap();
    // Kept open, lest a later write of sbatch meet a closed pipe.
    child.stdout = Some(stdout.into_inner());
    // "ID" or "ID;CLUSTER".
    let id = line.trim().split(';').next().unwrap().to_string();
    if id.is_empty() {
        let out = child.wait_with_output().unwrap();
        panic!(
            "sbatch submitted nothing: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    jobs.0.push(id.clone());
    (child, id)
}

/// Waits for `child` until `deadline`, then returns its status and error output.
fn finish(mut child: Child, deadline: Instant, dir: &Path) -> Output {
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!(
                "sbatch --wait still waiting at the deadline\n{}",
                job_logs(dir)
            );
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn stylize_sharded_on_slurm_matches_one_process() {
    if !slurm_available() {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI needs a Slurm cluster: sbatch is not on PATH or sinfo fails (run .ci/slurm-up)"
        );
        // Straight to standard error: the test harness would capture eprintln!.
        let _ = writeln!(
            std::io::stderr(),
            "SKIPPED: no Slurm cluster (run .ci/slurm-up as root to start one)"
        );
        return;
    }
    let deadline = Instant::now() + Duration::from_secs(600);
    let dir = scratch("slurm");
    let bundle = save_tiny_bundle(&dir);
    let args = |out: &Path| -> Vec<OsString> {
        let mut v: Vec<OsString> = vec!["stylize".into(), bundle.clone().into()];
        for style in ["data/styles/mondrian.jpg", "data/styles/small-set/3.jpg"] {
            v.extend(["--style".into(), shared_path(style).into()]);
        }
        let opts =
            "--style-size 96 --cameras path --frames 7 --sheet-views 3 --gif --no-progress -o";
        v.extend(opts.split(' ').map(OsString::from));
        v.push(out.into());
        v
    };
    let reference = dir.join("ref");
    ok(dsgs().args(args(&reference)));

    // The array 1-3 through the shipped script, with the test's wrapper as dsgs.
    let out = dir.join("out");
    let started = dir.join("started");
    let wrapper = dir.join("dsgs-wrapper");
    std::fs::write(&wrapper, WRAPPER).unwrap();
    std::fs::set_permissions(&wrapper, std::fs::Permissions::from_mode(0o755)).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/slurm/dsgs-array.sbatch");
    let sbatch = |array: &str| {
        let mut c = Command::new("sbatch");
        c.args(["--parsable", "--wait", "--export=ALL"])
            .arg(format!("--array={array}"))
            .arg("--chdir")
            .arg(&dir)
            .arg("--output")
            .arg(dir.join("slurm-%A_%a.out"))
            .arg(&script)
            .args(args(&out))
            .env("DSGS", &wrapper)
            .env("TEST_DSGS", env!("CARGO_BIN_EXE_dsgs"))
            .env("TEST_STARTED", &started);
        c
    };
    let mut jobs = Jobs(Vec::new());
    // The shard count comes from the array itself here (SLURM_ARRAY_TASK_COUNT).
    let (mut child, id) = submit(sbatch("1-3").env_remove("DSGS_SHARDS"), &mut jobs);

    // Task 2 runs (and waits): cancel it.
    while !started.exists() {
        let ended = child.try_wait().unwrap();
        assert!(
            ended.is_none() && Instant::now() < deadline,
            "task 2 never started (sbatch: {ended:?})\n{}",
            job_logs(&dir)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(std::fs::read_to_string(&started).unwrap().trim(), id);
    let cancel = Command::new("scancel")
        .arg(format!("{id}_2"))
        .output()
        .unwrap();
    assert!(
        cancel.status.success(),
        "scancel {id}_2: {}",
        String::from_utf8_lossy(&cancel.stderr)
    );
    let first = finish(child, deadline, &dir);
    assert!(
        !first.status.success(),
        "the array with a cancelled task succeeded\n{}",
        job_logs(&dir)
    );
    let shard = |k: usize| out.join(format!("shards/stylize-{k}-of-3.json"));
    for k in [1, 3] {
        assert!(shard(k).is_file(), "shard {k} missing\n{}", job_logs(&dir));
    }
    assert!(!shard(2).exists(), "the cancelled shard finished");

    // Assembling names the missing shard.
    let err = fails(dsgs().arg("assemble").arg(&out));
    assert!(err.contains("shard 2 of 3 is missing"), "{err}");
    // Shards 1 and 3 are sound: no complaint about them.
    assert!(
        !err.contains("shard 1/") && !err.contains("shard 3/"),
        "{err}"
    );

    // Shard 2 alone: an array of one task, so the shard count comes from DSGS_SHARDS.
    let (child, _) = submit(sbatch("2").env("DSGS_SHARDS", "3"), &mut jobs);
    let rerun = finish(child, deadline, &dir);
    assert!(
        rerun.status.success(),
        "the rerun of shard 2 failed: {}\n{}",
        String::from_utf8_lossy(&rerun.stderr),
        job_logs(&dir)
    );
    assert!(shard(2).is_file(), "{}", job_logs(&dir));
    ok(dsgs().arg("assemble").arg(&out));

    // The single process's files, byte for byte; the sharded output has its shards beside them.
    for name in ["mondrian", "3"] {
        for i in 0..7 {
            let f = out.join(name).join(format!("frame_{i:04}.png"));
            assert!(f.is_file(), "{}", f.display());
        }
        assert!(out.join(format!("{name}.gif")).is_file());
    }
    assert!(out.join("contact_sheet.png").is_file());
    assert!(!reference.join("shards").exists());
    assert_same_files_except(&reference, &out, &["shards"]);
    std::fs::remove_dir_all(&dir).ok();
}
