//! What the tick publishes for the admin API: the players online and the map's NPC
//! density, taken on the tick thread only while someone asks (a request in the last
//! [`WANTED_FOR`]) and at most every [`SNAPSHOT_EVERY`], then handed over behind an
//! `Arc` with a `try_lock`: the tick never waits on the admin. A busy lock (a request
//! cloning the `Arc` at that instant) only delays the snapshot to the next tick.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use myriad_core::{ObjectKind, World};
use myriad_physics::{Backend, ZoneCuts};

use super::AdminShared;
use crate::session::Sessions;

/// How long after a request the tick keeps taking snapshots.
pub(crate) const WANTED_FOR: Duration = Duration::from_secs(5);
/// Least time between two snapshots.
pub(crate) const SNAPSHOT_EVERY: Duration = Duration::from_millis(200);
/// Cells on each side of the density grid the tick counts (the API's `cells` at most).
pub(crate) const FINE_CELLS: usize = 256;

/// One player online, as the admin API shows it.
#[derive(Debug, Clone)]
pub(crate) struct PlayerRow {
    pub account: String,
    pub user_id: i64,
    pub entity: u64,
    /// Where its datagrams come from (`None` before its first one).
    pub addr: Option<SocketAddr>,
    pub connected_since: SystemTime,
    pub position: [f32; 3],
    /// Update bytes sent to it per second since the previous snapshot.
    pub bytes_per_s: f64,
}

/// The tick's picture of the world for the admin API.
#[derive(Debug, Clone)]
pub(crate) struct Snapshot {
    /// When it was taken.
    pub taken: Instant,
    /// The tick it was taken at.
    pub tick: u64,
    pub players: Vec<PlayerRow>,
    /// The world's extent on the ground: min x, min z, max x, max z.
    pub bounds: [f32; 4],
    /// NPCs per cell of a [`FINE_CELLS`]² grid over `bounds`, row-major (z rows, x
    /// columns).
    pub density: Vec<u32>,
    /// The zone cuts, on a gateway ([`Backend::zone_cuts`]).
    pub cuts: Option<ZoneCuts>,
}

/// The grid cell of coordinate `v` in `[min, max)` split into `cells` (edges clamp in).
pub(crate) fn cell_of(v: f32, min: f32, max: f32, cells: usize) -> usize {
    let t = ((v - min) / (max - min).max(f32::EPSILON)).clamp(0.0, 1.0);
    ((t * cells as f32) as usize).min(cells - 1)
}

impl Snapshot {
    /// Takes a snapshot of `sessions` in `world` (split by `cuts`, on a gateway); each
    /// player's byte rate is over the time since its last snapshot (or since it joined).
    pub(crate) fn take(sessions: &mut Sessions, world: &World, cuts: Option<ZoneCuts>, now: Instant) -> Snapshot {
        let b = world.bounds;
        let bounds = [b.min.x, b.min.z, b.max.x, b.max.z];
        let mut density = vec![0u32; FINE_CELLS * FINE_CELLS];
        let d = &world.dynamics;
        for (pos, kind) in d.positions().iter().zip(d.kinds()) {
            if *kind == ObjectKind::Npc {
                let x = cell_of(pos.x, bounds[0], bounds[2], FINE_CELLS);
                let z = cell_of(pos.z, bounds[1], bounds[3], FINE_CELLS);
                density[z * FINE_CELLS + x] += 1;
            }
        }
        let players = sessions
            .iter_mut()
            .map(|p| {
                let (mark_bytes, mark_at) = p.rate_mark;
                let secs = now.saturating_duration_since(mark_at).as_secs_f64();
                let bytes_per_s = if secs > 0.0 { p.bytes_sent.saturating_sub(mark_bytes) as f64 / secs } else { 0.0 };
                p.rate_mark = (p.bytes_sent, now);
                let position = d.slot(p.entity).map_or([f32::NAN; 3], |slot| d.positions()[slot].to_array());
                PlayerRow {
                    account: p.username.clone(),
                    user_id: p.user_id.0,
                    entity: u64::from(p.entity.0),
                    addr: p.addr,
                    connected_since: p.connected_since,
                    position,
                    bytes_per_s,
                }
            })
            .collect();
        Snapshot { taken: now, tick: world.tick, players, bounds, density, cuts }
    }
}

/// The tick's side of the snapshots: when the next one is due.
#[derive(Debug)]
pub(crate) struct Publisher {
    shared: Arc<AdminShared>,
    next: Instant,
}

impl Publisher {
    pub(crate) fn new(shared: Arc<AdminShared>) -> Self {
        Publisher { shared, next: Instant::now() }
    }

    /// Takes and publishes a snapshot if one is wanted and due; never blocks.
    pub(crate) fn maybe_publish(&mut self, sessions: &mut Sessions, world: &World, backend: &dyn Backend) {
        let now = Instant::now();
        if now < self.next || !self.shared.wanted() {
            return;
        }
        // Taken before the lock, so a request reading the last one never waits for it.
        let snapshot = Arc::new(Snapshot::take(sessions, world, backend.zone_cuts(), now));
        let Ok(mut slot) = self.shared.snapshot.try_lock() else { return };
        *slot = Some(snapshot);
        drop(slot);
        // What a snapshot costs the tick (outside its stages: it runs after the tick's
        // work is timed, like the checkpoint's hand-over).
        let took = now.elapsed();
        self.shared.snapshot_us.store(took.as_micros() as u64, std::sync::atomic::Ordering::Relaxed);
        metrics::histogram!("myriad_admin_snapshot_duration_seconds").record(took.as_secs_f64());
        self.next = now + SNAPSHOT_EVERY;
    }
}

#[cfg(test)]
mod tests {
    use super::cell_of;

    #[test]
    fn cells_clamp_at_the_edges() {
        assert_eq!(cell_of(0.0, 0.0, 100.0, 4), 0);
        assert_eq!(cell_of(24.9, 0.0, 100.0, 4), 0);
        assert_eq!(cell_of(25.0, 0.0, 100.0, 4), 1);
        assert_eq!(cell_of(100.0, 0.0, 100.0, 4), 3);
        assert_eq!(cell_of(-5.0, 0.0, 100.0, 4), 0);
        assert_eq!(cell_of(500.0, 0.0, 100.0, 4), 3);
    }
}
