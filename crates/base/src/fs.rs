//! The one atomic file write of the workspace: every output file (scenes, checkpoints, weights,
//! images, reports) is written through [`write_atomic`], so a reader never sees a partly
//! written file and an interrupted write leaves the previous file intact. The file and its
//! directory are synced to disk, except through [`write_atomic_unsynced_with`]: the same write
//! without the syncs, for large files whose readers check them and rebuild them when the check
//! fails (the encoding cache). That one also writes around the operating system's page cache
//! where the platform and the file system allow it (Linux `O_DIRECT`, through
//! [`UncachedWriter`]): copying gigabytes into the page cache costs the kernel several CPU-seconds
//! that the program's own threads need, and the pages would only crowd out memory.
//!
//! While a write is in flight its temporary file (`.NAME.tmp-PID-N`, beside the target) is
//! recorded in a process-wide registry, and removed from it once the write has finished or
//! failed. A program that must exit at once, in the middle of a write (a second Ctrl-C during a
//! checkpoint, say), calls [`remove_unfinished_writes`] first: it deletes the temporary files of
//! every write still in flight, so the abandoned writes leave nothing behind, and makes every
//! later write of the process fail instead of starting one. The temporary files of a process
//! that was killed outright are removed by a later write of the same file once they are a day
//! old.

use std::ffi::OsString;
use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard, PoisonError};
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
/// old; until then they are ignored (no reader looks at them). While the write is in flight its
/// temporary file is registered for [`remove_unfinished_writes`]; after that function has run,
/// the write fails with [`io::ErrorKind::Interrupted`] without creating anything.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// Deletes the temporary file of every [`write_atomic`] of this process still in flight (best
/// effort: a file that cannot be removed is skipped) and makes every later [`write_atomic`] of
/// the process fail with [`io::ErrorKind::Interrupted`] without creating a file.
///
/// It is meant for a process about to exit in the middle of a write (e.g. from a second
/// interrupt signal), right before `std::process::exit`: the abandoned writes then leave
/// neither a partial target (there never is one) nor their temporary files. The writes it
/// interrupts fail (their temporary file is gone when they rename it), their targets keep their
/// previous contents.
pub fn remove_unfinished_writes() {
    let mut reg = registry();
    reg.closed = true;
    for tmp in reg.in_flight.drain(..) {
        let _ = fs::remove_file(tmp);
    }
}

/// The temporary files of the writes in flight, and whether [`remove_unfinished_writes`] has
/// run.
struct Registry {
    in_flight: Vec<PathBuf>,
    closed: bool,
}

static REGISTRY: Mutex<Registry> = Mutex::new(Registry {
    in_flight: Vec::new(),
    closed: false,
});

/// The registry; it holds only paths, so a panic while it was locked left nothing inconsistent.
fn registry() -> MutexGuard<'static, Registry> {
    REGISTRY.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Creates the temporary file `tmp` and registers it, both under the registry's lock, so that
/// [`remove_unfinished_writes`] either runs first (and the file is never created) or sees it.
fn create_registered(tmp: &Path) -> io::Result<fs::File> {
    let mut reg = registry();
    if reg.closed {
        return Err(io::Error::new(
            io::ErrorKind::Interrupted,
            "the process is exiting: unfinished writes were abandoned",
        ));
    }
    let f = fs::File::create(tmp)?;
    reg.in_flight.push(tmp.to_path_buf());
    Ok(f)
}

/// Removes `tmp` from the registry (a write that finished, or failed and cleaned up).
fn unregister(tmp: &Path) {
    registry().in_flight.retain(|p| p != tmp);
}

/// [`write_atomic`] with the file's contents written by `write` (for contents streamed in
/// pieces rather than held whole in memory).
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut fs::File) -> io::Result<()>,
) -> io::Result<()> {
    write_atomic_impl(path, true, write)
}

