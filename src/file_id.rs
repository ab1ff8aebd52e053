//! Whether two paths name one file: the same path spelled differently, a symbolic link, or a
//! hard link (the same device and inode). An output that is its own input would be truncated
//! before it is read; two outputs on one file would each report every event while the file
//! held a mix of both.

use std::path::{Path, PathBuf};

/// What a path names, for comparing files: its device and inode where the file exists, and
/// the path resolved (the file itself with links resolved, else its resolved folder and its
/// name, else the path made absolute).
#[derive(Debug, Clone)]
pub struct FileId {
    inode: Option<(u64, u64)>,
    path: PathBuf,
}

impl FileId {
    /// The identity of `path` now.
    pub fn of(path: &Path) -> Self {
        FileId {
            inode: inode(path),
            path: resolved(path),
        }
    }

    /// Whether `self` and `other` are one file: one inode where both exist, else one resolved
    /// path.
    pub fn same(&self, other: &FileId) -> bool {
        match (self.inode, other.inode) {
            (Some(a), Some(b)) => a == b,
            _ => self.path == other.path,
        }
    }

    /// The path resolved (for messages).
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Whether `a` and `b` name one file (see [`FileId`]).
pub fn same_file(a: &Path, b: &Path) -> bool {
    FileId::of(a).same(&FileId::of(b))
}

#[cfg(unix)]
fn inode(path: &Path) -> Option<(u64, u64)> {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
}

#[cfg(not(unix))]
fn inode(_: &Path) -> Option<(u64, u64)> {
    None
}

fn resolved(path: &Path) -> PathBuf {
    if let Ok(p) = path.canonicalize() {
        return p;
    }
    let folder = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    match (folder.canonicalize(), path.file_name()) {
        (Ok(d), Some(name)) => d.join(name),
        _ => std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Spellings, symbolic and hard links of one file are one file; another file is not.
    #[test]
    fn links_and_spellings_of_one_file_are_one_file() {
        let dir = std::env::temp_dir().join(format!("v2ce-file-id-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("d")).unwrap();
        let a = dir.join("a.csv");
        std::fs::write(&a, "x").unwrap();
        std::fs::write(dir.join("b.csv"), "x").unwrap();
        let hard = dir.join("hard.csv");
        let _ = std::fs::remove_file(&hard);
        std::fs::hard_link(&a, &hard).unwrap();
        let soft = dir.join("soft.csv");
        let _ = std::fs::remove_file(&soft);
        #[cfg(unix)]
        std::os::unix::fs::symlink(&a, &soft).unwrap();
        assert!(same_file(&a, &dir.join("d/../a.csv")));
        assert!(same_file(&a, &hard));
        #[cfg(unix)]
        assert!(same_file(&a, &soft));
        assert!(!same_file(&a, &dir.join("b.csv")));
        // Files not yet written compare by path.
        assert!(same_file(&dir.join("new.csv"), &dir.join("d/../new.csv")));
        assert!(!same_file(&dir.join("new.csv"), &dir.join("new2.csv")));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
