//! Where a dataset's files come from: [`DatasetFiles`], paths relative to the dataset's root mapped to bytes. The
//! reader reads through it, so one reader serves a directory on disk ([`DirFiles`], feature `io`) and files a
//! browser page picked and read into memory ([`MemoryFiles`]); nothing else in the crate knows which.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{DataError, Result};

/// A dataset's files by path relative to its root (`meta/info.json`, `data/chunk-000/file-000.parquet`, ...).
pub trait DatasetFiles: Send + Sync {
    /// Where the files lie, for messages: the directory natively, the picked folder's name in a browser.
    fn root(&self) -> &Path;

    /// Whether `path` is one of the dataset's files.
    fn exists(&self, path: &Path) -> bool;

    /// The whole file.
    fn read(&self, path: &Path) -> Result<Vec<u8>>;

    /// `len` bytes from `offset` (a video's box headers and samples), an error when they run past the end.
    fn read_range(&self, path: &Path, offset: u64, len: usize) -> Result<Vec<u8>>;

    /// The file's size in bytes.
    fn size(&self, path: &Path) -> Result<u64>;

    /// The files under directory `dir` (recursively) whose names end in `.ext`, sorted.
    fn list(&self, dir: &Path, ext: &str) -> Result<Vec<PathBuf>>;

    /// `path` as messages name it.
    fn display_path(&self, path: &Path) -> PathBuf {
        self.root().join(path)
    }
}

/// A dataset directory on disk.
#[cfg(feature = "io")]
pub struct DirFiles {
    root: PathBuf,
}

#[cfg(feature = "io")]
impl DirFiles {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }
}

#[cfg(feature = "io")]
impl DatasetFiles for DirFiles {
    fn root(&self) -> &Path {
        &self.root
    }

    fn exists(&self, path: &Path) -> bool {
        self.root.join(path).is_file()
    }

    fn read(&self, path: &Path) -> Result<Vec<u8>> {
        let full = self.root.join(path);
        std::fs::read(&full).map_err(|e| DataError::io(&full, e))
    }

    fn read_range(&self, path: &Path, offset: u64, len: usize) -> Result<Vec<u8>> {
        use std::io::{Read, Seek, SeekFrom};
        let full = self.root.join(path);
        let mut file = std::fs::File::open(&full).map_err(|e| DataError::io(&full, e))?;
        file.seek(SeekFrom::Start(offset)).map_err(|e| DataError::io(&full, e))?;
        let mut buf = vec![0; len];
        file.read_exact(&mut buf).map_err(|_| past_the_end(&full, offset, len))?;
        Ok(buf)
    }

    fn size(&self, path: &Path) -> Result<u64> {
        let full = self.root.join(path);
        Ok(std::fs::metadata(&full).map_err(|e| DataError::io(&full, e))?.len())
    }

    fn list(&self, dir: &Path, ext: &str) -> Result<Vec<PathBuf>> {
        let mut out = Vec::new();
        let mut stack = vec![self.root.join(dir)];
        while let Some(d) = stack.pop() {
            let entries = match std::fs::read_dir(&d) {
                Ok(e) => e,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(DataError::io(&d, e)),
            };
            for entry in entries {
                let path = entry.map_err(|e| DataError::io(&d, e))?.path();
                if path.is_dir() {
                    stack.push(path);
                } else if path.extension().is_some_and(|e| e == ext)
                    && let Ok(relative) = path.strip_prefix(&self.root)
                {
                    out.push(relative.to_path_buf());
                }
            }
        }
        out.sort();
        Ok(out)
    }
}

/// A dataset's files held in memory: every path of a picked folder is listed (so the reader finds what exists),
/// but only the files put in with [`MemoryFiles::insert`] have contents. Reading one that was not put in is an
/// error naming it, so a reader that wants more than its caller loaded says what.
pub struct MemoryFiles {
    root: PathBuf,
    /// Every listed file: its size, and its bytes once loaded.
    files: BTreeMap<PathBuf, (u64, Option<Vec<u8>>)>,
}

impl MemoryFiles {
    /// The folder `root` (its name, for messages) holding `listing`: (path relative to the root, size in bytes).
    pub fn new(root: impl Into<PathBuf>, listing: impl IntoIterator<Item = (PathBuf, u64)>) -> Self {
        Self { root: root.into(), files: listing.into_iter().map(|(path, size)| (path, (size, None))).collect() }
    }

    /// Puts in the contents of `path` (which the listing must name, with this size).
    pub fn insert(&mut self, path: &Path, bytes: Vec<u8>) -> Result<()> {
        let full = self.display_path(path);
        let (size, contents) = self.files.get_mut(path).ok_or(DataError::MissingFile { path: full.clone() })?;
        if *size != bytes.len() as u64 {
            return Err(DataError::InvalidInput(format!(
                "{}: listed with {size} bytes, read {} bytes",
                full.display(),
                bytes.len()
            )));
        }
        *contents = Some(bytes);
        Ok(())
    }

