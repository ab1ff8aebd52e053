//! The `[run]` table: what `v2ce run` reads, how its pipeline copes, and its outputs.
//!
//! Besides its own keys, `[run]` holds a shorthand for one output of each kind, whose keys fill
//! that sink's configuration directly (the same struct a `[[sink]]` table fills): `udp` is the
//! UDP output's address and `udp_KEY` (or `emit*`, as they have always been spelled) its `KEY`;
//! `tcp` and `tcp_KEY` the TCP output's; `out` and `out_KEY` the file output's. A key added
//! to a sink's configuration is a `[run]` key at once.

use std::collections::BTreeMap;

use serde::de::Error as _;
use serde::{Deserialize, Deserializer};

use crate::error::{Error, Result};
use crate::pipeline::queue::QueuePolicy;
use crate::sink::file::FileSinkConfig;
use crate::sink::tcp::TcpSinkConfig;
use crate::sink::udp::UdpSinkConfig;
use crate::sink::SinkConfig;

/// The `[run]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
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
    /// Hold the source until the first TCP client has connected (nothing is streamed before).
    pub wait_for_client: bool,
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
    /// The shorthand outputs (every other key of the table).
    #[serde(flatten)]
    pub outputs: Shorthands,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            source: String::new(),
            size: String::new(),
            replay_speed: 1.0,
            loop_source: false,
            fps: 0.0,
            wait_for_client: false,
            queue_policy: QueuePolicy::DropOldest,
            queue_capacity: 4,
            duration: 0.0,
            max_frames: 0,
            stats_interval: 10.0,
            reconnect_min_ms: 500,
            reconnect_max_ms: 10_000,
            http: String::new(),
            ready_timeout: 2.0,
            outputs: Shorthands::default(),
        }
    }
}

impl RunConfig {
    /// Checks values that TOML types cannot (the outputs are checked with the others, see
    /// [`super::Config::outputs`]).
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
            super::parse_size(&self.size)?;
        }
        Ok(())
    }
}

/// The UDP output the daemon sends to unless told otherwise.
pub const DEFAULT_UDP: &str = "127.0.0.1:3333";

/// The outputs the `[run]` table's shorthand keys configure: one of each kind, off while its
/// address (or path) is empty.
#[derive(Debug, Clone, PartialEq)]
pub struct Shorthands {
    /// `udp` (the address, [`DEFAULT_UDP`] by default), `udp_format`, `udp_payload`,
    /// `udp_rate` and `emit*`.
    pub udp: UdpSinkConfig,
    /// `tcp` (the address, off by default) and `tcp_format`, `tcp_max_clients`.
    pub tcp: TcpSinkConfig,
    /// `out` (the path, off by default) and `out_evt`.
    pub out: FileSinkConfig,
}

impl Default for Shorthands {
    fn default() -> Self {
        Shorthands {
            udp: UdpSinkConfig {
                address: DEFAULT_UDP.into(),
                ..UdpSinkConfig::default()
            },
            tcp: TcpSinkConfig::default(),
            out: FileSinkConfig::default(),
        }
    }
}

/// Which output a shorthand key is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Udp,
    Tcp,
    Out,
}

impl Kind {
    const ALL: [Kind; 3] = [Kind::Udp, Kind::Tcp, Kind::Out];

    /// The key that names the output's address or path, and the prefix of its other keys.
    fn key(self) -> &'static str {
        match self {
            Kind::Udp => "udp",
            Kind::Tcp => "tcp",
            Kind::Out => "out",
        }
    }

    /// The sink config's field the bare key fills.
    fn address_field(self) -> &'static str {
        match self {
            Kind::Out => "path",
            _ => "address",
        }
    }

    /// The sink config's fields.
    fn fields(self) -> &'static [&'static str] {
        match self {
            Kind::Udp => crate::toml_doc::keys::<UdpSinkConfig>(),
            Kind::Tcp => crate::toml_doc::keys::<TcpSinkConfig>(),
            Kind::Out => crate::toml_doc::keys::<FileSinkConfig>(),
        }
    }

    /// The `[run]` key of one of its fields.
    fn run_key(self, field: &str) -> String {
        if field == self.address_field() {
            self.key().to_string()
        } else if self == Kind::Udp && field.starts_with("emit") {
            field.to_string()
        } else {
            format!("{}_{field}", self.key())
        }
    }

    /// The output and the field a `[run]` key names, if it names one.
    fn route(key: &str) -> Option<(Kind, &'static str)> {
        Kind::ALL.into_iter().find_map(|kind| {
            let field = kind.fields().iter().find(|f| kind.run_key(f) == key)?;
            Some((kind, *field))
        })
    }
}

impl Shorthands {
    /// The outputs that are on, UDP first, then TCP, then the file.
    pub fn sinks(&self) -> Vec<SinkConfig> {
        let mut sinks = Vec::new();
        if !self.udp.address.is_empty() {
            sinks.push(SinkConfig::Udp(self.udp.clone()));
        }
        if !self.tcp.address.is_empty() {
            sinks.push(SinkConfig::Tcp(self.tcp.clone()));
        }
        if !self.out.path.is_empty() {
            sinks.push(SinkConfig::File(self.out.clone()));
        }
        sinks
    }

