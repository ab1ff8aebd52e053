//! ROS 2 topics over DDS (RTPS, the wire protocol of ROS 2's default middlewares) from pure
//! Rust, through `rustdds`: a participant on a domain, a publication or a subscription of raw
//! CDR messages ([`super::msg`] writes and reads them) under ROS 2's names (`rt/` topics,
//! `pkg::msg::dds_::Type_` types).
//!
//! `rustdds` was chosen by test against Cyclone DDS (the DDS of `rmw_cyclonedds`): it
//! publishes to and subscribes from it on loopback with default discovery, builds without a C
//! library, and leaves the message bytes to us, so the CDR is written and read once, bounded
//! ([`super::cdr`]), for DDS and rosbag2 alike.
//!
//! This layer runs in the DDS transport's own process ([`super::host`]), never in the daemon:
//! the crate sizes a fragmented sample's buffer from what a peer declares.

use std::time::{Duration, Instant};

use bytes::Bytes;
use rustdds::no_key::{
    DataReader, DataWriter, Decode, DefaultDecoder, DeserializerAdapter, SerializerAdapter,
};
use rustdds::policy::{Durability, History, Reliability};
use rustdds::{
    DomainParticipant, QosPolicies, QosPolicyBuilder, RepresentationIdentifier, TopicKind,
};

use crate::error::{Error, Result};

/// The DDS domain of `ROS_DOMAIN_ID`, else 0; a value that is not a domain (0 to 232) is an
/// error.
pub fn default_domain() -> Result<u16> {
    match std::env::var("ROS_DOMAIN_ID") {
        Ok(v) if !v.trim().is_empty() => v
            .trim()
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= 232)
            .ok_or_else(|| Error::invalid("ROS_DOMAIN_ID", format!("'{v}' (expected 0 to 232)"))),
        _ => Ok(0),
    }
}

/// Checks a domain id (0 to 232, as ROS 2 allows).
pub fn check_domain(what: &'static str, domain: u32) -> Result<u16> {
    u16::try_from(domain)
        .ok()
        .filter(|d| *d <= 232)
        .ok_or_else(|| Error::invalid(what, format!("{domain} (expected 0 to 232)")))
}

/// Delivery of a topic's messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    /// Reliable (lost samples resent while the history holds them) or best effort.
    pub reliable: bool,
    /// Samples kept for resending and for a slow reader (keep-last depth).
    pub depth: u32,
}

impl Qos {
    fn policies(self) -> QosPolicies {
        let reliability = if self.reliable {
            Reliability::Reliable {
                max_blocking_time: rustdds::Duration::from_millis(100),
            }
        } else {
            Reliability::BestEffort
        };
        QosPolicyBuilder::new()
            .reliability(reliability)
            .durability(Durability::Volatile)
            .history(History::KeepLast {
                depth: self.depth.clamp(1, i32::MAX as u32) as i32,
            })
            .build()
    }
}

fn dds_error(what: &str, e: impl std::fmt::Debug) -> Error {
    Error::invalid("ROS 2", format!("{what}: {e:?}"))
}

/// Raw CDR messages as DDS samples: the bytes after the 4-byte encapsulation header.
struct Raw;

#[derive(Debug)]
struct Never;

impl std::fmt::Display for Never {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("never")
    }
}

impl std::error::Error for Never {}

impl SerializerAdapter<Vec<u8>> for Raw {
    type Error = Never;

    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }

    /// The message after its header, padded with zeros to a multiple of 4 bytes: a sample
    /// over 1 KiB leaves in fragments of 1 KiB, and Cyclone DDS refuses a last fragment whose
    /// length is not a multiple of 4 as malformed (measured: a reliable stream then stalls on
    /// the sample it can never complete). Readers ignore bytes after the last field.
    fn to_bytes(value: &Vec<u8>) -> std::result::Result<Bytes, Never> {
        let body = value.get(4..).unwrap_or_default();
        let mut v = Vec::with_capacity(body.len() + 3);
        v.extend_from_slice(body);
        v.resize(body.len().next_multiple_of(4), 0);
        Ok(Bytes::from(v))
    }
}

/// A sample as received: the whole CDR message, its header rebuilt from the representation.
#[derive(Clone, Copy)]
struct RawDecoder;

impl Decode<Vec<u8>> for RawDecoder {
    type Error = Never;

    fn decode_bytes(
        self,
        input: &[u8],
        encoding: RepresentationIdentifier,
    ) -> std::result::Result<Vec<u8>, Never> {
        let mut v = Vec::with_capacity(input.len() + 4);
        let little = encoding == RepresentationIdentifier::CDR_LE;
        v.extend_from_slice(&[0, little as u8, 0, 0]);
        v.extend_from_slice(input);
        Ok(v)
    }
}