/// [`write_atomic_with`] without its two syncs, for files whose readers verify them (a
/// checksum) and rebuild them when they do not verify, such as caches. A reader still never
/// sees a partly written file while the system runs; after a system crash the file may be
/// missing, old, or (on file systems that let the rename reach the disk before the data) empty
/// or partial, which the reader's check must catch. Syncing is what makes a write of tens of
/// megabytes wait for the disk.
///
/// The contents go through an [`UncachedWriter`], which bypasses the page cache where it can;
/// the file's bytes are the same either way.
pub fn write_atomic_unsynced_with(
    path: &Path,
    write: impl FnOnce(&mut UncachedWriter<'_>) -> io::Result<()>,
) -> io::Result<()> {
    write_atomic_impl(path, false, |f| {
        let mut w = UncachedWriter::new(f, true);
        write(&mut w)?;
        w.finish()
    })
}

/// Alignment of the buffer, file offsets and lengths of a write around the page cache: the
/// page size, a multiple of every logical block size Linux's `O_DIRECT` asks for.
const DIRECT_ALIGN: usize = 4096;

/// Bytes gathered per write (1 MiB, a multiple of [`DIRECT_ALIGN`]).
const DIRECT_BLOCK: usize = 1 << 20;

/// The writer of [`write_atomic_unsynced_with`]: it gathers the bytes in an aligned 1 MiB
/// block and writes whole blocks, with the file opened for direct I/O (Linux `O_DIRECT`, data
/// sent from the block to the device without a copy into the page cache) when the file system
/// accepts it. The last, partial block is padded with zeros to the alignment, written, and the
/// padding cut off again (`set_len`). Where direct I/O is not available (another platform, a
/// file system such as tmpfs that refuses it, or a write it rejects), it writes the same bytes
/// through the page cache; the file is the same either way. [`Write::flush`] writes the whole
/// blocks gathered so far; the rest is written when the write completes.
pub struct UncachedWriter<'f> {
    file: &'f mut fs::File,
    /// One aligned block starts at `start`.
    buf: Vec<u8>,
    start: usize,
    /// Bytes of the block filled.
    filled: usize,
    /// Bytes written to the file so far (the file's offset).
    written: u64,
    direct: bool,
}

impl<'f> UncachedWriter<'f> {
    /// A writer at the start of the empty `file`; `direct` asks for direct I/O.
    fn new(file: &'f mut fs::File, direct: bool) -> Self {
        let buf = vec![0u8; DIRECT_BLOCK + DIRECT_ALIGN];
        let start = buf.as_ptr().align_offset(DIRECT_ALIGN);
        let direct = direct && set_direct(file, true);
        UncachedWriter {
            file,
            buf,
            start,
            filled: 0,
            written: 0,
            direct,
        }
    }

    /// Whether the writes go around the page cache.
    pub fn is_direct(&self) -> bool {
        self.direct
    }

    /// Writes the first `len` bytes of the block (a multiple of [`DIRECT_ALIGN`] while direct);
    /// a direct write the system rejects is written again through the page cache, which stays in
    /// use from then on.
    fn write_block(&mut self, len: usize) -> io::Result<()> {
        let block = &self.buf[self.start..self.start + len];
        if self.direct {
            match self.file.write_all(block) {
                Ok(()) => {
                    self.written += len as u64;
                    return Ok(());
                }
                Err(e) if e.kind() == io::ErrorKind::InvalidInput => {
                    // Whatever part of the block got through before the rejection is cut off,
                    // and the block written again, buffered, from where the file stood.
                    self.direct = false;
                    set_direct(self.file, false);
                    self.file.set_len(self.written)?;
                    use std::io::Seek;
                    self.file.seek(io::SeekFrom::Start(self.written))?;
                }
                Err(e) => return Err(e),
            }
        }
        self.file.write_all(block)?;
        self.written += len as u64;
        Ok(())
    }

    /// Writes what is left and gives the file its exact length.
    fn finish(mut self) -> io::Result<()> {
        let len = self.filled;
        if len == 0 {
            return Ok(());
        }
        if self.direct {
            // Padded to the alignment (written directly, or again through the page cache if the
            // system rejects it), then cut to the exact length.
            let padded = len.next_multiple_of(DIRECT_ALIGN);
            self.buf[self.start + len..self.start + padded].fill(0);
            let exact = self.written + len as u64;
            self.write_block(padded)?;
            return self.file.set_len(exact);
        }
        self.write_block(len)
    }
}

impl Write for UncachedWriter<'_> {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        // A full block is written before more bytes are taken, so that an error takes none.
        if self.filled == DIRECT_BLOCK && !bytes.is_empty() {
            self.write_block(DIRECT_BLOCK)?;
            self.filled = 0;
        }
        let n = bytes.len().min(DIRECT_BLOCK - self.filled);
        let at = self.start + self.filled;
        self.buf[at..at + n].copy_from_slice(&bytes[..n]);
        self.filled += n;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        let whole = self.filled / DIRECT_ALIGN * DIRECT_ALIGN;
        if whole > 0 {
            self.write_block(whole)?;
            let rest = self.filled - whole;
            let at = self.start;
            self.buf.copy_within(at + whole..at + whole + rest, at);
            self.filled = rest;
        }
        Ok(())
    }
}

