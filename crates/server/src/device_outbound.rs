//! The device implementation of [`Outbound`]: the CUDA backend answers the AOI boxes,
//! selects each player's records by the host interest manager's rule, packs them into
//! state update bodies and seals them, all on the device (`myriad_cuda`'s interest
//! updates), so only finished datagrams come back, never the AOI lists. Each player's
//! datagrams are sealed under sequence numbers leased from its sealer
//! ([`myriad_protocol::Sealer::lease`], as many as its budget of datagrams); the host
//! checks them, takes them and returns the unused numbers
//! ([`InterestManager::adopt_sealed`]). What was packed becomes the staleness of the next
//! tick on the device.
//!
//! The players go in chunks (at most [`MAX_CHUNKS`], each a whole number of the device's
//! waves of selection): the device queues every chunk at once, and every thread of the
//! pool takes its share of each chunk as soon as the device has finished it, checks and
//! takes its datagrams and hands them to its lane of the tick's [`Ready`] (which sends
//! them), while the device builds the next chunks. A tick's time is then about the
//! device's part plus the sending of one chunk, instead of the sum of both; the threads
//! never wait for each other, so none sleeps and wakes between chunks.
//!
//! The datagrams are byte for byte those of [`CpuOutbound`] for the same world, tick and
//! history (the GPU suite's `device_outbound` test). With another backend, a budget
//! larger than the device selection holds, or after a device error, it serves the tick
//! through a [`CpuOutbound`] (a device error is logged and counted as
//! `myriad_outbound_errors_total{reason="device_select"}`; the players of the chunks the
//! device had finished keep what it built); players then start their rotation afresh.

use std::ops::Range;
use std::sync::Mutex;
use std::time::Instant;

use myriad_core::{Aabb, Vec3, World};
use myriad_cuda::CudaBackend;
use myriad_cuda::backend::{InterestQuery, MAX_PACK_DATAGRAMS, MAX_SELECTED, NO_PREVIOUS};
use myriad_interest::{InterestConfig, InterestManager, Packed, TickInfo, TickReport};
use myriad_physics::Backend;
use myriad_protocol::{MAX_COMPACT_RECORDS, SealLease};
use rayon::prelude::*;

use crate::outbound::{CpuOutbound, Outbound, OutboundReport, Ready, Recipient};

/// The most chunks a tick's players are split into. Each chunk costs the host a few
/// hand-overs between threads and the device a partly idle last wave of its selection,
/// so a chunk holds a whole number of the device's waves
/// ([`CudaBackend::interest_wave`]), as few as keep the chunks at most this many.
pub const MAX_CHUNKS: usize = 8;

/// Interest selection, packing and sealing on the device.
#[derive(Debug)]
pub struct DeviceOutbound {
    interest: InterestManager,
    half: Vec3,
    fallback: CpuOutbound,
    /// Players per chunk (`None`: by the device's wave and [`MAX_CHUNKS`]).
    chunk: Option<usize>,
    /// The device's wave of selection, once asked.
    wave: Option<usize>,
}

impl DeviceOutbound {
    /// AOI boxes of edge `aoi_size` centred on each player, at most `max_datagrams`
    /// update datagrams per player and tick.
    pub fn new(aoi_size: f32, max_datagrams: usize) -> Self {
        DeviceOutbound {
            interest: InterestManager::new(InterestConfig { max_datagrams, ..Default::default() }),
            half: Vec3::splat(aoi_size / 2.0),
            fallback: CpuOutbound::new(aoi_size, max_datagrams),
            chunk: None,
            wave: None,
        }
    }

    /// The same with `players` (at least one) in every chunk but the last, whatever the
    /// number of players (the tests' way to cut a few hundred players into chunks).
    pub fn with_chunk(mut self, players: usize) -> Self {
        self.chunk = Some(players.max(1));
        self
    }

    /// Players per chunk for `n` players, on a device that selects `wave` at once.
    fn chunk_players(&self, n: usize, wave: usize) -> usize {
        let wave = wave.max(1);
        self.chunk.unwrap_or_else(|| wave * n.div_ceil(wave * MAX_CHUNKS).max(1))
    }

