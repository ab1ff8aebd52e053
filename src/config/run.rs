//! The `[run]` table: what `v2ce run` reads, how its pipeline copes, and its outputs.
//!
//! Besides its own keys (the pipeline's), `[run]` holds the source's keys, which fill its
//! [`SourceConfig`], and a shorthand for one output of each kind, whose keys fill that sink's
//! configuration directly (the same struct a `[[sink]]` table fills): `udp` is the UDP
//! output's address and `udp_KEY` (or `emit*`, as they have always been spelled) its `KEY`;
//! `tcp` and `tcp_KEY` the TCP output's; `out` and `out_KEY` the file output's. A key added
//! to the source's or a sink's configuration is a `[run]` key at once.

use std::collections::BTreeMap;

use serde::de::Error as _;
use serde::{Deserialize, Deserializer};

use crate::error::{Error, Result};
use crate::pipeline::queue::QueuePolicy;
use crate::sink::file::FileSinkConfig;
use crate::sink::ros2::Ros2SinkConfig;
use crate::sink::tcp::TcpSinkConfig;
use crate::sink::udp::UdpSinkConfig;
use crate::sink::SinkConfig;
use crate::source::SourceConfig;

/// The `[run]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct RunConfig {
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
    /// Serve `/metrics`, `/healthz`, `/readyz` and the live preview page on this `HOST:PORT`
    /// (`""`: off; keep it on loopback unless the network is trusted: no authentication).
    pub http: String,
    /// `/readyz` says not ready when no frame came for this many seconds.
    pub ready_timeout: f64,
    /// The source and the shorthand outputs (every other key of the table).
    #[serde(flatten)]
    pub parts: Parts,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            wait_for_client: false,
            queue_policy: QueuePolicy::DropOldest,
            queue_capacity: 4,
            duration: 0.0,
            max_frames: 0,
            stats_interval: 10.0,
            http: String::new(),
            ready_timeout: 2.0,
            parts: Parts::default(),
        }
    }
}

impl RunConfig {
    /// Checks values that TOML types cannot, and the source's (the outputs are checked with
    /// the others, see [`super::Config::outputs`]).
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &'static str, message: String| Err(Error::invalid(what, message));
        self.parts.source.validate()?;
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
        Ok(())
    }
}

/// The UDP output the daemon sends to unless told otherwise.
pub const DEFAULT_UDP: &str = "127.0.0.1:3333";

/// What the `[run]` table's other keys configure: the source, and one output of each kind
/// (off while its address or path is empty).
#[derive(Debug, Clone, PartialEq)]
pub struct Parts {
    /// `source`, `size`, `replay_speed`, `loop`, `fps`, `reconnect_min_ms`,
    /// `reconnect_max_ms`.
    pub source: SourceConfig,
    /// `udp` (the address, [`DEFAULT_UDP`] by default), `udp_format`, `udp_payload`,
    /// `udp_rate` and `emit*`.
    pub udp: UdpSinkConfig,
    /// `tcp` (the address, off by default) and `tcp_format`, `tcp_max_clients`.
    pub tcp: TcpSinkConfig,
    /// `out` (the path, off by default) and `out_evt`.
    pub out: FileSinkConfig,
    /// `ros2` (the topic, off by default) and `ros2_KEY` (`ros2_domain_id`, `ros2_depth`, ...).
    pub ros2: Ros2SinkConfig,
}

impl Default for Parts {
    fn default() -> Self {
        Parts {
            source: SourceConfig::default(),
            udp: UdpSinkConfig {
                address: DEFAULT_UDP.into(),
                ..UdpSinkConfig::default()
            },
            tcp: TcpSinkConfig::default(),
            out: FileSinkConfig::default(),
            ros2: Ros2SinkConfig {
                topic: String::new(),
                ..Ros2SinkConfig::default()
            },
        }
    }
}

/// Which part a `[run]` key is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Source,
    Udp,
    Tcp,
    Out,
    Ros2,
}

