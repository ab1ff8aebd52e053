//! The typed configuration, read from TOML. Unknown keys are rejected with their line.
//!
//! Every field has a default, so an empty file (or none) is a valid configuration; command-line
//! flags override the file. The documented defaults live in `config/v2ce.toml`.

use std::path::Path;

use serde::Deserialize;

mod run;

pub use run::{Parts, RunConfig, DEFAULT_UDP};

use crate::error::{Error, Result};
pub use crate::sink::udp::EmitMode;
use crate::sink::SinkConfig;
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
    /// The daemon (`v2ce run`): source, outputs, queues, limits.
    pub run: RunConfig,
    /// What to ask a camera for.
    pub camera: crate::capture::CameraConfig,
    /// More outputs of the daemon, one `[[sink]]` table each (besides the `[run]` shorthands
    /// `udp`, `tcp` and `out`).
    pub sink: Vec<SinkConfig>,
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
    /// Every output of the daemon: the `[run]` shorthands, then the `[[sink]]` tables; an
    /// error when there is none.
    pub fn outputs(&self) -> Result<Vec<SinkConfig>> {
        let mut sinks = self.run.parts.sinks();
        sinks.extend(self.sink.iter().cloned());
        if sinks.is_empty() {
            return Err(Error::invalid(
                "run",
                "no output: set udp, tcp or out, or add a [[sink]]",
            ));
        }
        Ok(sinks)
    }

    /// Checks the whole configuration once the command line has been applied: the `[run]`
    /// table, each output, and that there is at least one (and a TCP one for
    /// `wait_for_client`).
    pub fn validate(&self) -> Result<()> {
        self.run.validate()?;
        let outputs = self.outputs()?;
        for sink in &outputs {
            sink.validate()?;
        }
        let files: Vec<&crate::sink::file::FileSinkConfig> = outputs
            .iter()
            .filter_map(|s| match s {
                SinkConfig::File(f) => Some(f),
                _ => None,
            })
            .collect();
        crate::sink::file::distinct_paths(&files)?;
        crate::sink::file::not_the_source(&files, Path::new(&self.run.parts.source.source))?;
        if self.run.wait_for_client && !outputs.iter().any(SinkConfig::serves_clients) {
            return Err(Error::invalid("run.wait_for_client", "needs a TCP output"));
        }
        Ok(())
    }

    /// Parses a TOML document; `origin` names it in errors.
    pub fn parse(text: &str, origin: &Path) -> Result<Self> {
        let mut config: Config = crate::toml_doc::parse(text, origin)?;
        if !config.stage1.preset_file.as_os_str().is_empty() {
            let file = origin
                .parent()
                .map_or(config.stage1.preset_file.clone(), |d| {
                    d.join(&config.stage1.preset_file)
                });
            config.stage1.load_preset_file(&file)?;
        }
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
        config
            .stage1
            .validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        config
            .stage1
            .learned
            .validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        config
            .run
            .validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        config
            .camera
            .validate()
            .map_err(|e| Error::format(origin, e.to_string()))?;
        for sink in &config.sink {
            sink.validate()
                .map_err(|e| Error::format(origin, e.to_string()))?;
        }
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
    use crate::sink::file::FileSinkConfig;
    use crate::sink::tcp::TcpFormat;
    use crate::sink::udp::UdpFormat;

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

    #[test]
    fn two_file_outputs_on_one_file_are_refused() {
        let dir = std::env::temp_dir().join(format!("v2ce-same-out-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let d = dir.display();
        for (a, b) in [
            (format!("{d}/a.csv"), format!("{d}/a.csv")),
            (format!("{d}/a.csv"), format!("{d}/sub/../a.csv")),
            (format!("{d}/a.csv"), format!("{d}/./a.csv")),
        ] {
            let text = format!("[run]\nout = \"{a}\"\n[[sink]]\ntype = \"file\"\npath = \"{b}\"\n");
            let e = Config::parse(&text, Path::new("x.toml"))
                .unwrap()
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains("two file outputs"), "{a} {b}: {e}");
        }
        // Through a hard link.
        std::fs::write(dir.join("hard-a.csv"), "").unwrap();
        let _ = std::fs::remove_file(dir.join("hard-b.csv"));
        std::fs::hard_link(dir.join("hard-a.csv"), dir.join("hard-b.csv")).unwrap();
        let text = format!(
            "[run]\nout = \"{d}/hard-a.csv\"\n[[sink]]\ntype = \"file\"\npath = \"{d}/hard-b.csv\"\n"
        );
        let e = Config::parse(&text, Path::new("x.toml"))
            .unwrap()
            .validate();
        assert!(e.unwrap_err().to_string().contains("two file outputs"));
        // An output that is the source: the same path, a symbolic or a hard link.
        std::fs::write(dir.join("source.aedat4"), "frames").unwrap();
        let _ = std::fs::remove_file(dir.join("source-hard.aedat4"));
        let _ = std::fs::remove_file(dir.join("source-soft.aedat4"));
        std::fs::hard_link(dir.join("source.aedat4"), dir.join("source-hard.aedat4")).unwrap();
        std::os::unix::fs::symlink(dir.join("source.aedat4"), dir.join("source-soft.aedat4"))
            .unwrap();
        for out in [
            "source.aedat4",
            "sub/../source.aedat4",
            "source-hard.aedat4",
            "source-soft.aedat4",
        ] {
            let text = format!("[run]\nsource = \"{d}/source.aedat4\"\nout = \"{d}/{out}\"\n");
            let e = Config::parse(&text, Path::new("x.toml"))
                .unwrap()
                .validate();
            let e = e.unwrap_err().to_string();
            assert!(e.contains("is the source"), "{out}: {e}");
        }
        let text = format!("[run]\nsource = \"{d}/source.aedat4\"\nout = \"{d}/other.aedat4\"\n");
        Config::parse(&text, Path::new("x.toml"))
            .unwrap()
            .validate()
            .unwrap();
        // Through a link to an existing file.
        std::fs::write(dir.join("real.csv"), "").unwrap();
        std::os::unix::fs::symlink(dir.join("real.csv"), dir.join("link.csv")).unwrap();
        let text = format!(
            "[run]\nout = \"{d}/real.csv\"\n[[sink]]\ntype = \"file\"\npath = \"{d}/link.csv\"\n"
        );
        let c = Config::parse(&text, Path::new("x.toml")).unwrap();
        assert!(c.validate().is_err());
        // Two files: fine.
        let text = format!(
            "[run]\nout = \"{d}/a.csv\"\n[[sink]]\ntype = \"file\"\npath = \"{d}/b.csv\"\n"
        );
        Config::parse(&text, Path::new("x.toml"))
            .unwrap()
            .validate()
            .unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn sink_tables_add_outputs_after_the_shorthands() {
        let text = r#"
[run]
tcp = "127.0.0.1:0"
tcp_format = "evt3"

[[sink]]
type = "udp"
address = "127.0.0.1:4000"
format = "t64_x16_y16_on8"
payload = 1300

[[sink]]
type = "tcp"
address = "127.0.0.1:0"

[[sink]]
type = "file"
path = "out.raw"
evt = 3
"#;
        let c = Config::parse(text, Path::new("x.toml")).unwrap();
        let outputs = c.outputs().unwrap();
        assert_eq!(outputs.len(), 5, "{outputs:?}");
        match (&outputs[0], &outputs[1], &outputs[2], &outputs[3]) {
            (SinkConfig::Udp(u0), SinkConfig::Tcp(t0), SinkConfig::Udp(u), SinkConfig::Tcp(t)) => {
                assert_eq!(u0.address, "127.0.0.1:3333");
                assert_eq!(t0.format, TcpFormat::Evt3);
                assert_eq!(
                    (u.format, u.payload, u.rate),
                    (UdpFormat::T64X16Y16On8, 1300, 0)
                );
                assert_eq!(t.format, TcpFormat::Aedat4);
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            outputs[4],
            SinkConfig::File(FileSinkConfig {
                path: "out.raw".into(),
                evt: Some(3)
            })
        );
        c.validate().unwrap();
    }

    #[test]
    fn bad_sink_tables_are_errors_that_say_what() {
        let cases = [
            ("[[sink]]\ntype = \"pigeon\"\naddress = \"x\"\n", "pigeon"),
            (
                "[[sink]]\ntype = \"udp\"\naddress = \"h:1\"\nport = 3\n",
                "port",
            ),
            (
                "[[sink]]\ntype = \"udp\"\naddress = \"h:1\"\npayload = 2\n",
                "payload",
            ),
            ("[[sink]]\ntype = \"tcp\"\n", "address"),
            ("[[sink]]\ntype = \"file\"\npath = \"a.mp4\"\n", "mp4"),
        ];
        for (text, needle) in cases {
            let err = Config::parse(text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(needle), "{text}: {err}");
        }
        let mut c = Config::default();
        c.run.parts.udp.address.clear();
        assert!(c.validate().unwrap_err().to_string().contains("no output"));
        c.run.wait_for_client = true;
        c.sink.push(SinkConfig::File(FileSinkConfig::new("a.csv")));
        assert!(c.validate().unwrap_err().to_string().contains("TCP"));
    }

    #[test]
    fn a_preset_file_is_read_relative_to_the_config_and_replaces_the_preset() {
        let dir = std::env::temp_dir().join(format!("v2ce-config-preset-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut sensor = crate::stage1::Preset::Dvxplorer.config();
        sensor.threshold_on = 0.41;
        std::fs::write(dir.join("sensor.toml"), toml::to_string(&sensor).unwrap()).unwrap();
        let c = Config::parse(
            "[stage1]\npreset_file = \"sensor.toml\"\n[stage1.physics]\nleak_hz = 0.5\nlight = \"exposure\"\nflicker_hz = 120\nflicker_depth = 0.2\n",
            &dir.join("v2ce.toml"),
        )
        .unwrap();
        let got = c.stage1.physics_config();
        assert_eq!(got.threshold_on, 0.41);
        assert_eq!(got.cutoff_hz, sensor.cutoff_hz);
        // Overrides still apply on top.
        assert_eq!(got.leak_hz, 0.5);
        assert_eq!(got.light, crate::stage1::LightModel::Exposure);
        assert_eq!((got.flicker_hz, got.flicker_depth), (120.0, 0.2));
        assert!(c.stage1.preset_name().contains("sensor.toml"));
        // A bad file is an error naming it.
        std::fs::write(dir.join("bad.toml"), "threshold_on = -1\n").unwrap();
        let err = Config::parse(
            "[stage1]\npreset_file = \"bad.toml\"\n",
            &dir.join("v.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("bad.toml") && err.contains("threshold_on"),
            "{err}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Every parameter a preset file holds can be overridden in `[stage1.physics]`: a whole
    /// preset given as overrides, each value changed, makes that preset.
    #[test]
    fn every_preset_parameter_is_an_override() {
        let mut sensor = crate::stage1::Preset::Dvxplorer.config();
        sensor.threshold_noise = 0.07;
        sensor.threshold_sigma = 0.04;
        let table = toml::to_string(&sensor).unwrap();
        let c = Config::parse(
            &format!("[stage1.physics]\n{table}"),
            std::path::Path::new("v2ce.toml"),
        )
        .unwrap();
        assert_eq!(c.stage1.physics_config(), sensor);
    }
}