    /// Whether the contents of `path` are in.
    pub fn is_loaded(&self, path: &Path) -> bool {
        self.files.get(path).is_some_and(|(_, c)| c.is_some())
    }

    /// The paths whose contents are in, in order: what was read from the folder.
    pub fn loaded(&self) -> Vec<&Path> {
        self.files.iter().filter(|(_, (_, c))| c.is_some()).map(|(p, _)| p.as_path()).collect()
    }

    fn contents(&self, path: &Path) -> Result<&[u8]> {
        match self.files.get(path) {
            None => Err(DataError::MissingFile { path: self.display_path(path) }),
            Some((_, None)) => Err(DataError::InvalidInput(format!(
                "{} was not read from the folder (the reader asked for a file its caller did not load)",
                self.display_path(path).display()
            ))),
            Some((_, Some(bytes))) => Ok(bytes),
        }
    }
}

impl DatasetFiles for MemoryFiles {
    fn root(&self) -> &Path {
        &self.root
    }

    fn exists(&self, path: &Path) -> bool {
        self.files.contains_key(path)
    }

    fn read(&self, path: &Path) -> Result<Vec<u8>> {
        self.contents(path).map(<[u8]>::to_vec)
    }

    fn read_range(&self, path: &Path, offset: u64, len: usize) -> Result<Vec<u8>> {
        let bytes = self.contents(path)?;
        let start = usize::try_from(offset).unwrap_or(usize::MAX);
        start
            .checked_add(len)
            .and_then(|end| bytes.get(start..end))
            .map(<[u8]>::to_vec)
            .ok_or_else(|| past_the_end(&self.display_path(path), offset, len))
    }

    fn size(&self, path: &Path) -> Result<u64> {
        self.files.get(path).map(|(size, _)| *size).ok_or(DataError::MissingFile { path: self.display_path(path) })
    }

    fn list(&self, dir: &Path, ext: &str) -> Result<Vec<PathBuf>> {
        Ok(self
            .files
            .keys()
            .filter(|p| p.starts_with(dir) && p.extension().is_some_and(|e| e == ext))
            .cloned()
            .collect())
    }
}

fn past_the_end(path: &Path, offset: u64, len: usize) -> DataError {
    DataError::InvalidInput(format!("{}: {len} bytes at {offset} run past the end of the file", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn files() -> MemoryFiles {
        let mut files = MemoryFiles::new(
            "picked",
            [
                (PathBuf::from("meta/info.json"), 2),
                (PathBuf::from("meta/episodes/chunk-000/file-000.parquet"), 3),
                (PathBuf::from("videos/top/chunk-000/file-000.mp4"), 4),
            ],
        );
        files.insert(Path::new("meta/info.json"), b"{}".to_vec()).unwrap();
        files.insert(Path::new("videos/top/chunk-000/file-000.mp4"), vec![1, 2, 3, 4]).unwrap();
        files
    }

    #[test]
    fn lists_every_file_and_reads_only_the_loaded_ones() {
        let files = files();
        assert_eq!(files.list(Path::new("meta/episodes"), "parquet").unwrap().len(), 1);
        assert!(files.exists(Path::new("meta/episodes/chunk-000/file-000.parquet")));
        assert_eq!(files.read(Path::new("meta/info.json")).unwrap(), b"{}");
        assert_eq!(files.read_range(Path::new("videos/top/chunk-000/file-000.mp4"), 1, 2).unwrap(), [2, 3]);
        let unloaded = files.read(Path::new("meta/episodes/chunk-000/file-000.parquet")).unwrap_err().to_string();
        assert!(unloaded.contains("picked/meta/episodes/chunk-000/file-000.parquet was not read"), "{unloaded}");
        let missing = files.read(Path::new("meta/stats.json")).unwrap_err().to_string();
        assert_eq!(missing, "picked/meta/stats.json: file not found");
        let past = files.read_range(Path::new("videos/top/chunk-000/file-000.mp4"), 3, 2).unwrap_err().to_string();
        assert!(past.contains("run past the end"), "{past}");
        assert_eq!(files.loaded(), [Path::new("meta/info.json"), Path::new("videos/top/chunk-000/file-000.mp4")]);
    }

    #[test]
    fn refuses_contents_of_another_size_than_listed() {
        let mut files = files();
        let err = files.insert(Path::new("meta/info.json"), b"{ }".to_vec()).unwrap_err().to_string();
        assert!(err.contains("listed with 2 bytes, read 3 bytes"), "{err}");
    }
}
