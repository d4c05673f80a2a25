//! The one way a run's files are written: to a temporary name beside the target, synced, renamed over it, and the
//! directory synced, so after a crash (or a full disk) a reader finds the old file or the new one, never half of
//! one. It also owns the other half of that promise: directories created durably, a tree synced before it is
//! renamed into place, and the temporaries a killed process left behind recognised and swept.

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::Path;

/// What [`write_atomic`] appends to the hidden temporary beside its target: `.<name>.partial`.
const TEMPORARY_SUFFIX: &str = ".partial";

fn named(e: io::Error, p: &Path) -> io::Error {
    io::Error::new(e.kind(), format!("{}: {e}", p.display()))
}

/// Writes `bytes` to `path` atomically; the error names the path that failed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |tmp| File::create(tmp)?.write_all(bytes))
}

/// [`write_atomic`] of a file that `write` creates at the temporary path it is given: a writer that streams (a
/// checkpoint written tensor by tensor) never holds the whole file in memory.
pub fn write_atomic_with(path: &Path, write: impl FnOnce(&Path) -> io::Result<()>) -> io::Result<()> {
    let file_name = path.file_name().ok_or_else(|| io::Error::other(format!("{}: not a file path", path.display())))?;
    let tmp = path.with_file_name(format!(".{}{TEMPORARY_SUFFIX}", file_name.to_string_lossy()));
    write(&tmp).and_then(|()| File::open(&tmp)?.sync_all()).map_err(|e| {
        let _ = fs::remove_file(&tmp);
        named(e, &tmp)
    })?;
    fs::rename(&tmp, path).map_err(|e| named(e, path))?;
    sync_dir(path.parent().unwrap_or(Path::new(".")))
}

/// Whether `name` is one of [`write_atomic`]'s temporaries: what a process killed mid-write leaves, never a file
/// anyone should read.
pub fn is_temporary(name: &str) -> bool {
    name.starts_with('.') && name.ends_with(TEMPORARY_SUFFIX)
}

/// Removes every [`write_atomic`] temporary under `dir` (a crash's leftovers); the number removed.
pub fn remove_temporaries(dir: &Path) -> io::Result<usize> {
    let mut removed = 0;
    for entry in fs::read_dir(dir).map_err(|e| named(e, dir))? {
        let entry = entry.map_err(|e| named(e, dir))?;
        let path = entry.path();
        if entry.file_type().map_err(|e| named(e, &path))?.is_dir() {
            removed += remove_temporaries(&path)?;
        } else if is_temporary(&entry.file_name().to_string_lossy()) {
            fs::remove_file(&path).map_err(|e| named(e, &path))?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Creates `dir` and its missing parents, syncing the parent of each one created, so that the new entries outlive
/// a crash as the files written into them do.
pub fn create_dir_all(dir: &Path) -> io::Result<()> {
    if dir.as_os_str().is_empty() || dir.is_dir() {
        return Ok(());
    }
    let parent = dir.parent().unwrap_or(Path::new("."));
    create_dir_all(parent)?;
    match fs::create_dir(dir) {
        Ok(()) => sync_dir(parent),
        // Created meanwhile by another writer (two clients' uploads into one round's folder).
        Err(e) if e.kind() == io::ErrorKind::AlreadyExists && dir.is_dir() => Ok(()),
        Err(e) => Err(named(e, dir)),
    }
}

/// Syncs every file and directory under `dir`, and `dir` itself: what was written there without [`write_atomic`]
/// (a video encoder's output, a directory's entries) is on disk before the tree is renamed into place.
pub fn sync_tree(dir: &Path) -> io::Result<()> {
    for entry in fs::read_dir(dir).map_err(|e| named(e, dir))? {
        let path = entry.map_err(|e| named(e, dir))?.path();
        if path.is_dir() {
            sync_tree(&path)?;
        } else {
            File::open(&path).and_then(|f| f.sync_all()).map_err(|e| named(e, &path))?;
        }
    }
    sync_dir(dir)
}

/// Makes a rename into `dir` durable (a no-op where directories cannot be opened, as on Windows).
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    let dir = if dir.as_os_str().is_empty() { Path::new(".") } else { dir };
    match File::open(dir) {
        Ok(handle) => handle.sync_all().or_else(|e| if cfg!(unix) { Err(e) } else { Ok(()) }),
        Err(_) if !cfg!(unix) => Ok(()),
        Err(e) => Err(named(e, dir)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_replace_whole_files_and_leave_no_temporary() {
        let dir = std::env::temp_dir().join(format!("fedvla-fs-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.json");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"two");
        assert_eq!(fs::read_dir(&dir).unwrap().count(), 1, "no temporary left");
        let err = write_atomic(&dir.join("missing/b.json"), b"x").unwrap_err().to_string();
        assert!(err.contains("missing"), "{err}");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_crash_leftover_is_recognised_and_swept_and_trees_are_created_and_synced() {
        let dir = std::env::temp_dir().join(format!("fedvla-fs-sweep-{}", std::process::id()));
        let deep = dir.join("a/b/c");
        create_dir_all(&deep).unwrap();
        create_dir_all(&deep).unwrap();
        write_atomic(&deep.join("kept.json"), b"{}").unwrap();
        // What a process killed between create and rename leaves.
        fs::write(deep.join(".kept.json.partial"), b"{").unwrap();
        fs::write(dir.join(".other.partial"), b"").unwrap();
        assert!(is_temporary(".kept.json.partial") && !is_temporary("kept.json") && !is_temporary("x.partial"));
        sync_tree(&dir).unwrap();
        assert_eq!(remove_temporaries(&dir).unwrap(), 2);
        assert_eq!(fs::read_dir(&deep).unwrap().count(), 1);
        assert_eq!(fs::read(deep.join("kept.json")).unwrap(), b"{}");
        fs::remove_dir_all(&dir).unwrap();
    }
}