impl Kind {
    const ALL: [Kind; 5] = [Kind::Source, Kind::Udp, Kind::Tcp, Kind::Out, Kind::Ros2];

    /// For an output: the key that names its address or path (and the prefix of its other
    /// keys), and the field that key fills. The source's keys are its fields' names.
    fn address(self) -> Option<(&'static str, &'static str)> {
        match self {
            Kind::Source => None,
            Kind::Udp => Some(("udp", "address")),
            Kind::Tcp => Some(("tcp", "address")),
            Kind::Out => Some(("out", "path")),
            Kind::Ros2 => Some(("ros2", "topic")),
        }
    }

    /// The part's fields.
    fn fields(self) -> &'static [&'static str] {
        match self {
            Kind::Source => crate::toml_doc::keys::<SourceConfig>(),
            Kind::Udp => crate::toml_doc::keys::<UdpSinkConfig>(),
            Kind::Tcp => crate::toml_doc::keys::<TcpSinkConfig>(),
            Kind::Out => crate::toml_doc::keys::<FileSinkConfig>(),
            Kind::Ros2 => crate::toml_doc::keys::<Ros2SinkConfig>(),
        }
    }

    /// The `[run]` key of one of its fields.
    fn run_key(self, field: &str) -> String {
        match self.address() {
            None => field.to_string(),
            Some((key, address)) if field == address => key.to_string(),
            Some(_) if self == Kind::Udp && field.starts_with("emit") => field.to_string(),
            Some((key, _)) => format!("{key}_{field}"),
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

impl Parts {
    /// The outputs that are on, UDP first, then TCP, then the file, then ROS 2.
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
        if !self.ros2.topic.is_empty() {
            sinks.push(SinkConfig::Ros2(self.ros2.clone()));
        }
        sinks
    }

    /// Every key the parts take, for error messages.
    fn all_keys() -> Vec<String> {
        Kind::ALL
            .into_iter()
            .flat_map(|kind| kind.fields().iter().map(move |f| kind.run_key(f)))
            .collect()
    }
}

/// The keys `[run]` does not know itself come here: each fills its part's configuration, and
/// a key that names no part's field is an error that names it.
impl<'de> Deserialize<'de> for Parts {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let given = BTreeMap::<String, toml::Value>::deserialize(d)?;
        let defaults = Parts::default();
        // An output's table starts with its default address (the UDP output's is on).
        let seed = |kind: Kind| {
            let mut table = toml::Table::new();
            let address = match kind {
                Kind::Source => return table,
                Kind::Udp => defaults.udp.address.clone(),
                Kind::Tcp => defaults.tcp.address.clone(),
                Kind::Out => defaults.out.path.clone(),
                Kind::Ros2 => defaults.ros2.topic.clone(),
            };
            if let Some((_, field)) = kind.address() {
                table.insert(field.into(), address.into());
            }
            table
        };
        let mut tables = Kind::ALL.map(seed);
        for (key, value) in given {
            let Some((kind, field)) = Kind::route(&key) else {
                let known = Parts::all_keys().join("`, `");
                return Err(D::Error::custom(format!(
                    "unknown field `{key}`, expected a key of the [run] table (config/v2ce.toml) or one of `{known}`"
                )));
            };
            tables[kind as usize].insert(field.into(), value);
        }
        let [source, udp, tcp, out, ros2] = tables;
        Ok(Parts {
            source: fill(Kind::Source, source)?,
            udp: fill(Kind::Udp, udp)?,
            tcp: fill(Kind::Tcp, tcp)?,
            out: fill(Kind::Out, out)?,
            ros2: fill(Kind::Ros2, ros2)?,
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
        let keys = Parts::all_keys();
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
            "source",
            "loop",
            "reconnect_max_ms",
        ] {
            assert!(keys.iter().any(|x| x == k), "{k} not in {keys:?}");
        }
        // No two parts share a key, and each key routes back to the part and field it was
        // made from.
        let mut unique = keys.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), keys.len(), "{keys:?}");
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
        let o = &c.run.parts;
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
