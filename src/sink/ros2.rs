//! Events published on a ROS 2 topic as `event_camera_msgs/msg/EventPacket` (`evt3`), over
//! DDS from pure Rust ([`crate::ros2::dds`], in a process of its own under a memory cap:
//! [`crate::ros2::host`]), as the Prophesee and iniVation drivers publish them: a robot's nodes
//! subscribe to v2ce as to a real event camera.
//!
//! Each packet holds at most `packet_us` of events and is decodable alone
//! ([`crate::format::event_packet`]); a batch's last packet is closed with the batch, so no
//! packet waits for the next frame. Packets leave at their own time as the UDP sink's
//! datagrams do ([`super::emit`]): each when its last event is due, `emit_delay_ms` behind
//! the frames (or as fast as they come, `emit = "asap"`). The writer is reliable with a
//! keep-last history of `depth` packets by default (a subscriber that keeps up loses
//! nothing; one that falls `depth` packets behind loses the oldest), or best effort. At the
//! end the sink waits up to `linger_ms` for reliable subscribers to acknowledge every packet.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Deserialize;

use super::emit::EmitClock;
use super::udp::EmitMode;
use super::{ClosedBy, Sink, SinkContext, SinkStats};
use crate::error::{Error, Result};
use crate::event::Event;
use crate::format::event_packet::{Packet, Packetizer};
use crate::ros2::dds::{self, Qos};
use crate::ros2::host::Publication;
use crate::ros2::msg;

/// How long a reason for lost packets goes unsaid after it was said.
const WARN_AGAIN: Duration = Duration::from_secs(10);

/// How long the first packet waits after `wait_subscribers` were matched.
const SETTLE: Duration = Duration::from_secs(2);

/// The topic events are published on unless told otherwise (the one a bag's packets are on).
pub use crate::format::mcap::DEFAULT_TOPIC;

/// How a ROS 2 writer or reader delivers samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Reliability {
    /// Lost samples are sent again while the history holds them (ROS 2's default).
    #[default]
    Reliable,
    /// Each sample once (ROS 2's sensor-data profile).
    BestEffort,
}

/// A `[[sink]]` table of `type = "ros2"` (the `[run]` key `ros2` names the topic, `ros2_KEY`
/// the others; `--ros2 TOPIC` on `run`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Ros2SinkConfig {
    /// The ROS 2 topic.
    pub topic: String,
    /// The DDS domain (ROS 2's `ROS_DOMAIN_ID`); unset: `ROS_DOMAIN_ID`, else 0.
    pub domain_id: Option<u32>,
    /// `header.frame_id` of every packet.
    pub frame_id: String,
    /// The longest span of one packet, us.
    pub packet_us: u32,
    /// `reliable` or `best_effort`.
    pub reliability: Reliability,
    /// Packets the writer keeps for resending and slow subscribers (keep-last depth).
    pub depth: u32,
    /// When packets leave: "event-time" (each when its last event is due) or "asap".
    pub emit: EmitMode,
    /// How far behind the frames packets leave at event time, milliseconds.
    pub emit_delay_ms: f64,
    /// Hold the first packet until this many subscribers are matched (0: publish at once).
    pub wait_subscribers: u32,
    /// At the end, how long to wait for reliable subscribers to acknowledge, milliseconds.
    pub linger_ms: u64,
}

impl Default for Ros2SinkConfig {
    fn default() -> Self {
        Ros2SinkConfig {
            topic: DEFAULT_TOPIC.into(),
            domain_id: None,
            frame_id: crate::format::mcap::DEFAULT_FRAME_ID.into(),
            packet_us: crate::format::mcap::PACKET_US as u32,
            reliability: Reliability::Reliable,
            depth: 1000,
            emit: EmitMode::EventTime,
            emit_delay_ms: 100.0,
            wait_subscribers: 0,
            linger_ms: 2000,
        }
    }
}

impl Ros2SinkConfig {
    /// Checks the values that TOML types cannot.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::invalid("ROS 2 sink", m));
        if let Err(m) = msg::dds_topic(&self.topic) {
            return bad(m);
        }
        if let Some(d) = self.domain_id {
            dds::check_domain("ROS 2 sink domain_id", d)?;
        }
        if self.frame_id.len() > msg::MAX_STRING {
            return bad(format!("frame_id longer than {} bytes", msg::MAX_STRING));
        }
        if !(1..=1_000_000).contains(&self.packet_us) {
            return bad(format!("packet_us {} (1 to 1000000)", self.packet_us));
        }
        if !(1..=100_000).contains(&self.depth) {
            return bad(format!("depth {} (1 to 100000)", self.depth));
        }
        if !(self.emit_delay_ms.is_finite() && (0.0..=60_000.0).contains(&self.emit_delay_ms)) {
            return bad(format!(
                "emit_delay_ms {} (must be 0 to 60000)",
                self.emit_delay_ms
            ));
        }
        if self.linger_ms > 600_000 {
            return bad(format!("linger_ms {} (at most 600000)", self.linger_ms));
        }
        Ok(())
    }

    /// The QoS of the writer.
    pub fn qos(&self) -> Qos {
        Qos {
            reliable: self.reliability == Reliability::Reliable,
            depth: self.depth,
        }
    }

    /// Joins the domain and opens the writer.
    pub fn build(&self, context: &SinkContext) -> Result<Box<dyn Sink>> {
        let domain = match self.domain_id {
            Some(d) => dds::check_domain("ROS 2 sink domain_id", d)?,
            None => dds::default_domain()?,
        };
        let publication = Publication::open(domain, &self.topic, msg::EVENT_PACKET, self.qos())?;
        let delay = Duration::from_secs_f64(self.emit_delay_ms / 1000.0);
        Ok(Box::new(Ros2Sink {
            packets: Packetizer::new(
                context.width,
                context.height,
                &self.frame_id,
                self.packet_us as i64,
            )?,
            clock: (self.emit == EmitMode::EventTime).then(|| EmitClock::new(delay, context.speed)),
            config: self.clone(),
            domain,
            publication,
            ready: Vec::new(),
            stats: SinkStats::default(),
            stop: Arc::new(AtomicBool::new(false)),
            waited: self.wait_subscribers == 0,
            warned: None,
        }))
    }
}