impl DeserializerAdapter<Vec<u8>> for Raw {
    type Error = Never;
    type Decoded = Vec<u8>;

    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &[
            RepresentationIdentifier::CDR_LE,
            RepresentationIdentifier::CDR_BE,
        ]
    }

    fn transform_decoded(decoded: Vec<u8>) -> Vec<u8> {
        decoded
    }
}

impl DefaultDecoder<Vec<u8>> for Raw {
    type Decoder = RawDecoder;
    const DECODER: RawDecoder = RawDecoder;
}

/// One DDS participant on a domain (what a ROS 2 node has).
pub struct Participant {
    inner: DomainParticipant,
    domain: u16,
}

impl Participant {
    /// Joins `domain`.
    pub fn new(domain: u16) -> Result<Self> {
        let inner = DomainParticipant::new(domain)
            .map_err(|e| dds_error(&format!("joining DDS domain {domain}"), e))?;
        Ok(Participant { inner, domain })
    }

    /// The domain joined.
    pub fn domain(&self) -> u16 {
        self.domain
    }

    fn topic(&self, topic: &str, ros_type: &str, qos: &QosPolicies) -> Result<rustdds::Topic> {
        let name = super::msg::dds_topic(topic).map_err(|m| Error::invalid("ROS 2 topic", m))?;
        self.inner
            .create_topic(
                name,
                super::msg::dds_type_name(ros_type),
                qos,
                TopicKind::NoKey,
            )
            .map_err(|e| dds_error(&format!("topic {topic}"), e))
    }

    /// A publication of `ros_type` messages on the ROS 2 `topic`.
    pub fn publish(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<Publication> {
        let policies = qos.policies();
        let t = self.topic(topic, ros_type, &policies)?;
        let publisher = self
            .inner
            .create_publisher(&policies)
            .map_err(|e| dds_error("publisher", e))?;
        let writer = publisher
            .create_datawriter_no_key::<Vec<u8>, Raw>(&t, None)
            .map_err(|e| dds_error(&format!("writer on {topic}"), e))?;
        Ok(Publication {
            writer,
            matched: std::cell::Cell::new(0),
        })
    }

    /// A subscription to `ros_type` messages on the ROS 2 `topic`.
    pub fn subscribe(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<Subscription> {
        let policies = qos.policies();
        let t = self.topic(topic, ros_type, &policies)?;
        let subscriber = self
            .inner
            .create_subscriber(&policies)
            .map_err(|e| dds_error("subscriber", e))?;
        let reader = subscriber
            .create_datareader_no_key::<Vec<u8>, Raw>(&t, None)
            .map_err(|e| dds_error(&format!("reader on {topic}"), e))?;
        Ok(Subscription { reader })
    }
}

/// A DDS writer of one topic.
pub struct Publication {
    writer: DataWriter<Vec<u8>, Raw>,
    /// Subscribers matched, as the writer's status events last said.
    matched: std::cell::Cell<usize>,
}

impl Publication {
    /// Publishes one CDR message (as [`super::msg`] writes it). A reliable writer whose
    /// subscribers' history is full waits for them up to its blocking time, then errs.
    pub fn send(&self, message: Vec<u8>) -> Result<()> {
        self.writer
            .write(message, None)
            .map_err(|e| dds_error("publishing", e.to_string()))
    }

    /// The subscribers matched so far.
    pub fn subscribers(&self) -> usize {
        use rustdds::StatusEvented;
        while let Some(status) = self.writer.try_recv_status() {
            if let rustdds::DataWriterStatus::PublicationMatched { current, .. } = status {
                self.matched.set(current.count().max(0) as usize);
            }
        }
        self.matched.get()
    }

    /// Waits until every reliable subscriber has acknowledged what was sent, at most `wait`;
    /// whether they all did.
    pub fn wait_acknowledged(&self, wait: Duration) -> bool {
        matches!(self.writer.wait_for_acknowledgments(wait), Ok(true))
    }
}

/// A DDS reader of one topic.
pub struct Subscription {
    reader: DataReader<Vec<u8>, Raw>,
}

/// How often a waiting subscription looks for a sample.
const POLL: Duration = Duration::from_millis(1);

impl Subscription {
    /// The next message (a whole CDR message), waiting at most `timeout`; `None` when none came.
    pub fn next(&mut self, timeout: Duration) -> Result<Option<Vec<u8>>> {
        let until = Instant::now() + timeout;
        loop {
            match self.reader.take_next_sample() {
                Ok(Some(s)) => return Ok(Some(s.into_value())),
                Ok(None) => {}
                Err(e) => return Err(dds_error("reading", e)),
            }
            let now = Instant::now();
            if now >= until {
                return Ok(None);
            }
            std::thread::sleep(POLL.min(until - now));
        }
    }
}
