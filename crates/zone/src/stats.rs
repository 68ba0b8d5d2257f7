//! What a zone counts, for logs, `myriad sim --zones` and the Prometheus endpoint.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::Duration;

use crate::layout::ZoneId;

/// A zone's counters: gauges of the last tick and totals since it started.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ZoneStats {
    /// Ticks stepped.
    pub ticks: u64,
    /// Objects owned after the last tick.
    pub owned: usize,
    /// Ghosts stepped in the last tick (objects of neighbours, and objects just handed
    /// away, within reach).
    pub ghosts: usize,
    /// Object records received from neighbours, in all.
    pub ghosts_in: u64,
    /// Object records sent to neighbours, in all.
    pub ghosts_out: u64,
    /// Objects received as their new owner, in all.
    pub handoffs_in: u64,
    /// Objects handed to a neighbour, in all.
    pub handoffs_out: u64,
    /// Time spent waiting for neighbours' border states.
    pub wait: Duration,
    /// Time spent stepping (assembling the zone's world and the physics).
    pub step: Duration,
    /// Messages sent and received.
    pub messages: (u64, u64),
    /// Fabric payload bytes sent and received.
    pub bytes: (u64, u64),
    /// Messages rejected, by reason ([`crate::wire::WireError::label`], or `run`,
    /// `misrouted`, `stranger`, `stale`, `early`, `replayed`, `parts`).
    pub rejected: BTreeMap<&'static str, u64>,
}

impl ZoneStats {
    /// Messages rejected for every reason.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.values().sum()
    }

    /// The counters in Prometheus' text format, labelled with the zone.
    pub fn prometheus(&self, zone: ZoneId) -> String {
        let z = zone.0;
        let mut s = String::new();
        let mut metric = |name: &str, kind: &str, help: &str, value: String| {
            let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} {kind}\n{name}{{zone=\"{z}\"}} {value}");
        };
        metric("myriad_zone_ticks_total", "counter", "Ticks stepped.", self.ticks.to_string());
        metric("myriad_zone_owned_objects", "gauge", "Objects this zone owns.", self.owned.to_string());
        metric("myriad_zone_ghosts", "gauge", "Ghosts stepped in the last tick.", self.ghosts.to_string());
        metric("myriad_zone_ghosts_in_total", "counter", "Object records received.", self.ghosts_in.to_string());
        metric("myriad_zone_ghosts_out_total", "counter", "Object records sent.", self.ghosts_out.to_string());
        metric("myriad_zone_handoffs_in_total", "counter", "Objects received as owner.", self.handoffs_in.to_string());
        metric("myriad_zone_handoffs_out_total", "counter", "Objects handed away.", self.handoffs_out.to_string());
        metric(
            "myriad_zone_wait_seconds_total",
            "counter",
            "Time waiting for neighbours.",
            self.wait.as_secs_f64().to_string(),
        );
        metric("myriad_zone_step_seconds_total", "counter", "Time stepping.", self.step.as_secs_f64().to_string());
        metric("myriad_zone_fabric_sent_bytes_total", "counter", "Fabric bytes sent.", self.bytes.0.to_string());
        metric(
            "myriad_zone_fabric_received_bytes_total",
            "counter",
            "Fabric bytes received.",
            self.bytes.1.to_string(),
        );
        let _ = writeln!(
            s,
            "# HELP myriad_zone_rejected_total Fabric messages rejected, by reason.\n# TYPE myriad_zone_rejected_total counter"
        );
        for (reason, n) in &self.rejected {
            let _ = writeln!(s, "myriad_zone_rejected_total{{zone=\"{z}\",reason=\"{reason}\"}} {n}");
        }
        s
    }
}