    /// Slots the device may choose for one player: a view that fits can hold
    /// `MAX_COMPACT_RECORDS` a datagram when the player has no own object.
    fn selection_room(&self) -> usize {
        self.interest.config().max_datagrams.max(1) * MAX_COMPACT_RECORDS
    }

    /// Whether the device selection and packing can hold this budget.
    fn budget_fits(&self) -> bool {
        self.selection_room() <= MAX_SELECTED && self.interest.config().max_datagrams <= MAX_PACK_DATAGRAMS
    }

    /// Serves the tick on the host; the device's staleness is then out of date.
    fn on_host(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
        ready: &dyn Ready,
    ) -> OutboundReport {
        self.fallback.build(backend, world, tick, recipients, ready)
    }

    /// After a device error: logs and counts it, and serves the players the device did
    /// not (`parts`) on the host.
    fn device_failed(
        &mut self,
        error: &str,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        parts: Vec<&mut [Recipient<'_>]>,
        ready: &dyn Ready,
    ) -> OutboundReport {
        let players: usize = parts.iter().map(|p| p.len()).sum();
        tracing::error!(error, players, "device interest updates failed; these players are served on the host");
        metrics::counter!("myriad_outbound_errors_total", "reason" => "device_select").increment(1);
        let mut report = OutboundReport::default();
        for part in parts {
            let rest = self.on_host(backend, world, tick, part, ready);
            report.records += rest.records;
            report.seal_failures += rest.seal_failures;
        }
        report
    }
}

impl Outbound for DeviceOutbound {
    fn description(&self) -> String {
        let max = self.interest.config().max_datagrams;
        if self.budget_fits() {
            format!("device interest selection, packing and sealing ({max} datagrams a player at most)")
        } else {
            format!(
                "host interest management: {max} datagrams a player is over the device selection's {MAX_SELECTED} records"
            )
        }
    }

