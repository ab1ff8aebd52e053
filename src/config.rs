//! The typed configuration, read from TOML. Unknown keys are rejected with their line.
//!
//! Every field has a default, so an empty file (or none) is a valid configuration; command-line
//! flags override the file. The documented defaults live in `config/v2ce.toml`.

use std::path::Path;

use serde::Deserialize;

use crate::error::{Error, Result};
use crate::format::datagram::UdpFormat;
use crate::pipeline::queue::QueuePolicy;
use crate::sink::file::FileSinkConfig;
use crate::sink::tcp::{TcpFormat, TcpSinkConfig};
pub use crate::sink::udp::EmitMode;
use crate::sink::udp::UdpSinkConfig;
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

/// The `[run]` table: what `v2ce run` reads, where it sends, and how it copes.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// A camera (`/dev/video0`, or an index), a file (video, image folder, `.y4m`, `.aedat4`
    /// with APS frames), or `""`: the first camera, else the bundled fixture video.
    pub source: String,
    /// Resample frames to `WIDTHxHEIGHT` (`""`: the source's size).
    pub size: String,
    /// A file source is replayed at this multiple of real time, paced by its own timestamps.
    pub replay_speed: f64,
    /// Replay a file source again and again (times keep increasing).
    #[serde(rename = "loop")]
    pub loop_source: bool,
    /// Frame rate of an image folder without a times file (0: required from the folder).
    pub fps: f64,
    /// Send events as UDP datagrams to this `HOST:PORT` (`""`: no UDP).
    pub udp: String,
    /// The datagram format: spif, spif_timestamped, t64_x16_y16_on8, t32_x16_y15_on1.
    pub udp_format: UdpFormat,
    /// Most datagrams per second (0: as fast as the socket takes them).
    pub udp_rate: u32,
    /// Largest datagram payload in bytes; 512 fits every common receiver whole (aestream
    /// reads 512 bytes per datagram, SpiNNaker's SPIF listener 1024; more is cut off there).
    pub udp_payload: usize,
    /// When events leave over UDP: "event-time" (each at its own time plus `emit_delay_ms`,
    /// spread as a sensor's) or "asap" (a frame interval's events in one burst).
    pub emit: EmitMode,
    /// How far behind the frames events leave at event time, milliseconds: one frame interval
    /// (a learned window's stride of them) plus the processing time.
    pub emit_delay_ms: f64,
    /// Longest spread of due times in one datagram at event time, milliseconds.
    pub emit_slice_ms: f64,
    /// Realtime (`SCHED_FIFO`) priority of the thread that sends at event time, 1..=99, when
    /// the process may (CAP_SYS_NICE or `LimitRTPRIO`); 0, or when refused: normal scheduling,
    /// spinning the last 100 us before each due time.
    pub emit_priority: u8,
    /// Serve an event stream to TCP clients on this `HOST:PORT` (`""`: no TCP).
    pub tcp: String,
    /// What TCP clients receive: "aedat4" (DV's network stream), "evt2" or "evt3" (Prophesee
    /// RAW, the bytes of a `.raw` file).
    pub tcp_format: TcpFormat,
    /// Hold the source until the first TCP client has connected (nothing is streamed before).
    pub wait_for_client: bool,
    /// Also write events to this file; the extension picks the format (`""`: none).
    pub out: String,
    /// What a full queue does: "drop-oldest" (stay live) or "block" (lose nothing).
    pub queue_policy: QueuePolicy,
    /// Capacity of each queue between stages, in frames.
    pub queue_capacity: usize,
    /// Stop after this many seconds (0: run until stopped).
    pub duration: f64,
    /// Stop after this many frames (0: no limit).
    pub max_frames: u64,
    /// Seconds between stats lines on the log and in the systemd status.
    pub stats_interval: f64,
    /// First wait before reopening a camera that failed, milliseconds; doubled per failure.
    pub reconnect_min_ms: u64,
    /// Longest wait between reopening attempts, milliseconds.
    pub reconnect_max_ms: u64,
    /// Serve `/metrics`, `/healthz`, `/readyz` and the live preview page on this `HOST:PORT`
    /// (`""`: off; keep it on loopback unless the network is trusted: no authentication).
    pub http: String,
    /// `/readyz` says not ready when no frame came for this many seconds.
    pub ready_timeout: f64,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            source: String::new(),
            size: String::new(),
            replay_speed: 1.0,
            loop_source: false,
            fps: 0.0,
            udp: "127.0.0.1:3333".into(),
            udp_format: UdpFormat::Spif,
            udp_rate: 0,
            udp_payload: 512,
            emit: EmitMode::EventTime,
            emit_delay_ms: 100.0,
            emit_slice_ms: 0.5,
            emit_priority: 10,
            tcp: String::new(),
            tcp_format: TcpFormat::Aedat4,
            wait_for_client: false,
            out: String::new(),
            queue_policy: QueuePolicy::DropOldest,
            queue_capacity: 4,
            duration: 0.0,
            max_frames: 0,
            stats_interval: 10.0,
            reconnect_min_ms: 500,
            reconnect_max_ms: 10_000,
            http: String::new(),
            ready_timeout: 2.0,
        }
    }
}

