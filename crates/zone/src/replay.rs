//! Live runs that replay bit for bit: every zone logs the intents it applied, with the
//! tick it applied them at, and a replay re-runs the world from a checkpoint with those
//! inputs, ending in the live run's hash.
//!
//! A zone applies a gateway's intents at the tick it is at when they arrive, so the same
//! players do not make the same run twice. What a zone did is still exact: every intents
//! message it took, in order, and the tick it took it at ([`IntentLog`]). Its log is cut
//! at every checkpoint into a **segment** that starts with the zone's intent book as it
//! was at that checkpoint (a book remembers actions, leaves and gateways from before)
//! and is stored next to the checkpoint (`z<zone>-t<tick>-log`), signed with the
//! cluster's key, and forgotten with it: the log is as bounded as the checkpoints.
//!
//! [`load`] reads every zone's checkpoint of tick `from` and the chain of segments from
//! `from` to `to`, all of one epoch (a rollback starts a new one: a chain that mixes
//! epochs is refused); [`replay`] steps the zones on threads, offering each zone the
//! intents of each tick before stepping it, exactly as the live zone took them.
//!
//! Cut moves of a live cluster ([`crate::rebalance::live`]) are logged the same way: the
//! supervisor's signed message, at the tick the zone applied it (before stepping it). A
//! replay starts on the cuts the checkpoint holds and applies each logged move at its
//! tick, so every zone follows the live run's cuts.
//!
//! Segment layout (little-endian): magic `MZL1`, zone (u16), 0 (u16), epoch (u64),
//! first tick (u64), end tick (u64, exclusive), book length (u32), entries (u32), the
//! book ([`IntentBook::snapshot`]), then per entry its tick (u64), length (u32) and the
//! message as it arrived (itself signed: intents, or a cut move), and a 32-byte
//! HMAC-SHA256 tag over everything before it.

use std::sync::Arc;
use std::time::Instant;

use myriad_core::{ActionScript, ObjectState, World};
use myriad_physics::{Backend, TickConstants};

use crate::checkpoint::CheckpointStore;
use crate::error::ZoneError;
use crate::fabric::{Fabric, MemoryFabric};
use crate::intents::IntentBook;
use crate::layout::{ZoneId, ZoneLayout};
use crate::local::ZonedRun;
use crate::rebalance::Cuts;
use crate::wire::{ClusterKey, KIND_CUT_MOVE, sign, verified};
use crate::zone::{TickEnd, Zone, ZoneConfig};

/// The first bytes of a segment.
pub const LOG_MAGIC: [u8; 4] = *b"MZL1";

/// Header bytes of a segment.
const LOG_HEADER: usize = 40;

/// Largest intents message a segment entry may hold (a fabric message is at most a few
/// MiB; a corrupt length never makes a large allocation).
const MAX_ENTRY: usize = 64 << 20;

/// The intents a zone took since its last checkpoint, by tick, with its book as it was
/// then (see the module docs).
#[derive(Clone, Debug)]
pub struct IntentLog {
    from: u64,
    book: Vec<u8>,
    entries: Vec<(u64, Vec<u8>)>,
}

impl IntentLog {
    /// A log starting at tick `from`, with the book as it is then.
    pub fn start(from: u64, book: &IntentBook) -> IntentLog {
        IntentLog { from, book: book.snapshot(), entries: Vec::new() }
    }

    /// The tick the log starts at.
    pub fn from(&self) -> u64 {
        self.from
    }

    /// An intents message taken at tick `tick`, or a cut move applied before stepping
    /// it, as it arrived.
    pub fn record(&mut self, tick: u64, bytes: &[u8]) {
        self.entries.push((tick, bytes.to_vec()));
    }