/// The sink: a DDS writer of EventPacket messages.
pub struct Ros2Sink {
    config: Ros2SinkConfig,
    domain: u16,
    packets: Packetizer,
    clock: Option<EmitClock>,
    publication: Publication,
    ready: Vec<Packet>,
    stats: SinkStats,
    stop: Arc<AtomicBool>,
    waited: bool,
    /// The last reason a packet was lost, and when it was said.
    warned: Option<(String, Instant)>,
}

impl Ros2Sink {
    /// Sleeps until `until` in short steps; false when the run stops first.
    fn sleep_until(&self, until: Instant) -> bool {
        loop {
            if self.stop.load(Ordering::Relaxed) {
                return false;
            }
            let now = Instant::now();
            if now >= until {
                return true;
            }
            std::thread::sleep((until - now).min(Duration::from_millis(20)));
        }
    }

    fn wait_for_subscribers(&mut self) {
        if self.waited {
            return;
        }
        let want = self.config.wait_subscribers as usize;
        let mut said = false;
        while self.publication.subscribers() < want && !self.stop.load(Ordering::Relaxed) {
            if !said {
                tracing::info!(
                    "ros2 {}: waiting for {want} subscriber(s) before the first packet",
                    self.config.topic
                );
                said = true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        // The writer sees a subscriber before the subscriber has seen the writer (discovery
        // runs both ways); a volatile subscriber takes only what is sent after its side
        // matched, so the first packet waits a moment more.
        self.sleep_until(Instant::now() + SETTLE);
        self.waited = true;
    }

    fn publish_ready(&mut self) -> Result<()> {
        if self.ready.is_empty() {
            return Ok(());
        }
        self.wait_for_subscribers();
        let ready = std::mem::take(&mut self.ready);
        let mut first_error = None;
        for p in ready {
            if let Some(clock) = self.clock.as_mut() {
                let now = Instant::now();
                if let Some(due) = clock.due_at(p.last_t, now) {
                    if due > now && !self.sleep_until(due) {
                        // Stopping: what is left goes at once.
                        self.clock = None;
                    } else if now > due + Duration::from_millis(1) {
                        self.stats.events_late += p.events as u64;
                    }
                }
            }
            let bytes = p.msg.to_cdr();
            let n = bytes.len() as u64;
            match self.publication.send(&bytes) {
                Ok(()) => {
                    self.stats.events_sent += p.events as u64;
                    self.stats.messages_sent += 1;
                    self.stats.bytes_sent += n;
                }
                Err(e) => {
                    self.stats.events_dropped += p.events as u64;
                    self.stats.messages_dropped += 1;
                    first_error.get_or_insert(e);
                }
            }
        }
        if let Some(c) = &self.clock {
            self.stats.reanchors = c.reanchors;
        }
        if let Some(e) = first_error {
            // A writer that could not take a packet (its subscribers' history full for longer
            // than its blocking time, its transport being replaced) loses it, counted; the run
            // goes on. The same reason is said again after WARN_AGAIN at most.
            let e = e.to_string();
            let now = Instant::now();
            let again = self
                .warned
                .as_ref()
                .is_none_or(|(said, at)| *said != e || now.duration_since(*at) >= WARN_AGAIN);
            if again {
                tracing::warn!(
                    "ros2 {}: {e} ({} packets lost so far)",
                    self.config.topic,
                    self.stats.messages_dropped
                );
                self.warned = Some((e, now));
            }
        }
        Ok(())
    }
}

impl Sink for Ros2Sink {
    fn describe(&self) -> String {
        format!(
            "ros2 {} (event_camera_msgs/msg/EventPacket, evt3, domain {}, {})",
            self.config.topic,
            self.domain,
            match self.config.reliability {
                Reliability::Reliable => format!("reliable, depth {}", self.config.depth),
                Reliability::BestEffort => "best effort".into(),
            }
        )
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.stats.events_in += events.len() as u64;
        self.packets.push(events, &mut self.ready)?;
        self.packets.close(&mut self.ready);
        self.publish_ready()
    }

    fn send_closed(&mut self, events: &[Event], closed_by: ClosedBy) -> Result<()> {
        if let Some(c) = self.clock.as_mut() {
            c.anchor(closed_by.t, closed_by.captured);
        }
        self.send(events)
    }

    fn holds_back(&self) -> Duration {
        self.clock.as_ref().map_or(Duration::ZERO, |c| c.delay())
    }

    fn finish(&mut self) -> Result<()> {
        self.packets.close(&mut self.ready);
        self.publish_ready()?;
        if self.config.reliability == Reliability::Reliable
            && self.stats.messages_sent > 0
            && self.publication.subscribers() > 0
            && !self
                .publication
                .wait_acknowledged(Duration::from_millis(self.config.linger_ms))
        {
            tracing::warn!(
                "ros2 {}: not every subscriber acknowledged the last packets within {} ms",
                self.config.topic,
                self.config.linger_ms
            );
        }
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        SinkStats {
            clients: self.publication.matched() as u64,
            ..self.stats
        }
    }

    fn stop_waiting_on(&mut self, flag: Arc<AtomicBool>) {
        self.stop = flag;
    }
}