/// Turns direct I/O on or off for `file`; whether that succeeded (never, off Linux).
fn set_direct(file: &fs::File, on: bool) -> bool {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let fd = file.as_raw_fd();
        // SAFETY: `fcntl` with F_GETFL / F_SETFL and integer flags on a descriptor that `file`
        // owns and keeps open for the call; no memory is passed.
        unsafe {
            let flags = libc::fcntl(fd, libc::F_GETFL);
            if flags < 0 {
                return false;
            }
            let new = if on {
                flags | libc::O_DIRECT
            } else {
                flags & !libc::O_DIRECT
            };
            libc::fcntl(fd, libc::F_SETFL, new) == 0
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = (file, on);
        false
    }
}

/// The write of [`write_atomic_with`]; `sync` syncs the file before the rename and the
/// directory after it.
fn write_atomic_impl(
    path: &Path,
    sync: bool,
    write: impl FnOnce(&mut fs::File) -> io::Result<()>,
) -> io::Result<()> {
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
    let mut f = create_registered(&tmp)?;
    let result = (|| {
        write(&mut f)?;
        if sync {
            f.sync_all()?;
        }
        drop(f);
        fs::rename(&tmp, path)?;
        if sync {
            sync_dir(&dir)?;
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    unregister(&tmp);
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
    use std::sync::{mpsc, RwLock, RwLockReadGuard};

    /// Tests that write hold this shared; the test of [`remove_unfinished_writes`], which
    /// deletes the temporary files of every write of the process and refuses new ones until it
    /// reopens the registry, holds it exclusively.
    static WRITES: RwLock<()> = RwLock::new(());

    fn writing() -> RwLockReadGuard<'static, ()> {
        WRITES.read().unwrap_or_else(PoisonError::into_inner)
    }

    /// The registered temporary files inside `dir`.
    fn registered_in(dir: &Path) -> Vec<PathBuf> {
        registry()
            .in_flight
            .iter()
            .filter(|p| p.starts_with(dir))
            .cloned()
            .collect()
    }

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
        let _w = writing();
        let d = scratch("replace");
        let p = d.join("out.bin");
        write_atomic(&p, b"first").unwrap();
        write_atomic(&p, b"second").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"second");
        assert_eq!(names(&d), ["out.bin"]);
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn the_unsynced_write_replaces_the_file_and_a_failed_one_keeps_it() {
        let _w = writing();
        let d = scratch("unsynced");
        let p = d.join("a/out.bin");
        write_atomic_unsynced_with(&p, |f| f.write_all(b"first")).unwrap();
        write_atomic_unsynced_with(&p, |f| f.write_all(b"second")).unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"second");
        let failing = write_atomic_unsynced_with(&p, |f| {
            f.write_all(b"partial")?;
            Err(io::Error::other("the writer failed"))
        });
        assert!(failing.is_err());
        assert_eq!(fs::read(&p).unwrap(), b"second");
        assert_eq!(names(&d.join("a")), ["out.bin"]);
        assert!(registered_in(&d).is_empty());
        fs::remove_dir_all(&d).unwrap();
    }

    /// Bytes that tell positions apart (not a repeating pattern of a power-of-two period).
    fn pattern(len: usize) -> Vec<u8> {
        (0..len).map(|i| (i * 7 + i / 251) as u8).collect()
    }

    #[test]
    fn the_uncached_writer_gives_the_bytes_written_at_every_length_and_chunking() {
        let _w = writing();
        let d = scratch("uncached");
        let p = d.join("out.bin");
        let lens = [
            0,
            1,
            DIRECT_ALIGN - 1,
            DIRECT_ALIGN,
            DIRECT_ALIGN + 1,
            DIRECT_BLOCK - 1,
            DIRECT_BLOCK,
            DIRECT_BLOCK + 3,
            3 * DIRECT_BLOCK + DIRECT_ALIGN + 5,
        ];
        for len in lens {
            let data = pattern(len);
            for chunk in [1000, 4096, DIRECT_BLOCK + 17] {
                write_atomic_unsynced_with(&p, |w| {
                    for (i, piece) in data.chunks(chunk).enumerate() {
                        w.write_all(piece)?;
                        if i % 3 == 1 {
                            w.flush()?;
                        }
                    }
                    Ok(())
                })
                .unwrap();
                assert!(
                    fs::read(&p).unwrap() == data,
                    "length {len}, chunks of {chunk}"
                );
            }
        }
        assert_eq!(names(&d), ["out.bin"]);
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn the_uncached_writer_goes_on_through_the_page_cache_when_direct_io_is_refused() {
        let _w = writing();
        let d = scratch("uncached-refused");
        let p = d.join("out.bin");
        let data = pattern(2 * DIRECT_BLOCK + 9);
        for direct in [false, true] {
            let mut f = fs::File::create(&p).unwrap();
            let mut w = UncachedWriter::new(&mut f, direct);
            // One byte written past the writer moves the file's offset off the alignment: a
            // direct write is refused there (where direct I/O is on at all), and the writer
            // must go on buffered with every byte in place.
            let was_direct = w.is_direct();
            set_direct(w.file, false);
            w.file.write_all(&data[..1]).unwrap();
            if was_direct {
                assert!(set_direct(w.file, true));
            }
            w.written = 1;
            w.write_all(&data[1..]).unwrap();
            assert!(!w.is_direct());
            w.finish().unwrap();
            drop(f);
            assert!(fs::read(&p).unwrap() == data, "direct asked: {direct}");
        }
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn creates_missing_directories() {
        let _w = writing();
        let d = scratch("dirs");
        let p = d.join("a/b/out.txt");
        write_atomic(&p, b"x").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"x");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_failed_write_keeps_the_old_file_and_removes_its_temporary_file() {
        let _w = writing();
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
        let _w = writing();
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
    fn finished_and_failed_writes_leave_nothing_registered() {
        let _w = writing();
        let d = scratch("registry");
        write_atomic(&d.join("out.bin"), b"data").unwrap();
        // renaming over a non-empty directory fails after the temporary file was written
        fs::create_dir_all(d.join("dir/inner")).unwrap();
        assert!(write_atomic(&d.join("dir"), b"lost").is_err());
        assert_eq!(registered_in(&d), Vec::<PathBuf>::new());
        assert_eq!(names(&d), ["dir", "out.bin"]);
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn removing_unfinished_writes_deletes_the_temporary_file_of_a_write_in_flight() {
        let _exclusive = WRITES.write().unwrap_or_else(PoisonError::into_inner);
        let d = scratch("unfinished");
        let p = d.join("checkpoint.bin");
        write_atomic(&p, b"previous").unwrap();

        // A writer thread stops half-way through its write until told to go on.
        let (started_tx, started) = mpsc::channel();
        let (resume, resume_rx) = mpsc::channel::<()>();
        let target = p.clone();
        let writer = std::thread::spawn(move || {
            write_atomic_with(&target, |f| {
                f.write_all(b"first half")?;
                started_tx.send(()).unwrap();
                resume_rx.recv().unwrap();
                f.write_all(b"second half")
            })
        });
        started.recv().unwrap();
        let in_flight = registered_in(&d);
        assert_eq!(in_flight.len(), 1, "{in_flight:?}");
        let tmp_name = in_flight[0]
            .file_name()
            .unwrap()
            .to_string_lossy()
            .into_owned();
        assert!(tmp_name.starts_with(".checkpoint.bin.tmp-"), "{tmp_name}");
        assert_eq!(names(&d), [tmp_name.as_str(), "checkpoint.bin"]);

        remove_unfinished_writes();
        assert_eq!(names(&d), ["checkpoint.bin"]);
        assert_eq!(registered_in(&d), Vec::<PathBuf>::new());
        // a write starting afterwards (while the process exits) creates nothing
        let late = write_atomic(&d.join("late.bin"), b"x").unwrap_err();
        assert_eq!(late.kind(), io::ErrorKind::Interrupted);

        // the interrupted write fails and the target keeps its previous contents
        resume.send(()).unwrap();
        assert!(writer.join().unwrap().is_err());
        assert_eq!(fs::read(&p).unwrap(), b"previous");
        assert_eq!(names(&d), ["checkpoint.bin"]);

        // reopen the registry for the other tests of this process
        registry().closed = false;
        write_atomic(&p, b"next").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"next");
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