    /// The signed segment of zone `zone`, epoch `epoch`, covering ticks `from..to`.
    pub fn seal(&self, key: &ClusterKey, zone: ZoneId, epoch: u64, to: u64) -> Vec<u8> {
        let len = self.entries.iter().map(|(_, b)| 12 + b.len()).sum::<usize>();
        let mut b = Vec::with_capacity(LOG_HEADER + self.book.len() + len);
        b.extend_from_slice(&LOG_MAGIC);
        b.extend_from_slice(&zone.0.to_le_bytes());
        b.extend_from_slice(&0u16.to_le_bytes());
        for v in [epoch, self.from, to] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&(self.book.len() as u32).to_le_bytes());
        b.extend_from_slice(&(self.entries.len() as u32).to_le_bytes());
        b.extend_from_slice(&self.book);
        for (tick, m) in &self.entries {
            b.extend_from_slice(&tick.to_le_bytes());
            b.extend_from_slice(&(m.len() as u32).to_le_bytes());
            b.extend_from_slice(m);
        }
        sign(key, &b)
    }
}

/// One stored segment, opened.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    /// The zone that wrote it.
    pub zone: ZoneId,
    /// Its epoch.
    pub epoch: u64,
    /// First tick covered.
    pub from: u64,
    /// End tick (exclusive).
    pub to: u64,
    /// The zone's book at `from` ([`IntentBook::snapshot`]).
    pub book: Vec<u8>,
    /// The messages taken (intents, cut moves), with their ticks, in order.
    pub entries: Vec<(u64, Vec<u8>)>,
}

/// Whether a logged message is a cut move (an intents message otherwise; the zone
/// authenticates either when it takes it).
pub fn is_cut_move(message: &[u8]) -> bool {
    message.get(3) == Some(&KIND_CUT_MOVE)
}

/// Checks a segment's tag, then its fields; a clear error on anything else.
pub fn open_segment(key: &ClusterKey, bytes: &[u8]) -> Result<Segment, ZoneError> {
    let bad = |what: String| ZoneError::Replay(format!("intent log: {what}"));
    if bytes.len() < LOG_HEADER || bytes[..4] != LOG_MAGIC {
        return Err(bad("not a segment (magic or length)".into()));
    }
    let b = verified(key, bytes).map_err(|e| bad(e.to_string()))?;
    let u16_at = |at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
    let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes")) as usize;
    let u64_at = |at: usize| u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"));
    if b.len() < LOG_HEADER || u16_at(6) != 0 {
        return Err(bad("header".into()));
    }
    let (zone, epoch, from, to) = (ZoneId(u16_at(4)), u64_at(8), u64_at(16), u64_at(24));
    let (book_len, count) = (u32_at(32), u32_at(36));
    if to <= from {
        return Err(bad(format!("ticks {from}..{to}")));
    }
    let book = b.get(LOG_HEADER..LOG_HEADER + book_len).ok_or_else(|| bad("book length".into()))?.to_vec();
    let mut at = LOG_HEADER + book_len;
    let mut entries = Vec::with_capacity(count.min(b.len() / 12));
    for i in 0..count {
        let head = b.get(at..at + 12).ok_or_else(|| bad(format!("entry {i} is cut")))?;
        let tick = u64::from_le_bytes(head[..8].try_into().expect("8 bytes"));
        let len = u32::from_le_bytes(head[8..].try_into().expect("4 bytes")) as usize;
        if !(from..to).contains(&tick) || entries.last().is_some_and(|(t, _)| *t > tick) || len > MAX_ENTRY {
            return Err(bad(format!("entry {i}: tick {tick}, {len} bytes")));
        }
        let m = b.get(at + 12..at + 12 + len).ok_or_else(|| bad(format!("entry {i} is cut")))?;
        entries.push((tick, m.to_vec()));
        at += 12 + len;
    }
    if at != b.len() {
        return Err(bad(format!("{} bytes after the last entry", b.len() - at)));
    }
    Ok(Segment { zone, epoch, from, to, book, entries })
}

/// What one zone needs to replay: its objects at the first tick, its book then, and the
/// intents it took after, by tick.
#[derive(Debug)]
pub struct ZoneReplay {
    /// The zone.
    pub zone: ZoneId,
    /// Its objects at the first tick (its checkpoint).
    pub objects: Vec<ObjectState>,
    /// The cuts its checkpoint holds.
    pub cuts: Cuts,
    /// Its intent book then.
    pub book: IntentBook,
    /// The messages it took (intents) or applied (cut moves), with their ticks, in order.
    pub entries: Vec<(u64, Vec<u8>)>,
}

