//! The outputs' paths, relative to the output folder: normalised lexically (so `x`, `./x`,
//! `a/../x` and `a//x` are one output), kept out of the ledgers' folder, and checked on disk
//! (through links) for two outputs that are one file.

use std::collections::HashMap;
use std::os::unix::fs::MetadataExt;
use std::path::{Component, Path, PathBuf};

use super::ledger::LEDGER_DIR;
use super::manifest::Item;
use crate::error::{Error, Result};

/// `p` normalised without looking at the disk: `.` and empty parts dropped, `a/..` taken
/// away; `None` when `p` is absolute, empty once normalised, or leaves its folder (`../x`,
/// `a/../../x`).
pub(super) fn normalize(p: &Path) -> Option<PathBuf> {
    let mut parts: Vec<&std::ffi::OsStr> = Vec::new();
    for c in p.components() {
        match c {
            Component::Normal(s) => parts.push(s),
            Component::CurDir => {}
            Component::ParentDir => {
                parts.pop()?;
            }
            Component::RootDir | Component::Prefix(_) => return None,
        }
    }
    (!parts.is_empty()).then(|| parts.iter().collect())
}

/// A ledger's key for an output: the output normalised (a record written before outputs were
/// normalised, `./x.aedat4`, is the record of `x.aedat4`), else as written.
pub(super) fn output_key(output: &str) -> String {
    normalize(Path::new(output))
        .and_then(|p| p.to_str().map(str::to_owned))
        .unwrap_or_else(|| output.to_owned())
}

/// Whether the normalised output `p` lies in the ledgers' folder ([`LEDGER_DIR`], in any
/// case, for case-insensitive file systems), which the batch keeps for itself.
pub(super) fn in_ledger_dir(p: &Path) -> bool {
    p.components().next().is_some_and(|c| {
        c.as_os_str()
            .to_str()
            .is_some_and(|s| s.eq_ignore_ascii_case(LEDGER_DIR))
    })
}

/// Checks the outputs of `items` in the output folder `out` as the disk resolves them: no
/// output may lead (through a link) into the ledgers' folder, and no two may be one file,
/// whether one path (their existing folders resolved through links) or, where both exist,
/// one device and inode (a hard or symbolic link).
pub(super) fn check_on_disk(out: &Path, items: &[Item]) -> Result<()> {
    let canonical = |p: &Path| std::fs::canonicalize(p).map_err(|e| Error::io(p, e));
    let ledger = out.join(LEDGER_DIR);
    let ledger_dir = match std::fs::canonicalize(&ledger) {
        Ok(p) => p,
        Err(_) => canonical(out)?.join(LEDGER_DIR),
    };
    let ledger_id = std::fs::metadata(&ledger).ok().map(|m| (m.dev(), m.ino()));
    let mut folders: HashMap<PathBuf, PathBuf> = HashMap::new();
    let mut by_path: HashMap<PathBuf, &str> = HashMap::new();
    let mut by_inode: HashMap<(u64, u64), &str> = HashMap::new();
    for item in items {
        let path = out.join(&item.output);
        let (Some(parent), Some(name)) = (path.parent(), path.file_name()) else {
            continue;
        };
        let folder = match folders.get(parent) {
            Some(f) => f.clone(),
            None => {
                let f = resolve(parent);
                folders.insert(parent.to_path_buf(), f.clone());
                f
            }
        };
        let resolved = folder.join(name);
        let id = std::fs::metadata(&path).ok().map(|m| (m.dev(), m.ino()));
        if resolved.starts_with(&ledger_dir) || (id.is_some() && id == ledger_id) {
            return Err(Error::invalid(
                "manifest",
                format!(
                    "{}: output {} leads into {}, the folder of the batch's ledgers",
                    item.name,
                    item.output.display(),
                    ledger.display()
                ),
            ));
        }
        let same = |other: &str| {
            Error::invalid(
                "manifest",
                format!(
                    "{other} and {} would both write {}; give one another \"output\"",
                    item.name,
                    resolved.display()
                ),
            )
        };
        if let Some(other) = by_path.insert(resolved.clone(), &item.name) {
            return Err(same(other));
        }
        if let Some(id) = id {
            if let Some(other) = by_inode.insert(id, &item.name) {
                return Err(same(other));
            }
        }
    }
    Ok(())
}

