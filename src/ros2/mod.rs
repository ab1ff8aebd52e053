//! ROS 2 without a ROS installation: the messages in CDR ([`cdr`], [`msg`]) and the DDS
//! participant that publishes and subscribes to them ([`dds`], pure Rust through `rustdds`), run
//! in a process of its own under a memory cap ([`host`]).
//! The event packets' EVT 3.0 payloads are [`crate::format::event_packet`]'s; the rosbag2
//! container is [`crate::format::mcap`].

pub mod cdr;
pub mod dds;
pub mod host;
pub mod msg;