/// Every zone's checkpoint of tick `from` and chain of segments up to `to`, all of one
/// epoch (which is returned).
pub fn load(
    store: &mut dyn CheckpointStore,
    key: &ClusterKey,
    zones: usize,
    from: u64,
    to: u64,
) -> Result<(u64, Vec<ZoneReplay>), ZoneError> {
    if to < from {
        return Err(ZoneError::Replay(format!("from tick {from} to {to}")));
    }
    let mut epoch = None;
    let mut out = Vec::with_capacity(zones);
    for z in (0..zones).map(|z| ZoneId(z as u16)) {
        let snap = store.get(z, from)?;
        if out.first().is_some_and(|first: &ZoneReplay| first.cuts != snap.cuts) {
            return Err(ZoneError::Replay(format!("the zones' checkpoints of tick {from} hold different cuts")));
        }
        let (mut t, mut book, mut entries) = (from, None, Vec::new());
        while t < to {
            let seg = open_segment(key, &store.get_log(z, t)?)?;
            if seg.zone != z || seg.from != t || seg.to > to {
                return Err(ZoneError::Replay(format!(
                    "the log of zone {} at tick {t} is zone {}'s, of ticks {}..{}",
                    z.0, seg.zone.0, seg.from, seg.to
                )));
            }
            if *epoch.get_or_insert(seg.epoch) != seg.epoch {
                return Err(ZoneError::Replay(format!(
                    "the logs from tick {from} span two epochs (a rollback): replay from a later checkpoint"
                )));
            }
            if book.is_none() {
                book = Some(IntentBook::restore(&seg.book).map_err(ZoneError::Replay)?);
            }
            entries.extend(seg.entries);
            t = seg.to;
        }
        let book = book.unwrap_or_else(|| IntentBook::new(from));
        out.push(ZoneReplay { zone: z, objects: snap.objects, cuts: snap.cuts, book, entries });
    }
    Ok((epoch.unwrap_or(0), out))
}

