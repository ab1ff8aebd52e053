//! `v2ce listen`: a receiver of what the daemon sends.

use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The flags of `v2ce listen`.
#[derive(Args)]
pub struct ListenArgs {
    /// Bind this HOST:PORT for UDP datagrams (port 0: any; the address is printed).
    #[arg(long, conflicts_with = "tcp")]
    pub(crate) udp: Option<String>,
    /// The datagram format: spif, spif_timestamped, t64_x16_y16_on8, t32_x16_y15_on1.
    #[arg(long, default_value = "spif")]
    pub(crate) format: String,
    /// Connect to a daemon's TCP stream at HOST:PORT (AEDAT 4.0 or RAW EVT 2.0/3.0).
    #[arg(long)]
    pub(crate) tcp: Option<String>,
    /// Subscribe to a ROS 2 topic of event_camera_msgs/msg/EventPacket (evt3) over DDS, on
    /// ROS_DOMAIN_ID (else 0).
    #[arg(long, value_name = "TOPIC", conflicts_with_all = ["udp", "tcp"])]
    pub(crate) ros2: Option<String>,
    /// Write the events to this file (.aedat4, .raw, .csv, .npz, .h5); plain spif events get their
    /// arrival time.
    #[arg(short, long)]
    pub(crate) out: Option<PathBuf>,
    /// Sensor size for the file (UDP formats carry none).
    #[arg(long, value_name = "WxH", default_value = "640x480")]
    pub(crate) size: String,
    /// Stop after this many seconds.
    #[arg(long)]
    pub(crate) duration: Option<f64>,
    /// Stop when nothing arrived for this many seconds after the first arrival.
    #[arg(long, default_value_t = 2.0)]
    pub(crate) idle: f64,
    /// Stop after this many events.
    #[arg(long)]
    pub(crate) max_events: Option<u64>,
    /// Kernel receive buffer for UDP, bytes (0: the system's default, about 200 KB, which holds
    /// some 50 ms of a 300,000 events/s stream; the kernel caps the request at
    /// net.core.rmem_max).
    #[arg(long, default_value_t = 4 << 20)]
    pub(crate) recv_buffer: usize,
    /// Realtime priority of the receiving thread, 1-99, when the process may (root or
    /// CAP_SYS_NICE; 0: normal scheduling): on busy cores a receiver at normal priority can
    /// wait milliseconds, and a default receive buffer holds about one at a million events/s.
    #[arg(long, default_value_t = 5)]
    pub(crate) priority: u8,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    pub(crate) json: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// Runs `v2ce listen`.
pub fn listen(args: ListenArgs) -> Result<()> {
    if let Some(out) = &args.out {
        crate::output::check(out, &[], args.force)?;
    }
    use crate::listen::{Listen, ListenOptions};
    let seconds = |what: &'static str, v: f64| crate::limits::seconds(what, v, true);
    let listen = match (&args.udp, &args.tcp) {
        _ if args.ros2.is_some() => Listen::Ros2 {
            topic: args.ros2.clone().unwrap_or_default(),
            domain: crate::ros2::dds::default_domain()?,
        },
        (_, Some(connect)) => Listen::Tcp {
            connect: connect.clone(),
        },
        (Some(bind), None) => Listen::Udp {
            bind: bind.clone(),
            format: crate::format::datagram::UdpFormat::from_name(&args.format)?,
        },
        (None, None) => Listen::Udp {
            bind: "127.0.0.1:3333".into(),
            format: crate::format::datagram::UdpFormat::from_name(&args.format)?,
        },
    };
    let options = ListenOptions {
        listen,
        out: args.out.clone(),
        size: parse_size(&args.size)?,
        duration: args
            .duration
            .map(|d| seconds("--duration", d))
            .transpose()?,
        idle: seconds("--idle", args.idle)?,
        max_events: args.max_events,
        recv_buffer: args.recv_buffer,
        priority: args.priority,
    };
    let stop = crate::daemon::stop_on_signals()?;
    let report = crate::listen::listen(&options, &stop, |at| {
        println!("listening on {at}");
        let _ = std::io::stdout().flush();
    })?;
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        println!(
            "{} events in {} messages ({} ragged, {} refused for times out of range, {} for \
             times going back, {} for pixels off the sensor) over {:.2} s: {:.0} events/s; \
             largest gap {:.1} ms; at most {} messages in one ms{}",
            report.events,
            report.messages,
            report.ragged,
            report.out_of_range,
            report.out_of_order,
            report.off_sensor,
            report.seconds,
            report.events_per_s,
            report.largest_gap_ms,
            report.max_messages_per_ms,
            report
                .arrival_spread
                .map(|l| format!(
                    "; arrival minus event time (less its minimum) p50 {:.2} ms p99 {:.2} ms \
                     max {:.2} ms",
                    l.p50_ms, l.p99_ms, l.max_ms
                ))
                .unwrap_or_default()
        );
        if args.ros2.is_some() {
            println!(
                "ros2: {} packets malformed (refused), {} missing from the seq numbering, the \
                 DDS transport replaced {} times",
                report.malformed, report.seq_gaps, report.transport_restarts
            );
        }
    }
    let udp = args.ros2.is_none() && (args.udp.is_some() || args.tcp.is_none());
    if udp && !report.realtime && args.priority > 0 {
        eprintln!(
            "v2ce listen: the receiver ran at normal priority (realtime {} refused: needs root or \
             CAP_SYS_NICE); on busy cores it may lose datagrams",
            args.priority
        );
    }
    Ok(())
}
