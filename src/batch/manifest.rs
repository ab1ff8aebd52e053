//! The inputs of a batch: a manifest file (a list of `PATH [key=value ...]` lines, or JSON
//! lines) or a glob, each input with its [`Settings`] and the output it gets.

use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

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
    /// Outputs get `extension` (the output format's).
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
                Some(o) => relative_output(Path::new(&o)).ok_or_else(|| {
                    Error::invalid(
                        "manifest",
                        format!(
                            "{name}: output '{o}' must be a relative path inside the output folder"
                        ),
                    )
                })?,
                None => default_output(&name, extension),
            };
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
}

type Entry = (String, PathBuf, Option<String>, Settings);

fn read_entries(path: &Path) -> Result<Vec<Entry>> {
    let base = path.parent().unwrap_or(Path::new(""));
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let jsonl = path.extension().is_some_and(|e| e == "jsonl");
    let mut entries = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |m: String| Error::format(path, format!("line {}: {m}", i + 1));
        let (name, output, settings) = if jsonl || line.starts_with('{') {
            let item: JsonItem = serde_json::from_str(line).map_err(|e| bad(e.to_string()))?;
            (item.input, item.output, item.settings)
        } else {
            let mut fields = line.split_whitespace();
            let name = fields.next().unwrap_or_default().to_string();
            let mut map = serde_json::Map::new();
            let mut output = None;
            for f in fields {
                let (k, v) = f
                    .split_once('=')
                    .ok_or_else(|| bad(format!("'{f}' is not key=value")))?;
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
            let settings: Settings = serde_json::from_value(serde_json::Value::Object(map))
                .map_err(|e| bad(e.to_string()))?;
            (name, output, settings)
        };
        let input = base.join(&name);
        entries.push((name, input, output, settings));
    }
    Ok(entries)
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

/// `p` if it stays inside a folder (relative, no `..`).
fn relative_output(p: &Path) -> Option<PathBuf> {
    let inside = !p.as_os_str().is_empty()
        && p.components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    inside.then(|| p.to_path_buf())
}

/// The input's own relative path with the output's extension; an absolute or escaping path
/// keeps its file name only.
pub(super) fn default_output(name: &str, extension: &str) -> PathBuf {
    let p = Path::new(name.trim_end_matches('/'));
    let base =
        relative_output(p).unwrap_or_else(|| PathBuf::from(p.file_name().unwrap_or_default()));
    base.with_extension(extension)
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
}
