//! [`BlobStore`] on a directory: each blob is written to a temporary file, fsynced and renamed
//! into place, so a crash leaves either the whole file or nothing.

use super::{BlobStore, BlobWriter, PinHook};
use crate::error::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// [`BlobStore`] on a directory: `<root>/<first 2 hex>/<hash>`.
pub struct FsBlobStore {
    root: PathBuf,
}

fn valid_hash(hash: &str) -> bool {
    hash.len() == 64 && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

impl FsBlobStore {
    /// Opens (or creates) a blob directory; removes temporary files a crash left behind.
    ///
    /// # Errors
    /// When the directory cannot be created or read.
    pub fn open(root: &Path) -> Result<Self> {
        std::fs::create_dir_all(root.join("tmp"))?;
        for entry in std::fs::read_dir(root.join("tmp"))? {
            let _ = std::fs::remove_file(entry?.path());
        }
        Ok(FsBlobStore { root: root.to_path_buf() })
    }

    fn path(&self, hash: &str) -> Result<PathBuf> {
        if !valid_hash(hash) {
            return Err(Error::Internal(format!("malformed blob hash `{hash}`")));
        }
        Ok(self.root.join(&hash[..2]).join(hash))
    }
}

/// [`BlobWriter`] of [`FsBlobStore`]: a temporary file in `tmp/`, hashed as it is written,
/// fsynced and renamed to its hash on commit (the same durability as [`BlobStore::put`]).
struct FsBlobWriter {
    tmp: tempfile::NamedTempFile,
    hasher: blake3::Hasher,
    store: FsBlobStore,
}

impl std::io::Write for FsBlobWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.tmp.write(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.tmp.flush()
    }
}

impl BlobWriter for FsBlobWriter {
    fn commit(self: Box<Self>, pin: PinHook<'_>) -> Result<String> {
        let FsBlobWriter { mut tmp, hasher, store } = *self;
        tmp.flush()?;
        let hash = hasher.finalize().to_hex().to_string();
        let dest = store.path(&hash)?;
        pin(&hash)?;
        if dest.exists() {
            // Already stored (content-addressed); the temporary file is removed on drop.
            return Ok(hash);
        }
        let dir = dest.parent().map(Path::to_path_buf).unwrap_or_else(|| store.root.clone());
        std::fs::create_dir_all(&dir)?;
        tmp.as_file().sync_all()?;
        tmp.persist(&dest).map_err(|e| Error::Io(e.error))?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(hash)
    }
}

impl BlobStore for FsBlobStore {
    fn check_writable(&self) -> Result<()> {
        // 64 KiB, so a disk with a few blocks left (which a bake's blob would not fit) is full
        // here too; the file is unlinked when dropped, never synced.
        let mut probe = tempfile::NamedTempFile::new_in(self.root.join("tmp"))?;
        probe.write_all(&[0u8; 64 << 10])?;
        probe.flush()?;
        Ok(())
    }
    fn writer(&self) -> Result<Box<dyn BlobWriter>> {
        Ok(Box::new(FsBlobWriter {
            tmp: tempfile::NamedTempFile::new_in(self.root.join("tmp"))?,
            hasher: blake3::Hasher::new(),
            store: FsBlobStore { root: self.root.clone() },
        }))
    }

    fn put(&self, bytes: &[u8], pin: PinHook<'_>) -> Result<String> {
        let hash = blake3::hash(bytes).to_hex().to_string();
        let dest = self.path(&hash)?;
        pin(&hash)?;
        if dest.exists() {
            return Ok(hash);
        }
        let dir = dest.parent().map(Path::to_path_buf).unwrap_or_else(|| self.root.clone());
        std::fs::create_dir_all(&dir)?;
        let mut tmp = tempfile::NamedTempFile::new_in(self.root.join("tmp"))?;
        tmp.write_all(bytes)?;
        tmp.as_file().sync_all()?;
        tmp.persist(&dest).map_err(|e| Error::Io(e.error))?;
        // Make the rename itself durable.
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(hash)
    }

    fn get(&self, hash: &str) -> Result<Option<Vec<u8>>> {
        match std::fs::read(self.path(hash)?) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn contains(&self, hash: &str) -> Result<bool> {
        Ok(self.path(hash)?.exists())
    }

    fn open(&self, hash: &str) -> Result<Option<(u64, Box<dyn std::io::Read + Send>)>> {
        match std::fs::File::open(self.path(hash)?) {
            Ok(f) => {
                let len = f.metadata()?.len();
                Ok(Some((len, Box::new(f))))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn open_range(
        &self,
        hash: &str,
        start: u64,
        end: u64,
    ) -> Result<Option<Box<dyn std::io::Read + Send>>> {
        use std::io::{Read, Seek};
        match std::fs::File::open(self.path(hash)?) {
            Ok(mut f) => {
                f.seek(std::io::SeekFrom::Start(start))?;
                Ok(Some(Box::new(f.take(end.saturating_sub(start)))))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn delete(&self, hash: &str) -> Result<()> {
        match std::fs::remove_file(self.path(hash)?) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    fn list(&self) -> Result<Vec<(String, u64)>> {
        let mut out = Vec::new();
        let now = SystemTime::now();
        for dir in std::fs::read_dir(&self.root)? {
            let dir = dir?;
            let name = dir.file_name();
            if name.len() != 2 || !dir.file_type()?.is_dir() {
                continue;
            }
            for f in std::fs::read_dir(dir.path())? {
                let f = f?;
                let hash = f.file_name().to_string_lossy().into_owned();
                if !valid_hash(&hash) {
                    continue;
                }
                let age = f
                    .metadata()
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|m| now.duration_since(m).ok())
                    .map(|d| d.as_secs())
                    .unwrap_or(0);
                out.push((hash, age));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blobs_are_content_addressed_and_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let b = FsBlobStore::open(dir.path()).unwrap();
        let h = b.put(b"hello", &|_| Ok(())).unwrap();
        assert_eq!(h, blake3::hash(b"hello").to_hex().to_string());
        assert_eq!(b.put(b"hello", &|_| Ok(())).unwrap(), h);
        assert_eq!(b.get(&h).unwrap().unwrap(), b"hello");
        assert_eq!(b.list().unwrap().len(), 1);
        assert!(std::fs::read_dir(dir.path().join("tmp")).unwrap().next().is_none());
        b.delete(&h).unwrap();
        assert!(!b.contains(&h).unwrap());
        assert!(b.get(&h).unwrap().is_none());
        assert!(b.get("../../etc/passwd").is_err());
    }
}