/// Re-runs `zones` (from [`load`]) from tick `from` to `to` on threads of this process,
/// each with the backend `backend(zone)`, on the cuts of their checkpoints (`layout`
/// gives the grid), offering each zone the intents it took at each tick and applying
/// the cut moves it applied, before stepping it; `world` supplies bounds, terrain,
/// statics and seed (as for [`Zone::resume`]). The result is comparable with the live run's checkpoints of `to`
/// ([`crate::supervisor::assemble`]).
#[allow(clippy::too_many_arguments)]
pub fn replay(
    world: &World,
    layout: ZoneLayout,
    script: &ActionScript,
    k: &TickConstants,
    backend: &(dyn Fn(ZoneId) -> Result<Box<dyn Backend>, ZoneError> + Sync),
    zones: Vec<ZoneReplay>,
    key: &ClusterKey,
    from: u64,
    to: u64,
) -> Result<ZonedRun, ZoneError> {
    if zones.len() != layout.len() {
        return Err(ZoneError::Layout(format!("{} zones to replay in a layout of {}", zones.len(), layout.len())));
    }
    let cuts = zones.first().map(|z| z.cuts.clone());
    let layout = Arc::new(match cuts {
        Some((xs, zs)) => layout.with_cuts(&xs, &zs)?,
        None => layout,
    });
    let mut start = world.clone();
    start.tick = from;
    let start = &start;
    let fabrics = MemoryFabric::mesh(layout.len());
    let run = 1;
    let results: Vec<Result<crate::local::Outcome, ZoneError>> = std::thread::scope(|s| {
        let handles: Vec<_> = zones
            .into_iter()
            .zip(fabrics)
            .map(|(z, fabric)| {
                let layout = layout.clone();
                s.spawn(move || {
                    let cfg = ZoneConfig {
                        id: z.zone,
                        run,
                        key: key.clone(),
                        wait: std::time::Duration::from_secs(60),
                        live: false,
                    };
                    let fabric: Box<dyn Fabric> = Box::new(fabric);
                    let mut zone = Zone::resume(cfg, layout, start, z.objects, backend(z.zone)?, fabric)?;
                    zone.restore_book(z.book);
                    let mut entries = z.entries.iter().peekable();
                    let (first, mut actions) = (Instant::now(), 0);
                    for t in from..to {
                        while let Some((_, m)) = entries.next_if(|(at, _)| *at == t) {
                            let (taken, what) = if is_cut_move(m) {
                                (zone.apply_logged_cut(m), "a cut move it applied")
                            } else {
                                (zone.offer_intents(m), "an intents message it took")
                            };
                            if !taken {
                                return Err(ZoneError::Replay(format!(
                                    "zone {} refused {what} live at tick {t}",
                                    z.zone.0
                                )));
                            }
                        }
                        match zone.step(script.at(t), k)? {
                            TickEnd::Stepped(n) => actions += n,
                            TickEnd::Interrupted(m) => {
                                return Err(ZoneError::Replay(format!("a control message in a replay: {m:?}")));
                            }
                        }
                    }
                    Ok(crate::local::Outcome {
                        objects: zone.advanced(),
                        actions,
                        stats: zone.stats().clone(),
                        static_prims: zone.static_prims(),
                        first,
                        last: Instant::now(),
                    })
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("a zone thread panicked")).collect()
    });
    crate::local::reassemble(results, None, to, None)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gateway::incarnation_ids;
    use crate::wire::{IntentKind, Intents, encode_intents};
    use myriad_core::{EntityId, ObjectKind, ShapeKind, Vec3};

    fn segment(key: &ClusterKey) -> Vec<u8> {
        let mut book = IntentBook::new(30);
        let o = ObjectState {
            id: EntityId(incarnation_ids(1, 5).start),
            kind: ObjectKind::User,
            shape: ShapeKind::Sphere,
            half: Vec3::splat(0.5),
            radius: 0.5,
            pos: Vec3::ONE,
            prev: Vec3::ONE,
            action: 1,
            flags: 0,
        };
        let m = Intents { incarnation: 5, tick: 3, gateway: 1, kind: IntentKind::Join, objects: vec![o] };
        book.offer(m.clone(), 30).unwrap();
        let mut log = IntentLog::start(30, &book);
        let bytes = encode_intents(key, &Intents { tick: 4, kind: IntentKind::Action, ..m }).unwrap();
        log.record(31, &bytes);
        log.record(33, &bytes);
        log.seal(key, ZoneId(2), 9, 60)
    }

    #[test]
    fn a_segment_opens_as_sealed_and_refuses_damage() {
        let key = ClusterKey::random();
        let bytes = segment(&key);
        let s = open_segment(&key, &bytes).unwrap();
        assert_eq!((s.zone, s.epoch, s.from, s.to, s.entries.len()), (ZoneId(2), 9, 30, 60, 2));
        assert_eq!(IntentBook::restore(&s.book).unwrap().snapshot(), s.book);
        assert!(open_segment(&ClusterKey::random(), &bytes).is_err(), "another key");
        for cut in [0, 10, 39, bytes.len() - 1] {
            assert!(open_segment(&key, &bytes[..cut]).is_err(), "cut at {cut}");
        }
        for flip in [0, 5, 20, 50, bytes.len() - 40, bytes.len() - 1] {
            let mut b = bytes.clone();
            b[flip] ^= 1;
            assert!(open_segment(&key, &b).is_err(), "bit flipped at {flip}");
        }
        // Signed but inconsistent: an entry outside the segment's ticks.
        let mut b = bytes[..bytes.len() - 32].to_vec();
        let at = LOG_HEADER + s.book.len();
        b[at..at + 8].copy_from_slice(&61u64.to_le_bytes());
        assert!(open_segment(&key, &sign(&key, &b)).is_err());
    }
}
