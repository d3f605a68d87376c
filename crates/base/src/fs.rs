//! The one atomic file write of the workspace: every output file (scenes, checkpoints, weights,
//! images, reports) is written through [`write_atomic`], so a reader never sees a partly
//! written file and an interrupted write leaves the previous file intact.

use std::ffi::OsString;
use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime};

/// Temporary files of interrupted writes older than this are removed by the next write of the
/// same file (a write in progress takes far less).
const STALE_AFTER: Duration = Duration::from_secs(24 * 60 * 60);

/// Writes `bytes` to `path` atomically.
///
/// The bytes go to a temporary file beside `path` (`.NAME.tmp-PID-N`, unique per process and
/// write), which is synced to disk and renamed over `path`; the directory is then synced so
/// that the rename itself survives a crash. Missing parent directories are created. On failure
/// the temporary file is removed and `path` is left as it was. Temporary files that an
/// interrupted earlier write of the same `path` left behind are removed once they are a day
/// old; until then they are ignored (no reader looks at them).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "not a file path"))?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    fs::create_dir_all(&dir)?;
    let prefix = temp_prefix(name);
    remove_stale(&dir, &prefix);
    let mut tmp_name = prefix;
    tmp_name.push(format!(
        "{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let tmp = dir.join(tmp_name);
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        fs::rename(&tmp, path)?;
        sync_dir(&dir)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// `.NAME.tmp-`: the start of every temporary file name of `NAME`.
fn temp_prefix(name: &std::ffi::OsStr) -> OsString {
    let mut p = OsString::from(".");
    p.push(name);
    p.push(".tmp-");
    p
}

/// Removes the temporary files of `prefix` in `dir` older than [`STALE_AFTER`] (best effort).
fn remove_stale(dir: &Path, prefix: &OsString) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    let prefix = prefix.to_string_lossy();
    let now = SystemTime::now();
    for entry in entries.flatten() {
        if !entry.file_name().to_string_lossy().starts_with(&*prefix) {
            continue;
        }
        let old = entry
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| now.duration_since(t).ok())
            .is_some_and(|age| age > STALE_AFTER);
        if old {
            let _ = fs::remove_file(entry.path());
        }
    }
}

/// Flushes a directory's entries (the rename) to disk, where the platform allows it.
fn sync_dir(dir: &Path) -> io::Result<()> {
    #[cfg(unix)]
    {
        fs::File::open(dir)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("dsgs-base-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        d
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn replaces_the_file_and_leaves_no_temporary_file() {
        let d = scratch("replace");
        let p = d.join("out.bin");
        write_atomic(&p, b"first").unwrap();
        write_atomic(&p, b"second").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"second");
        assert_eq!(names(&d), ["out.bin"]);
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn creates_missing_directories() {
        let d = scratch("dirs");
        let p = d.join("a/b/out.txt");
        write_atomic(&p, b"x").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"x");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_failed_write_keeps_the_old_file_and_removes_its_temporary_file() {
        let d = scratch("fail");
        let p = d.join("out.bin");
        write_atomic(&p, b"kept").unwrap();
        // Renaming a file over a non-empty directory fails.
        let blocked = d.join("dir");
        fs::create_dir_all(blocked.join("inner")).unwrap();
        assert!(write_atomic(&blocked, b"lost").is_err());
        assert_eq!(fs::read(&p).unwrap(), b"kept");
        assert_eq!(names(&d), ["dir", "out.bin"]);
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn stale_temporary_files_are_removed_and_fresh_ones_ignored() {
        let d = scratch("stale");
        let p = d.join("out.bin");
        let stale = d.join(".out.bin.tmp-1-0");
        let fresh = d.join(".out.bin.tmp-2-0");
        let other = d.join(".other.bin.tmp-1-0");
        for f in [&stale, &fresh, &other] {
            fs::write(f, b"partial").unwrap();
        }
        let two_days_ago = SystemTime::now() - 2 * STALE_AFTER;
        for f in [&stale, &other] {
            fs::File::options()
                .write(true)
                .open(f)
                .unwrap()
                .set_modified(two_days_ago)
                .unwrap();
        }
        write_atomic(&p, b"data").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"data");
        // Only the old temporary file of the same destination is removed.
        assert_eq!(
            names(&d),
            [".other.bin.tmp-1-0", ".out.bin.tmp-2-0", "out.bin"]
        );
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_path_without_a_file_name_is_an_error() {
        assert_eq!(
            write_atomic(Path::new("/"), b"x").unwrap_err().kind(),
            io::ErrorKind::InvalidInput
        );
    }
}
