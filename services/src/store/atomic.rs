//! Crash-safe file operations: a file is either its old or its new content after a crash,
//! never a mix, and a returned `Ok` means the change survives power loss (as far as the file
//! system honours `fsync`).

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Writes `bytes` to `path` atomically and durably: write `path.tmp`, `sync_all` it, rename it
/// over `path`, then fsync the folder so the rename itself is on disk.
///
/// # Errors
/// Any I/O error; `path` then still holds its old content (a stale `.tmp` may remain and is
/// overwritten by the next write).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = tmp_path(path);
    {
        let mut f = File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    fs::rename(&tmp, path)?;
    sync_parent(path)
}

/// Applies several changes to files of one folder durably with a single folder fsync (group
/// commit): every new content is written to `x.tmp` and `sync_all`ed, then renamed over `x`
/// (`None` removes `x`), then the folder is fsynced once. Each file is still old-or-new after
/// a crash; `Ok` means all of them are on disk.
///
/// # Errors
/// Any I/O error (files renamed before it hold their new content, the rest their old).
pub fn write_many_atomic(dir: &Path, files: &[(PathBuf, Option<Vec<u8>>)]) -> io::Result<()> {
    for (path, bytes) in files {
        if let Some(bytes) = bytes {
            let mut f = File::create(tmp_path(path))?;
            f.write_all(bytes)?;
            f.sync_all()?;
        }
    }
    for (path, bytes) in files {
        match bytes {
            Some(_) => fs::rename(tmp_path(path), path)?,
            None => match fs::remove_file(path) {
                Ok(()) => {}
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => return Err(e),
            },
        }
    }
    sync_dir(dir)
}

/// Removes a file (if present) and fsyncs its folder.
///
/// # Errors
/// Any I/O error but "not found".
pub fn remove_durable(path: &Path) -> io::Result<()> {
    match fs::remove_file(path) {
        Ok(()) => sync_parent(path),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
    }
}

/// `path` with `.tmp` appended (`a.json` → `a.json.tmp`).
#[must_use]
pub fn tmp_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".tmp");
    PathBuf::from(s)
}

/// Fsyncs the folder holding `path` (a no-op where folders cannot be opened, i.e. not Unix).
///
/// # Errors
/// The folder cannot be opened or synced.
pub fn sync_parent(path: &Path) -> io::Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => sync_dir(dir),
        _ => sync_dir(Path::new(".")),
    }
}

/// Fsyncs a folder so that entries created, renamed or removed in it are durable.
///
/// # Errors
/// The folder cannot be opened or synced.
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    #[cfg(unix)]
    {
        File::open(dir)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        Ok(())
    }
}

/// Moves a bad file or folder aside to `<path>.corrupt` (or `<path>.corrupt.N` when that is
/// taken) so nothing is lost and the next start does not trip over it. Returns where it went.
///
/// # Errors
/// The rename failed.
pub fn move_aside(path: &Path) -> io::Result<PathBuf> {
    let mut base = path.as_os_str().to_owned();
    base.push(".corrupt");
    let mut target = PathBuf::from(&base);
    let mut n = 1;
    while target.exists() {
        let mut s = base.clone();
        s.push(format!(".{n}"));
        target = PathBuf::from(s);
        n += 1;
    }
    fs::rename(path, &target)?;
    sync_parent(path)?;
    Ok(target)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_whole_content_and_leaves_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.json");
        write_atomic(&path, b"first version, rather long").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"second");
        assert!(!tmp_path(&path).exists());
        let names: Vec<_> = fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }

    #[test]
    fn a_stale_temp_from_a_crash_does_not_matter() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.json");
        write_atomic(&path, b"old").unwrap();
        // A crash after writing the temp file but before the rename.
        fs::write(tmp_path(&path), b"half-writ").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"old");
        write_atomic(&path, b"new").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"new");
        assert!(!tmp_path(&path).exists());
    }

    #[test]
    fn a_failed_write_keeps_the_old_content() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.json");
        write_atomic(&path, b"old").unwrap();
        // The temp path is a folder: creating the temp file fails.
        fs::create_dir(tmp_path(&path)).unwrap();
        assert!(write_atomic(&path, b"new").is_err());
        assert_eq!(fs::read(&path).unwrap(), b"old");
    }

    #[test]
    fn remove_and_move_aside() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.json");
        remove_durable(&path).unwrap();
        fs::write(&path, b"x").unwrap();
        let aside = move_aside(&path).unwrap();
        assert_eq!(aside, dir.path().join("s.json.corrupt"));
        fs::write(&path, b"y").unwrap();
        assert_eq!(
            move_aside(&path).unwrap(),
            dir.path().join("s.json.corrupt.1")
        );
        fs::write(&path, b"z").unwrap();
        remove_durable(&path).unwrap();
        assert!(!path.exists());
    }
}
