//! The inputs of a batch: a manifest file (a list of `PATH [key=value ...]` lines, or JSON
//! lines) or a glob, each input with its [`Settings`] and the output it gets.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::ledger::LEDGER_DIR;
use super::lines::{for_each_line, Line};
use super::paths::{in_ledger_dir, normalize};
use crate::error::{Error, Result};

/// The longest manifest line read, bytes: a path of up to `PATH_MAX` (4096) with its settings
/// fits many times over; a longer line is an error naming the file and line.
pub(crate) const MAX_MANIFEST_LINE: usize = 64 * 1024;

/// The largest manifest read, bytes (1 GiB: ten million lines of a hundred bytes).
pub(crate) const MAX_MANIFEST_BYTES: u64 = 1 << 30;

/// Per-item settings; absent ones come from the config.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Settings {
    /// Frame rate of an image folder without times.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// Resample frames to `WIDTHxHEIGHT`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size: Option<String>,
    /// The physics tier's preset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preset: Option<String>,
    /// Stage 1 tier: `physics`, `learned` or `auto`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tier: Option<crate::stage1::Tier>,
    /// Seed of Stage 1 and Stage 2.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// One input of a manifest.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Item {
    /// The input as the manifest names it (the key of the ledger).
    pub name: String,
    /// Where it is.
    pub input: PathBuf,
    /// The output, relative to the output folder.
    pub output: PathBuf,
    /// Its settings.
    pub settings: Settings,
    /// Its size in bytes (a folder: its files'), for balancing shards.
    pub bytes: u64,
}

/// A manifest line in JSON.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonItem {
    input: String,
    #[serde(default)]
    output: Option<String>,
    #[serde(flatten)]
    settings: Settings,
}

/// The inputs of a batch.
#[derive(Debug, Clone)]
pub struct Manifest {
    /// In manifest order.
    pub(crate) items: Vec<Item>,
}

impl Manifest {
    /// Reads `spec`: a manifest file (`.jsonl`, or lines starting with `{`, are JSON items;
    /// other lines are `PATH [key=value ...]`; `#` starts a comment; relative paths are taken
    /// from the manifest's folder), or, when no such file exists, a glob (`clips/*.mp4`).
    /// Outputs get `extension` (the output format's); each output is normalised (`./x` and
    /// `a/../x` are `x`), and two inputs with one output, or an output inside the ledgers'
    /// folder (`.v2ce-batch`), are refused. A line longer than 64 KiB or a file larger than
    /// 1 GiB (`MAX_MANIFEST_LINE`, `MAX_MANIFEST_BYTES`) is an error.
    pub fn load(spec: &str, extension: &str) -> Result<Manifest> {
        let path = Path::new(spec);
        let entries = if path.is_file() {
            read_entries(path)?
        } else if spec.contains(['*', '?', '[']) {
            glob_entries(spec)?
        } else {
            return Err(Error::invalid(
                "manifest",
                format!("{spec}: no such file, and not a glob pattern"),
            ));
        };
        if entries.is_empty() {
            return Err(Error::invalid(
                "manifest",
                format!("{spec}: lists no inputs"),
            ));
        }
        let mut items = Vec::with_capacity(entries.len());
        let mut outputs: HashMap<PathBuf, String> = HashMap::new();
        for (name, input, output, settings) in entries {
            let output = match output {
                Some(o) => normalize(Path::new(&o)).ok_or_else(|| {
                    Error::invalid(
                        "manifest",
                        format!(
                            "{name}: output '{o}' must be a relative path inside the output folder"
                        ),
                    )
                })?,
                None => default_output(&name, extension).ok_or_else(|| {
                    Error::invalid(
                        "manifest",
                        format!("{name}: no output name follows from it; give it an \"output\""),
                    )
                })?,
            };
            if in_ledger_dir(&output) {
                return Err(Error::invalid(
                    "manifest",
                    format!(
                        "{name}: output '{}' is inside {LEDGER_DIR}/, the folder the batch keeps \
                         for its ledgers; give it another \"output\"",
                        output.display()
                    ),
                ));
            }
            if let Some(other) = outputs.insert(output.clone(), name.clone()) {
                return Err(Error::invalid(
                    "manifest",
                    format!(
                        "{other} and {name} would both write {}; give one an \"output\"",
                        output.display()
                    ),
                ));
            }
            let bytes = size_of(&input);
            items.push(Item {
                name,
                input,
                output,
                settings,
                bytes,
            });
        }
        Ok(Manifest { items })
    }

    /// Checks the outputs in the output folder `out` as the disk resolves them (links
    /// followed): none leads into the ledgers' folder, and no two are one file.
    pub(crate) fn check_outputs(&self, out: &Path) -> Result<()> {
        super::paths::check_on_disk(out, &self.items)
    }
}

type Entry = (String, PathBuf, Option<String>, Settings);

