//! The typed configuration, read from TOML. Unknown keys are rejected with their line.
//!
//! Every field has a default, so an empty file (or none) is a valid configuration; command-line
//! flags override the file. The documented defaults live in `config/v2ce.toml`.

use std::path::Path;

use serde::Deserialize;

use crate::error::{Error, Result};
use crate::stage1::Stage1Config;
use crate::stage2::SamplerKind;
use crate::voxel::DEFAULT_BINS;

/// The whole configuration.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Stage 1 (frames to events).
    pub stage1: Stage1Config,
    /// Stage 2 (voxels to events).
    pub stage2: Stage2Config,
}

/// Stage 2 settings.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Stage2Config {
    /// The sampler.
    pub sampler: SamplerKind,
    /// Seed of the sampler's random draws.
    pub seed: u64,
    /// Temporal nodes per frame interval (`C`).
    pub bins: usize,
}

impl Default for Stage2Config {
    fn default() -> Self {
        Stage2Config {
            sampler: SamplerKind::DEFAULT,
            seed: 0,
            bins: DEFAULT_BINS,
        }
    }
}

impl Config {
    /// Parses a TOML document; `origin` names it in errors.
    pub fn parse(text: &str, origin: &Path) -> Result<Self> {
        let config: Config = toml::from_str(text).map_err(|e| {
            let at = e
                .span()
                .map(|s| {
                    let line = text[..s.start.min(text.len())].matches('\n').count() + 1;
                    format!("line {line}: ")
                })
                .unwrap_or_default();
            Error::format(origin, format!("{at}{}", e.message()))
        })?;
        if !(2..=1024).contains(&config.stage2.bins) {
            return Err(Error::format(
                origin,
                format!("stage2.bins = {} is outside 2..=1024", config.stage2.bins),
            ));
        }
        config
            .stage1
            .physics_config()
            .validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        Ok(config)
    }

    /// Reads a TOML file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_is_the_default() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/v2ce.toml");
        assert_eq!(Config::load(&path).unwrap(), Config::default());
    }

    #[test]
    fn unknown_key_is_rejected_with_its_line() {
        let err = Config::parse(
            "[stage2]\nseed = 3\nsampeler = \"even\"\n",
            Path::new("x.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("line 3"), "{err}");
        assert!(err.contains("sampeler"), "{err}");
        let err = Config::parse("[stage2]\nsampler = \"fast\"\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 2"), "{err}");
        let c = Config::parse("[stage2]\nsampler = \"ldati-random\"\n", Path::new("x")).unwrap();
        assert_eq!(c.stage2.sampler, SamplerKind::LdatiRandom);
    }
}