    fn build(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
        ready: &dyn Ready,
    ) -> OutboundReport {
        if !self.budget_fits() {
            return self.on_host(backend, world, tick, recipients, ready);
        }
        let Some(cuda) = backend.as_any_mut().downcast_mut::<CudaBackend>() else {
            return self.on_host(backend, world, tick, recipients, ready);
        };
        let mut report = OutboundReport::default();
        if recipients.is_empty() {
            return report;
        }
        // In parallel: each recipient and its previous index are cache misses. The views'
        // object and centre are the host interest manager's; the device takes them here,
        // with a lease of each player's sequence numbers (none: its sealer ran out, and
        // the player gets nothing, as with the host's sealing).
        let half = self.half;
        let config = *self.interest.config();
        let max_datagrams = config.max_datagrams.max(1);
        let ((boxes, own), (centres, (prev, mut leases))): Inputs = recipients
            .par_iter_mut()
            .map(|r| {
                let prev = match r.view.selected {
                    Some((t, i)) if t + 1 == tick.tick => i,
                    _ => NO_PREVIOUS,
                };
                let lease = r.view.sealer.lease(max_datagrams as u64).ok();
                ((Aabb::from_center_half(r.centre, half), r.object), (r.centre.to_array(), (prev, lease)))
            })
            .unzip();
        let query = InterestQuery {
            tick: tick.tick,
            dilation_permille: tick.dilation_permille,
            boxes: &boxes,
            own: &own,
            centres: &centres,
            prev: &prev,
            leases: &leases,
            max_datagrams: max_datagrams as u32,
            near_slots: config.near_slots() as u32,
            rotation_slots: config.rotation_slots() as u32,
            capacity: self.selection_room() as u32,
        };
        let wave = *self.wave.get_or_insert_with(|| {
            let wave = cuda.interest_wave().unwrap_or(1);
            tracing::info!(players = wave, "the device selects a wave of players at once; chunks hold whole waves");
            wave
        });
        let chunk = self.chunk_players(recipients.len(), wave);
        let queueing = Instant::now();
        if let Err(e) = cuda.queue_interest_updates(world, &query, chunk) {
            // Nothing is left queued, but the keys are wiped and the tables start afresh.
            let _ = cuda.finish_interest_updates(tick.tick, false);
            return self.device_failed(&e.to_string(), backend, world, tick, vec![recipients], ready);
        }
        let queued = queueing.elapsed();
        let mut failed = None;
        // Every thread of the pool takes its share of each chunk (module docs).
        let threads = rayon::current_num_threads().max(1);
        let chunks = cuda.interest_chunks();
        let ranges = (0..chunks.len()).map(|k| chunks.players(k).unwrap_or_default());
        let shares = Shares::new(recipients, &mut leases, ranges, threads);
        let interest = &self.interest;
        let waited: Vec<(TickReport, std::time::Duration, Option<String>)> = rayon::broadcast(|ctx| {
            let mut report = TickReport::default();
            let mut waited = std::time::Duration::ZERO;
            for k in 0..chunks.len() {
                let t = Instant::now();
                let (players, payloads) = match chunks.wait(k) {
                    Ok(chunk) => chunk,
                    Err(e) => return (report, waited, Some(e.to_string())),
                };
                waited += t.elapsed();
                let Some((start, part, leases)) = shares.take(k, ctx.index()) else { continue };
                let at = start - players.start;
                let datagrams = |i: usize| {
                    payloads.get(at + i).map(|p| Packed {
                        datagrams: p.datagrams(),
                        in_view: p.in_view as usize,
                        over_budget: p.over_budget,
                        pinned: p.pinned,
                        packed: p.packed as usize,
                    })
                };
                report = report.merge(interest.adopt_sealed(datagrams, part, leases));
                for (i, r) in part.iter_mut().enumerate() {
                    r.view.selected = Some((tick.tick, (start + i) as u32));
                }
                ready.ready(ctx.index(), part);
            }
            (report, waited, None)
        });
        let mut sealed = TickReport::default();
        for (report, _, error) in &waited {
            sealed = sealed.merge(*report);
            failed = failed.or_else(|| error.clone());
        }
        // The device's share: queueing (which waits for the AOI query's count), then the
        // first thread's waits for chunks.
        report.device_wait_ms = (queued + waited.first().map_or(std::time::Duration::ZERO, |w| w.1)).as_secs_f64() * 1e3;
        let unserved = shares.into_rest();
        if let Err(e) = cuda.finish_interest_updates(tick.tick, unserved.is_empty() && failed.is_none()) {
            failed = failed.or(Some(e.to_string()));
        }
        if sealed.skipped > 0 {
            // The device's counts disagreed with its bytes: those players get nothing
            // this tick (their staleness says they were sent; they are again soon).
            tracing::error!(players = sealed.skipped, "device datagrams refused");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_datagrams")
                .increment(sealed.skipped as u64);
        }
        report.add_interest(&sealed);
        if failed.is_some() || !unserved.is_empty() {
            let error = failed.unwrap_or_else(|| "chunks left unserved".into());
            let rest = self.device_failed(&error, backend, world, tick, unserved, ready);
            report.records += rest.records;
            report.seal_failures += rest.seal_failures;
            return report;
        }
        report
    }
}

/// The device's inputs, one entry a player: AOI boxes, own objects, centres, indices in the
/// last selection, leases (as `unzip` makes them).
type Inputs = ((Vec<Aabb>, Vec<u32>), (Vec<[f32; 3]>, (Vec<u32>, Vec<Option<SealLease>>)));

/// The tick's recipients (and their leases) cut into one share per chunk and thread,
/// for the threads to take without sharing anything.
struct Shares<'r, 'a> {
    threads: usize,
    /// Share `k * threads + j`: its first recipient's index, the recipients, the leases.
    slots: Vec<Mutex<Option<Share<'r, 'a>>>>,
}

type Share<'r, 'a> = (usize, &'r mut [Recipient<'a>], &'r mut [Option<SealLease>]);

impl<'r, 'a> Shares<'r, 'a> {
    /// Cuts `recipients` and `leases` (one a recipient) by `chunks`, consecutive ranges
    /// from 0, each into `threads` shares.
    fn new(
        mut recipients: &'r mut [Recipient<'a>],
        mut leases: &'r mut [Option<SealLease>],
        chunks: impl ExactSizeIterator<Item = Range<usize>>,
        threads: usize,
    ) -> Self {
        let mut slots = Vec::with_capacity(chunks.len() * threads);
        let mut at = 0;
        for players in chunks {
            let len = players.len();
            for j in 0..threads {
                let n = ((j + 1) * len / threads - j * len / threads).min(recipients.len()).min(leases.len());
                let (part, rest) = std::mem::take(&mut recipients).split_at_mut(n);
                let (lease, more) = std::mem::take(&mut leases).split_at_mut(n);
                (recipients, leases) = (rest, more);
                slots.push(Mutex::new(Some((at, part, lease))));
                at += n;
            }
        }
        Shares { threads, slots }
    }