fn read_entries(path: &Path) -> Result<Vec<Entry>> {
    let base = path.parent().unwrap_or(Path::new(""));
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let jsonl = path.extension().is_some_and(|e| e == "jsonl");
    let mut entries = Vec::new();
    let reader = std::io::BufReader::new(file);
    for_each_line(
        path,
        reader,
        MAX_MANIFEST_LINE,
        MAX_MANIFEST_BYTES,
        |number, line| {
            let bad = |m: String| Error::format(path, format!("line {number}: {m}"));
            let line = match line {
                Line::Text(l) => l.trim(),
                Line::NotUtf8 => return Err(bad("not UTF-8 text".into())),
                Line::TooLong => {
                    return Err(bad(format!(
                        "longer than {MAX_MANIFEST_LINE} bytes, the longest manifest line read"
                    )))
                }
            };
            if line.is_empty() || line.starts_with('#') {
                return Ok(());
            }
            let (name, output, settings) = parse_line(line, jsonl).map_err(bad)?;
            let input = base.join(&name);
            entries.push((name, input, output, settings));
            Ok(())
        },
    )?;
    Ok(entries)
}

/// One manifest line (trimmed, not a comment): the input's name, its output and settings.
fn parse_line(
    line: &str,
    jsonl: bool,
) -> std::result::Result<(String, Option<String>, Settings), String> {
    if jsonl || line.starts_with('{') {
        let item: JsonItem = serde_json::from_str(line).map_err(|e| e.to_string())?;
        return Ok((item.input, item.output, item.settings));
    }
    let mut fields = line.split_whitespace();
    let name = fields.next().unwrap_or_default().to_string();
    let mut map = serde_json::Map::new();
    let mut output = None;
    for f in fields {
        let (k, v) = f
            .split_once('=')
            .ok_or_else(|| format!("'{f}' is not key=value"))?;
        if k == "output" {
            output = Some(v.to_string());
            continue;
        }
        let value = match v.parse::<u64>() {
            Ok(n) => serde_json::Value::from(n),
            Err(_) => match v.parse::<f64>() {
                Ok(x) if x.is_finite() => serde_json::Value::from(x),
                _ => serde_json::Value::from(v),
            },
        };
        map.insert(k.to_string(), value);
    }
    let settings: Settings =
        serde_json::from_value(serde_json::Value::Object(map)).map_err(|e| e.to_string())?;
    Ok((name, output, settings))
}

fn glob_entries(pattern: &str) -> Result<Vec<Entry>> {
    let paths = glob::glob(pattern)
        .map_err(|e| Error::invalid("manifest", format!("bad glob '{pattern}': {e}")))?;
    let mut entries = Vec::new();
    for p in paths {
        let p = p.map_err(|e| Error::invalid("manifest", e.to_string()))?;
        let name = p.to_string_lossy().into_owned();
        entries.push((name, p, None, Settings::default()));
    }
    Ok(entries)
}

/// The input's own relative path (normalised) with the output's extension; an absolute or
/// escaping path keeps its file name only; `None` when neither gives a name (`.`).
pub(super) fn default_output(name: &str, extension: &str) -> Option<PathBuf> {
    let p = Path::new(name.trim_end_matches('/'));
    let base = normalize(p).or_else(|| Some(PathBuf::from(p.file_name()?)))?;
    Some(base.with_extension(extension))
}

