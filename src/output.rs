//! One way to open an output file, for every command that writes one: [`check`] before any
//! work (the path is none of the command's inputs, through links; not a directory, a device
//! or a FIFO; an existing file only with `--force`), then the file written under a partial
//! name and renamed when complete ([`crate::format::PartialOutput`], or [`write_whole`] for a
//! file made in one piece), so an output never destroys an input and a file under the name
//! asked for is always whole.

use std::path::Path;

use crate::error::{Error, Result};
use crate::file_id::FileId;

/// Checks `path` as an output of a command that reads `inputs` (paths that do not name files,
/// such as a camera or `fixture`, compare as paths and never match a file): refuses one of the
/// inputs (the same file through any spelling or link), an existing directory, device, FIFO or
/// socket (a rename would replace the node), and an existing file unless `force`.
pub fn check(path: &Path, inputs: &[&Path], force: bool) -> Result<()> {
    let id = FileId::of(path);
    if let Some(input) = inputs.iter().find(|i| FileId::of(i).same(&id)) {
        return Err(Error::invalid(
            "output",
            format!(
                "{} is an input of this command ({}): it would be overwritten; choose another \
                 output path",
                path.display(),
                input.display()
            ),
        ));
    }
    // `symlink_metadata`: a link is replaced by the rename, not followed (what it points to
    // is compared above).
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    let kind = meta.file_type();
    let what = if kind.is_dir() {
        Some("a directory")
    } else if kind.is_file() || kind.is_symlink() {
        None
    } else {
        Some("a device, FIFO or socket")
    };
    if let Some(what) = what {
        return Err(Error::invalid(
            "output",
            format!(
                "{} is {what}, not a file: outputs are written as files (under a partial name, \
                 then renamed), which would replace it",
                path.display()
            ),
        ));
    }
    if !force {
        return Err(Error::invalid(
            "output",
            format!("{} exists; add --force to overwrite it", path.display()),
        ));
    }
    Ok(())
}

/// Checks a folder output `dir` into which a command writes `names` (files or folders): it
/// must be a folder where it exists (not a file, device or FIFO), which it writes into only
/// with `force`, and none of `names` in it may be or hold one of the command's `inputs`
/// (through links and spellings).
pub fn check_folder(dir: &Path, names: &[&str], inputs: &[&Path], force: bool) -> Result<()> {
    let Ok(meta) = std::fs::metadata(dir) else {
        return Ok(());
    };
    if !meta.is_dir() {
        return Err(Error::invalid(
            "output",
            format!(
                "{} exists and is not a folder: this command writes a folder",
                dir.display()
            ),
        ));
    }
    if !force {
        return Err(Error::invalid(
            "output",
            format!("{} exists (--force writes into it)", dir.display()),
        ));
    }
    for name in names {
        let Ok(written) = std::fs::canonicalize(dir.join(name)) else {
            continue;
        };
        let held = inputs.iter().find(|input| {
            std::fs::canonicalize(input).is_ok_and(|input| input.starts_with(&written))
        });
        if let Some(input) = held {
            return Err(Error::invalid(
                "output",
                format!(
                    "{} would be written over an input of this command ({}); choose another \
                     folder",
                    written.display(),
                    input.display()
                ),
            ));
        }
    }
    Ok(())
}

/// Writes `path` whole through `write`, which is handed the partial name to write to (a
/// library that opens the file itself, such as a plot's): renamed when `write` succeeds; on
/// failure the partial file is removed and the path is left as it was.
pub fn write_via(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let out = crate::format::PartialOutput::new(path);
    let partial = out.writing();
    if let Err(e) = write(partial) {
        let _ = std::fs::remove_file(partial);
        return Err(e);
    }
    out.commit()
}

/// Writes `bytes` to `path` whole (see [`write_via`]), flushed to the disk before the rename.
pub fn write_whole(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via(path, |partial| {
        (|| -> std::io::Result<()> {
            use std::io::Write;
            let mut file = std::fs::File::create(partial)?;
            file.write_all(bytes)?;
            file.sync_all()
        })()
        .map_err(|e| Error::io(partial, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An input (through a link or another spelling), a directory and a device are refused
    /// even with `force`; an existing file needs `force`; a new path is fine; `write_whole`
    /// leaves no partial file.
    #[test]
    fn outputs_never_replace_inputs_or_nodes() {
        let dir = std::env::temp_dir().join(format!("v2ce-output-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let input = dir.join("in.aedat4");
        std::fs::write(&input, b"events").unwrap();
        let spelled = dir.join(".").join("in.aedat4");
        let err = check(&spelled, &[Path::new("fixture"), &input], true).unwrap_err();
        assert!(err.to_string().contains("is an input"), "{err}");
        #[cfg(unix)]
        {
            let link = dir.join("link.toml");
            let _ = std::fs::remove_file(&link);
            std::os::unix::fs::symlink(&input, &link).unwrap();
            assert!(check(&link, &[&input], true).is_err());
            let err = check(Path::new("/dev/null"), &[], true).unwrap_err();
            assert!(err.to_string().contains("device"), "{err}");
        }
        let err = check(&dir, &[], true).unwrap_err();
        assert!(err.to_string().contains("directory"), "{err}");
        let other = dir.join("other.toml");
        std::fs::write(&other, b"old").unwrap();
        assert!(check(&other, &[&input], false).is_err());
        check(&other, &[&input], true).unwrap();
        check(&dir.join("new.toml"), &[&input], false).unwrap();
        write_whole(&other, b"new").unwrap();
        assert_eq!(std::fs::read(&other).unwrap(), b"new");
        assert!(!dir.join("other.partial.toml").exists());
        assert_eq!(std::fs::read(&input).unwrap(), b"events");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A folder output: a file is refused, an existing folder needs `force`, and a folder
    /// whose written parts hold an input is refused.
    #[test]
    fn folder_outputs_never_hold_their_inputs() {
        let dir = std::env::temp_dir().join(format!("v2ce-folder-{}", std::process::id()));
        let images = dir.join("images");
        std::fs::create_dir_all(&images).unwrap();
        let input = images.join("e.csv");
        std::fs::write(&input, b"t_us,x,y,on\n").unwrap();
        let names = ["images.txt", "images"];
        let err = |d: &Path, force| check_folder(d, &names, &[&input], force).unwrap_err();
        assert!(err(&input, true).to_string().contains("not a folder"));
        assert!(err(&dir, false).to_string().contains("--force"));
        assert!(err(&dir, true).to_string().contains("over an input"));
        let other = dir.join("out");
        assert!(check_folder(&other, &names, &[&input], false).is_ok());
        std::fs::create_dir_all(&other).unwrap();
        assert!(check_folder(&other, &names, &[&input], true).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