    /// Thread `j`'s share of chunk `k`, once.
    fn take(&self, k: usize, j: usize) -> Option<Share<'r, 'a>> {
        let slot = self.slots.get(k * self.threads + j % self.threads)?;
        slot.lock().unwrap_or_else(|p| p.into_inner()).take()
    }

    /// The recipients of the shares no thread took, in order.
    fn into_rest(self) -> Vec<&'r mut [Recipient<'a>]> {
        self.slots
            .into_iter()
            .filter_map(|s| s.into_inner().unwrap_or_else(|p| p.into_inner()))
            .map(|(_, part, _)| part)
            .filter(|p| !p.is_empty())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_interest::Subscriber;
    use myriad_protocol::{Direction, Sealer};

    /// `n` players' views, player `i` of session `i`.
    fn views(n: u32) -> Vec<Subscriber> {
        (0..n)
            .map(|i| Subscriber::new(i, [0.0; 3], Sealer::new(u64::from(i), Direction::ServerToClient, &[1; 32])))
            .collect()
    }

    fn recipients(views: &mut [Subscriber]) -> Vec<Recipient<'_>> {
        views
            .iter_mut()
            .enumerate()
            .map(|(i, view)| Recipient { session_id: i as u64, object: i as u32, centre: Vec3::ZERO, addr: None, view })
            .collect()
    }

    /// Every recipient lands in exactly one share, in order, each share with its own
    /// leases, and the shares of a chunk cover the chunk (a short last chunk, more threads
    /// than players in a chunk).
    #[test]
    fn shares_cover_every_recipient_once_in_order() {
        let mut views = views(23);
        let mut recipients = recipients(&mut views);
        let mut leases: Vec<Option<SealLease>> =
            (0..23).map(|i| Some(Sealer::new(i, Direction::ServerToClient, &[1; 32]).lease(2).unwrap())).collect();
        let chunks = [0..10, 10..20, 20..23];
        let threads = 4;
        let shares = Shares::new(&mut recipients, &mut leases, chunks.iter().cloned(), threads);
        let mut seen = Vec::new();
        for (k, chunk) in chunks.iter().enumerate() {
            let mut covered = Vec::new();
            for j in 0..threads {
                let (start, part, leases) = shares.take(k, j).expect("a share per chunk and thread");
                assert_eq!(part.len(), leases.len());
                for (i, (r, l)) in part.iter().zip(leases.iter()).enumerate() {
                    assert_eq!(r.session_id as usize, start + i);
                    assert_eq!(l.as_ref().map(SealLease::session_id), Some(r.session_id));
                    covered.push(start + i);
                }
                assert!(shares.take(k, j).is_none(), "each share is taken once");
            }
            assert_eq!(covered, chunk.clone().collect::<Vec<_>>());
            seen.extend(covered);
        }
        assert_eq!(seen, (0..23).collect::<Vec<_>>());
        assert!(shares.into_rest().is_empty());
    }

    /// What no thread took comes back for the host, in order.
    #[test]
    fn untaken_shares_are_the_rest() {
        let mut views = views(8);
        let mut recipients = recipients(&mut views);
        let mut leases: Vec<Option<SealLease>> = (0..8).map(|_| None).collect();
        let shares = Shares::new(&mut recipients, &mut leases, [0..4, 4..8].into_iter(), 2);
        shares.take(0, 0).unwrap();
        shares.take(1, 1).unwrap();
        let rest: Vec<Vec<u64>> = shares.into_rest().iter().map(|p| p.iter().map(|r| r.session_id).collect()).collect();
        assert_eq!(rest, vec![vec![2, 3], vec![4, 5]]);
    }
}