fn size_of(path: &Path) -> u64 {
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => std::fs::read_dir(path)
            .map(|d| {
                d.filter_map(|e| e.ok()?.metadata().ok())
                    .filter(|m| m.is_file())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifests_in_every_form() {
        let dir = std::env::temp_dir().join(format!("v2ce-batch-manifest-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("clips")).unwrap();
        for f in ["a.y4m", "b.y4m", "c.mp4"] {
            std::fs::write(dir.join("clips").join(f), b"x").unwrap();
        }
        let list = dir.join("list.txt");
        std::fs::write(
            &list,
            "# clips\nclips/a.y4m fps=25 size=64x48 preset=davis346 seed=3\n\nclips/b.y4m tier=learned output=x/b.raw\n",
        )
        .unwrap();
        let m = Manifest::load(list.to_str().unwrap(), "aedat4").unwrap();
        assert_eq!(m.items.len(), 2);
        assert_eq!(m.items[0].input, dir.join("clips/a.y4m"));
        assert_eq!(m.items[0].output, PathBuf::from("clips/a.aedat4"));
        assert_eq!(m.items[0].settings.fps, Some(25.0));
        assert_eq!(m.items[0].settings.size.as_deref(), Some("64x48"));
        assert_eq!(m.items[0].settings.seed, Some(3));
        assert_eq!(m.items[1].settings.tier, Some(crate::stage1::Tier::Learned));
        assert_eq!(m.items[1].output, PathBuf::from("x/b.raw"));
        let jsonl = dir.join("m.jsonl");
        std::fs::write(&jsonl, "{\"input\": \"clips/c.mp4\", \"fps\": 30}\n").unwrap();
        let m = Manifest::load(jsonl.to_str().unwrap(), "csv").unwrap();
        assert_eq!(m.items[0].output, PathBuf::from("clips/c.csv"));
        let pattern = format!("{}/clips/*.y4m", dir.display());
        let m = Manifest::load(&pattern, "aedat4").unwrap();
        assert_eq!(m.items.len(), 2);
        // Errors: an unknown key, two inputs to one output, an output outside the folder.
        for (text, expect) in [
            ("clips/a.y4m colour=red\n", "colour"),
            ("clips/a.y4m\nclips/a.y4m\n", "would both write"),
            ("clips/a.y4m output=../x.aedat4\n", "relative path"),
            ("{\"input\": 3}\n", "line 1"),
        ] {
            std::fs::write(&list, text).unwrap();
            let err = Manifest::load(list.to_str().unwrap(), "aedat4")
                .unwrap_err()
                .to_string();
            assert!(err.contains(expect), "{text}: {err}");
        }
        assert!(Manifest::load("/nonexistent/list.txt", "aedat4").is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Loads `text` as a manifest in a folder of its own (named `tag`).
    fn load(tag: &str, text: &[u8]) -> Result<Manifest> {
        let dir = std::env::temp_dir().join(format!("v2ce-batch-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let list = dir.join("list.txt");
        std::fs::write(&list, text).unwrap();
        let m = Manifest::load(list.to_str().unwrap(), "aedat4");
        std::fs::remove_dir_all(&dir).unwrap();
        m
    }

    #[test]
    fn one_output_written_two_ways_is_one_output() {
        for text in [
            "a.y4m output=x.aedat4\nb.y4m output=./x.aedat4\n",
            "a.y4m output=x.aedat4\nb.y4m output=d/../x.aedat4\n",
            "a.y4m output=d/x.aedat4\nb.y4m output=d//x.aedat4\n",
            "a.y4m output=d/x.aedat4\nb.y4m output=./d/./x.aedat4\n",
            "clips/a.y4m\n./clips/a.y4m\n",
            "clips/a.y4m\nclips//a.y4m\n",
            "x.y4m\nb.y4m output=x.aedat4\n",
        ] {
            let err = load("dup", text.as_bytes()).unwrap_err().to_string();
            assert!(err.contains("would both write"), "{text}: {err}");
        }
        // What is written is the normalised output, and it may not leave the folder.
        let m = load("norm", b"a.y4m output=./d//e/../x.aedat4\n./clips/b.y4m\n").unwrap();
        assert_eq!(m.items[0].output, PathBuf::from("d/x.aedat4"));
        assert_eq!(m.items[1].output, PathBuf::from("clips/b.aedat4"));
        for text in ["a.y4m output=d/../../x.aedat4\n", "a.y4m output=.\n", ".\n"] {
            let err = load("escape", text.as_bytes()).unwrap_err().to_string();
            assert!(err.contains("output"), "{text}: {err}");
        }
    }

    #[test]
    fn the_ledgers_folder_is_no_output() {
        for text in [
            "a.y4m output=.v2ce-batch/shard-0-of-1.jsonl\n",
            "a.y4m output=./.v2ce-batch/shard-0-of-1.jsonl\n",
            "a.y4m output=d/../.v2ce-batch/x.aedat4\n",
            "a.y4m output=.v2ce-batch//x\n",
            "a.y4m output=.V2CE-BATCH/x\n",
            "{\"input\": \"a.y4m\", \"output\": \".v2ce-batch/x\"}\n",
            ".v2ce-batch/a.y4m\n",
        ] {
            let err = load("ledger", text.as_bytes()).unwrap_err().to_string();
            assert!(
                err.contains("inside .v2ce-batch/") && err.contains("ledgers"),
                "{text}: {err}"
            );
        }
        // A name that only begins like it is fine.
        let m = load(
            "ledger-ok",
            b"a.y4m output=.v2ce-batch.aedat4\nd/.v2ce-batch/b.y4m\n",
        );
        assert_eq!(m.unwrap().items.len(), 2);
    }

    #[test]
    fn manifest_lines_and_size_are_bounded() {
        let mut long = vec![b'a'; MAX_MANIFEST_LINE + 1];
        long.push(b'\n');
        let mut text = b"ok.y4m\n".to_vec();
        text.extend_from_slice(&long);
        let err = load("long", &text).unwrap_err().to_string();
        assert!(
            err.contains("list.txt: line 2: longer than 65536 bytes"),
            "{err}"
        );
        // Cut inside a character: an error with its line, not a whole-file failure without one.
        let err = load("utf8", b"ok.y4m\nb\xc3\n").unwrap_err().to_string();
        assert!(err.contains("line 2: not UTF-8"), "{err}");
        let err = Manifest::load("/dev/zero", "aedat4")
            .unwrap_err()
            .to_string();
        assert!(err.contains("/dev/zero"), "{err}");
    }
}