impl RunConfig {
    /// The outputs its shorthand keys `udp`, `tcp` and `out` configure, in that order.
    pub fn shorthand_sinks(&self) -> Vec<SinkConfig> {
        let mut sinks = Vec::new();
        if !self.udp.is_empty() {
            sinks.push(SinkConfig::Udp(UdpSinkConfig {
                address: self.udp.clone(),
                format: self.udp_format,
                payload: self.udp_payload,
                rate: self.udp_rate,
                emit: self.emit,
                emit_delay_ms: self.emit_delay_ms,
                emit_slice_ms: self.emit_slice_ms,
                emit_priority: self.emit_priority,
            }));
        }
        if !self.tcp.is_empty() {
            sinks.push(SinkConfig::Tcp(TcpSinkConfig {
                address: self.tcp.clone(),
                format: self.tcp_format,
                max_clients: crate::sink::tcp::DEFAULT_MAX_CLIENTS,
            }));
        }
        if !self.out.is_empty() {
            sinks.push(SinkConfig::File(FileSinkConfig::new(&self.out)));
        }
        sinks
    }

    /// Checks values that TOML types cannot.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &'static str, message: String| Err(Error::invalid(what, message));
        crate::limits::replay_speed("run.replay_speed", self.replay_speed)?;
        if self.fps != 0.0 {
            crate::limits::frame_rate("run.fps", self.fps)?;
        }
        crate::limits::seconds("run.duration", self.duration, true)?;
        crate::limits::seconds("run.stats_interval", self.stats_interval, false)?;
        crate::limits::seconds("run.ready_timeout", self.ready_timeout, false)?;
        if !self.http.is_empty() && self.http.parse::<std::net::SocketAddr>().is_err() {
            return bad(
                "run.http",
                format!("'{}' (expected IP:PORT, e.g. 127.0.0.1:9464)", self.http),
            );
        }
        if !(1..=1024).contains(&self.queue_capacity) {
            return bad(
                "run.queue_capacity",
                format!("{} (must be 1..=1024)", self.queue_capacity),
            );
        }
        if self.reconnect_min_ms == 0 || self.reconnect_max_ms < self.reconnect_min_ms {
            return bad(
                "run.reconnect_min_ms",
                "must be > 0 and at most reconnect_max_ms".into(),
            );
        }
        if !self.size.is_empty() {
            parse_size(&self.size)?;
        }
        Ok(())
    }
}

/// Parses a TOML document into `T`; an error names `origin` and the line (unknown keys
/// included, where `T` denies them).
pub fn parse_toml<T: serde::de::DeserializeOwned>(text: &str, origin: &Path) -> Result<T> {
    toml::from_str(text).map_err(|e| {
        let at = e
            .span()
            .map(|s| {
                let line = text[..s.start.min(text.len())].matches('\n').count() + 1;
                format!("line {line}: ")
            })
            .unwrap_or_default();
        Error::format(origin, format!("{at}{}", e.message()))
    })
}

/// Parses `WIDTHxHEIGHT` (each 1..=65535).
pub fn parse_size(text: &str) -> Result<(u16, u16)> {
    let parsed = text
        .split_once(['x', 'X'])
        .and_then(|(w, h)| Some((w.trim().parse::<u16>().ok()?, h.trim().parse::<u16>().ok()?)));
    match parsed {
        Some((w, h)) if w > 0 && h > 0 => {
            crate::limits::frame_size("size", w.into(), h.into())?;
            Ok((w, h))
        }
        _ => Err(Error::invalid(
            "size",
            format!("{text:?} (expected WIDTHxHEIGHT, e.g. 346x260)"),
        )),
    }
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
    /// Every output of the daemon: the `[run]` shorthands, then the `[[sink]]` tables.
    pub fn outputs(&self) -> Vec<SinkConfig> {
        let mut sinks = self.run.shorthand_sinks();
        sinks.extend(self.sink.iter().cloned());
        sinks
    }

    /// Checks the whole configuration once the command line has been applied: the `[run]`
    /// table, each output, and that there is at least one (and a TCP one for
    /// `wait_for_client`).
    pub fn validate(&self) -> Result<()> {
        self.run.validate()?;
        let outputs = self.outputs();
        for sink in &outputs {
            sink.validate()?;
        }
        if outputs.is_empty() {
            return Err(Error::invalid(
                "run",
                "no output: set udp, tcp or out, or add a [[sink]]",
            ));
        }
        if self.run.wait_for_client && !outputs.iter().any(SinkConfig::serves_clients) {
            return Err(Error::invalid("run.wait_for_client", "needs a TCP output"));
        }
        Ok(())
    }

    /// Parses a TOML document; `origin` names it in errors.
    pub fn parse(text: &str, origin: &Path) -> Result<Self> {
        let mut config: Config = parse_toml(text, origin)?;
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
        let outputs = c.outputs();
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
        c.run.udp.clear();
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
}