    /// Every shorthand key, for error messages.
    fn all_keys() -> Vec<String> {
        Kind::ALL
            .into_iter()
            .flat_map(|kind| kind.fields().iter().map(move |f| kind.run_key(f)))
            .collect()
    }
}

/// The keys `[run]` does not know itself come here: each fills its output's configuration,
/// and a key that names no output's field is an error that names it.
impl<'de> Deserialize<'de> for Shorthands {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let given = BTreeMap::<String, toml::Value>::deserialize(d)?;
        let defaults = Shorthands::default();
        let seed = |kind: Kind| {
            let address = match kind {
                Kind::Udp => defaults.udp.address.clone(),
                Kind::Tcp => defaults.tcp.address.clone(),
                Kind::Out => defaults.out.path.clone(),
            };
            let mut table = toml::Table::new();
            table.insert(kind.address_field().into(), address.into());
            table
        };
        let mut tables = Kind::ALL.map(seed);
        for (key, value) in given {
            let Some((kind, field)) = Kind::route(&key) else {
                let known = Shorthands::all_keys().join("`, `");
                return Err(D::Error::custom(format!(
                    "unknown field `{key}`, expected a key of the [run] table (config/v2ce.toml) or one of `{known}`"
                )));
            };
            tables[kind as usize].insert(field.into(), value);
        }
        let [udp, tcp, out] = tables;
        Ok(Shorthands {
            udp: fill(Kind::Udp, udp)?,
            tcp: fill(Kind::Tcp, tcp)?,
            out: fill(Kind::Out, out)?,
        })
    }
}

/// An output's config from its table; an error names the `[run]` key it came from.
fn fill<T: serde::de::DeserializeOwned, E: serde::de::Error>(
    kind: Kind,
    table: toml::Table,
) -> std::result::Result<T, E> {
    toml::Value::Table(table).try_into().map_err(|e| {
        let field = e.to_string();
        let field = field
            .rsplit_once("in `")
            .and_then(|(_, rest)| rest.split('`').next())
            .unwrap_or_default()
            .to_string();
        E::custom(format!("`{}`: {}", kind.run_key(&field), e.message()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::format::datagram::UdpFormat;
    use crate::sink::tcp::TcpFormat;
    use std::path::Path;

    #[test]
    fn every_sink_field_is_a_run_key() {
        let keys = Shorthands::all_keys();
        for k in [
            "udp",
            "udp_format",
            "udp_payload",
            "udp_rate",
            "emit",
            "emit_delay_ms",
            "emit_slice_ms",
            "emit_priority",
            "tcp",
            "tcp_format",
            "tcp_max_clients",
            "out",
            "out_evt",
        ] {
            assert!(keys.iter().any(|x| x == k), "{k} not in {keys:?}");
        }
        // Each key routes back to the output and field it was made from.
        for kind in Kind::ALL {
            for field in kind.fields() {
                assert_eq!(Kind::route(&kind.run_key(field)), Some((kind, *field)));
            }
        }
    }

    #[test]
    fn shorthand_keys_fill_the_sink_configs() {
        let c = Config::parse(
            "[run]\nudp_format = \"t64_x16_y16_on8\"\nemit_delay_ms = 5\ntcp = \"127.0.0.1:0\"\ntcp_max_clients = 3\nout = \"a.raw\"\nout_evt = 3\n",
            Path::new("x.toml"),
        )
        .unwrap();
        let o = &c.run.outputs;
        assert_eq!(o.udp.address, DEFAULT_UDP);
        assert_eq!(
            (o.udp.format, o.udp.emit_delay_ms),
            (UdpFormat::T64X16Y16On8, 5.0)
        );
        assert_eq!(o.udp.payload, UdpSinkConfig::default().payload);
        assert_eq!((o.tcp.format, o.tcp.max_clients), (TcpFormat::Aedat4, 3));
        assert_eq!((o.out.path.as_str(), o.out.evt), ("a.raw", Some(3)));
        assert_eq!(o.sinks().len(), 3);
    }

    #[test]
    fn a_bad_shorthand_key_is_an_error_at_its_line() {
        for (text, needles) in [
            (
                "[run]\nsource = \"x\"\nudp_paylod = 3\n",
                ["line 3", "udp_paylod"],
            ),
            ("[run]\n\nudp_payload = -3\n", ["line 3", "udp_payload"]),
            ("[run]\nemit = \"soon\"\n", ["line 2", "emit"]),
            ("[run]\n\n\ntcp_format = 7\n", ["line 4", "tcp_format"]),
        ] {
            let err = Config::parse(text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            for n in needles {
                assert!(err.contains(n), "{text:?}: {err}");
            }
        }
    }
}
