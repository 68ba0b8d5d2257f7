//! What a zone counts, for logs, `myriad sim --zones` and the Prometheus endpoint.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::layout::ZoneId;

/// A zone's counters: gauges of the last tick and totals since it started.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ZoneStats {
    /// Ticks stepped.
    pub ticks: u64,
    /// The world's tick the gauges describe: the tick the last step reached, or the one
    /// the zone started (or resumed) at. Zones' gauges add up only at one tick: a
    /// hand-off leaves its old owner's count at tick t and joins its new owner's in
    /// that zone's own step of t, so two zones read a tick apart count an object in
    /// flight twice or not at all.
    pub tick: u64,
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
    /// Players' objects adopted from gateways' joins, in all.
    pub joins: u64,
    /// Players' objects removed by gateways' leaves, in all.
    pub leaves: u64,
    /// Players' objects removed because their gateway died or restarted, in all.
    pub orphans: u64,
    /// Layouts followed after the first (cuts moved), in all.
    pub cut_moves: u64,
    /// Cut moves from the fabric refused ([`crate::rebalance::live::CutRefused`]; each is
    /// also in `rejected` under its reason), in all.
    pub cut_moves_refused: u64,
    /// Time spent waiting for neighbours' border states.
    pub wait: Duration,
    /// Time spent stepping: assembling the zone's world, the physics, keeping the owned
    /// results.
    pub step: Duration,
    /// The physics' share of `step` (the backend's step alone).
    pub physics: Duration,
    /// Time spent choosing, encoding and sending border states.
    pub send: Duration,
    /// Time spent after the step on what live gateways take (the states of the whole
    /// mirror, or each subscriber's view: tracking changes, bucketing, encoding,
    /// sending). At a million objects this was most of a zone's tick.
    pub publish: Duration,
    /// Of `step`, the pass over the positions that finds the slots near the edges.
    pub scan: Duration,
    /// Of `step`, making the world the one to step ([`crate::resident::ResidentWorld::apply`],
    /// the scan excluded).
    pub edit: Duration,
    /// Of `edit`, moving the slots (removals and insertions that keep ids ascending).
    pub moving: Duration,
    /// Objects inserted into the zone's world and removed from it (ghosts and hand-offs
    /// arriving and leaving, joins, leaves), in all.
    pub slots_inserted: u64,
    /// See `slots_inserted`.
    pub slots_removed: u64,
    /// Ticks whose edit inserted or removed an object: ticks that moved slots.
    pub moving_ticks: u64,
    /// Of `physics`, the backend's host side as its [`myriad_physics::Stage::Upload`]
    /// counts it: copies to the device and, on `cuda`, of the new state back into the
    /// world, plus its binding and launching (0 on the CPU).
    pub copies: Duration,
    /// Messages sent and received.
    pub messages: (u64, u64),
    /// Fabric payload bytes sent and received.
    pub bytes: (u64, u64),
    /// Of the bytes sent, those of the states published for gateways (live zones): what
    /// every gateway receives from this zone, the whole mirror today.
    pub states_bytes: u64,
    /// Per subscribed gateway: the bytes and object records of the views sent to it, in
    /// all (states by interest).
    pub views: BTreeMap<u16, (u64, u64)>,
    /// Gateways subscribed after the last tick.
    pub subscribers: usize,
    /// Messages rejected, by reason ([`crate::wire::WireError::label`], or `run`,
    /// `misrouted`, `stranger`, `stale`, `early`, `replayed`, `parts`, a refused cut
    /// move's [`crate::rebalance::live::CutRefused::label`], or a refused
    /// subscription's [`crate::views::SubscriptionError::label`]).
    pub rejected: BTreeMap<&'static str, u64>,
}

impl ZoneStats {
    /// Messages rejected for every reason.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.values().sum()
    }

    /// Publishes the counters through the `metrics` facade, labelled with the zone
    /// (a process that installs a Prometheus exporter serves them on `/metrics`).
    pub fn export(&self, zone: ZoneId) {
        let z = zone.0.to_string();
        let counter = |name: &'static str, v: u64| metrics::counter!(name, "zone" => z.clone()).absolute(v);
        counter("myriad_zone_ticks_total", self.ticks);
        counter("myriad_zone_ghosts_in_total", self.ghosts_in);
        counter("myriad_zone_ghosts_out_total", self.ghosts_out);
        counter("myriad_zone_handoffs_in_total", self.handoffs_in);
        counter("myriad_zone_handoffs_out_total", self.handoffs_out);
        counter("myriad_zone_player_joins_total", self.joins);
        counter("myriad_zone_player_leaves_total", self.leaves);
        counter("myriad_zone_player_orphans_total", self.orphans);
        counter("myriad_zone_cut_moves_total", self.cut_moves);
        counter("myriad_zone_cut_moves_refused_total", self.cut_moves_refused);
        counter("myriad_zone_fabric_sent_bytes_total", self.bytes.0);
        counter("myriad_zone_fabric_received_bytes_total", self.bytes.1);
        counter("myriad_zone_states_sent_bytes_total", self.states_bytes);
        counter("myriad_zone_messages_sent_total", self.messages.0);
        counter("myriad_zone_messages_received_total", self.messages.1);
        for (g, (bytes, objects)) in &self.views {
            let labels = [("zone", z.clone()), ("gateway", g.to_string())];
            metrics::counter!("myriad_zone_view_sent_bytes_total", &labels).absolute(*bytes);
            metrics::counter!("myriad_zone_view_objects_total", &labels).absolute(*objects);
        }
        metrics::gauge!("myriad_zone_subscribers", "zone" => z.clone()).set(self.subscribers as f64);
        metrics::gauge!("myriad_zone_owned_objects", "zone" => z.clone()).set(self.owned as f64);
        metrics::gauge!("myriad_zone_ghosts", "zone" => z.clone()).set(self.ghosts as f64);
        metrics::gauge!("myriad_zone_wait_seconds_total", "zone" => z.clone()).set(self.wait.as_secs_f64());
        metrics::gauge!("myriad_zone_step_seconds_total", "zone" => z.clone()).set(self.step.as_secs_f64());
        metrics::gauge!("myriad_zone_physics_seconds_total", "zone" => z.clone()).set(self.physics.as_secs_f64());
        metrics::gauge!("myriad_zone_send_seconds_total", "zone" => z.clone()).set(self.send.as_secs_f64());
        metrics::gauge!("myriad_zone_publish_seconds_total", "zone" => z.clone()).set(self.publish.as_secs_f64());
        for (reason, n) in &self.rejected {
            metrics::counter!("myriad_zone_rejected_total", "zone" => z.clone(), "reason" => *reason).absolute(*n);
        }
        // Last: a scrape that catches this export half done shows the tick before with
        // some newer values, and a reader that scrapes twice sees the tick move on.
        metrics::gauge!("myriad_zone_tick", "zone" => z).set(self.tick as f64);
    }
}