/// `path` with its longest existing beginning resolved through links (the rest as written).
fn resolve(path: &Path) -> PathBuf {
    let mut rest = Vec::new();
    let mut p = path;
    loop {
        if let Ok(mut found) = std::fs::canonicalize(p) {
            found.extend(rest.iter().rev());
            return found;
        }
        match (p.parent(), p.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name);
                p = if parent.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    parent
                };
            }
            _ => return path.to_path_buf(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::manifest::Settings;

    #[test]
    fn outputs_are_normalised_lexically() {
        for (p, want) in [
            ("x.aedat4", Some("x.aedat4")),
            ("./x.aedat4", Some("x.aedat4")),
            ("a/../x.aedat4", Some("x.aedat4")),
            ("a//b/./x.aedat4", Some("a/b/x.aedat4")),
            ("a/b/", Some("a/b")),
            ("../x", None),
            ("a/../../x", None),
            ("/x", None),
            (".", None),
            ("a/..", None),
            ("", None),
        ] {
            assert_eq!(normalize(Path::new(p)), want.map(PathBuf::from), "{p}");
        }
        assert_eq!(output_key("./a//x.csv"), "a/x.csv");
        assert_eq!(output_key("../x.csv"), "../x.csv");
        assert!(in_ledger_dir(Path::new(".v2ce-batch/shard-0-of-1.jsonl")));
        assert!(in_ledger_dir(Path::new(".V2CE-Batch/x")));
        assert!(!in_ledger_dir(Path::new(".v2ce-batch.aedat4")));
        assert!(!in_ledger_dir(Path::new("a/.v2ce-batch/x")));
    }

    fn item(name: &str, output: &str) -> Item {
        Item {
            name: name.into(),
            input: name.into(),
            output: output.into(),
            settings: Settings::default(),
            bytes: 0,
        }
    }

    #[test]
    fn outputs_that_are_one_file_on_disk_are_refused() {
        let out = std::env::temp_dir().join(format!("v2ce-batch-paths-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        std::fs::create_dir_all(out.join("a")).unwrap();
        std::fs::create_dir_all(out.join(LEDGER_DIR)).unwrap();
        std::os::unix::fs::symlink("a", out.join("b")).unwrap();
        std::os::unix::fs::symlink(LEDGER_DIR, out.join("l")).unwrap();
        let check = |items: &[Item]| check_on_disk(&out, items).map_err(|e| e.to_string());
        assert!(check(&[item("1", "a/x"), item("2", "a/y"), item("3", "new/x")]).is_ok());
        // Through a linked folder, before either exists.
        let err = check(&[item("1", "a/x"), item("2", "b/x")]).unwrap_err();
        assert!(err.contains("1 and 2 would both write"), "{err}");
        // Into the ledgers' folder through a link, or the link itself.
        for o in ["l/shard-0-of-1.jsonl", "l/new/x", "l"] {
            let err = check(&[item("1", o)]).unwrap_err();
            assert!(err.contains("folder of the batch's ledgers"), "{o}: {err}");
        }
        // Two existing outputs that are one file (a hard link).
        std::fs::write(out.join("a/x"), b"x").unwrap();
        std::fs::hard_link(out.join("a/x"), out.join("a/z")).unwrap();
        let err = check(&[item("1", "a/x"), item("2", "a/z")]).unwrap_err();
        assert!(err.contains("1 and 2 would both write"), "{err}");
        std::fs::remove_dir_all(&out).unwrap();
    }
}
