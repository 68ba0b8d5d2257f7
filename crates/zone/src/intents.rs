//! What gateways asked for their players, as one zone keeps it between ticks.
//!
//! Gateways send every intent to every zone (`docs/zones.md`, gateways): a zone cannot
//! know which object it will own when an intent arrives, because a hand-off may be on
//! its way. So each zone keeps, for every player's object:
//! - the newest **action** (applied to the object every tick the zone owns it: an action
//!   is a state, so applying it again changes nothing, and a zone that gains the object
//!   by a hand-off applies the same newest action);
//! - a **leave**, remembered for [`LEAVE_MEMORY`] ticks, so that an object handed to this
//!   zone after its leave arrived is still removed;
//! - **joins** until the next step, when the zone whose region holds a joining object
//!   adopts it (unless it is already in the world or has left).
//!
//! Intents are signed by the cluster key like every fabric message; within one gateway
//! they must come in order (incarnation, tick, kind), so a replayed message is refused.
//!
//! A player's object lives only as long as its gateway does: [`IntentBook::keeps`] says
//! no to an object of a gateway whose id is outside the ids of the gateway's current
//! incarnation ([`crate::gateway::incarnation_ids`]: a restarted gateway's earlier
//! players), or whose gateway has not been heard from for [`GATEWAY_TIMEOUT`] ticks (a
//! dead gateway's players; a live gateway speaks at least every second).

use std::collections::{BTreeMap, HashMap};

use myriad_core::{EntityId, ObjectState};

use crate::gateway::{gateway_of, incarnation_ids};
use crate::wire::{IntentKind, Intents};

/// Ticks without a message from a gateway after which its players' objects are removed
/// (5 s at 30 Hz; a gateway sends at least one message a second).
pub const GATEWAY_TIMEOUT: u64 = 150;

/// Ticks a leave is remembered (10 s at 30 Hz): longer than any hand-off takes.
pub const LEAVE_MEMORY: u64 = 300;

/// Most players' objects a zone keeps intents for; beyond it new ones are refused.
pub const MAX_TRACKED: usize = 1 << 20;

/// A zone's book of its gateways' intents (see the module docs).
#[derive(Debug, Default)]
pub struct IntentBook {
    /// Newest (incarnation, tick, kind) taken from each gateway.
    last: HashMap<u16, (u64, u64, IntentKind)>,
    /// Objects waiting to be adopted by the zone whose region holds them.
    joins: Vec<ObjectState>,
    /// Newest action per object.
    actions: BTreeMap<EntityId, u8>,
    /// Objects that left, with the tick the zone learnt it.
    leaves: BTreeMap<EntityId, u64>,
    /// Per gateway: its current incarnation and the tick it was last heard from.
    gateways: HashMap<u16, Heard>,
    /// The tick the book started (a gateway not heard from since is given until
    /// [`GATEWAY_TIMEOUT`] after it).
    since: u64,
}

#[derive(Debug, Default)]
struct Heard {
    incarnation: u64,
    at: u64,
}

/// Why an intents message was not taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refused {
    /// Not newer than what the same gateway sent before (a replay, or reordered).
    Stale,
    /// More objects than [`MAX_TRACKED`].
    Full,
    /// An object outside the sending gateway's id range: a gateway speaks only for its
    /// own players.
    Foreign,
}

impl Refused {
    /// A short name for metrics labels.
    pub fn label(self) -> &'static str {
        match self {
            Refused::Stale => "intent_stale",
            Refused::Full => "intent_full",
            Refused::Foreign => "intent_foreign",
        }
    }
}

impl IntentBook {
    /// An empty book for a zone starting at tick `since`.
    pub fn new(since: u64) -> IntentBook {
        IntentBook { since, ..IntentBook::default() }
    }

    /// Whether an object the zone owns stays at tick `now` (see the module docs).
    /// Objects outside every gateway's id range always stay.
    pub fn keeps(&self, id: EntityId, now: u64) -> bool {
        keeps(&self.gateways, self.since, id, now)
    }

    /// Takes one message of intents, seen while the zone is at tick `now`.
    pub fn offer(&mut self, m: Intents, now: u64) -> Result<(), Refused> {
        let order = (m.incarnation, m.tick, m.kind);
        if self.last.get(&m.gateway).is_some_and(|last| order <= *last) {
            return Err(Refused::Stale);
        }
        if m.objects.iter().any(|o| gateway_of(o.id) != Some(m.gateway)) {
            return Err(Refused::Foreign);
        }
        if self.actions.len() + self.leaves.len() + self.joins.len() + m.objects.len() > MAX_TRACKED {
            return Err(Refused::Full);
        }
        self.last.insert(m.gateway, order);
        self.gateways.insert(m.gateway, Heard { incarnation: m.incarnation, at: now });
        for o in m.objects {
            match m.kind {
                IntentKind::Join => {
                    self.leaves.remove(&o.id);
                    self.actions.insert(o.id, o.action);
                    self.joins.push(o);
                }
                IntentKind::Action => {
                    if !self.leaves.contains_key(&o.id) {
                        self.actions.insert(o.id, o.action);
                    }
                }
                IntentKind::Leave => {
                    self.actions.remove(&o.id);
                    self.joins.retain(|j| j.id != o.id);
                    self.leaves.insert(o.id, now);
                }
            }
        }
        Ok(())
    }

    /// The joins since the last step (emptied).
    pub fn take_joins(&mut self) -> Vec<ObjectState> {
        std::mem::take(&mut self.joins)
    }

    /// Whether `id` has left.
    pub fn left(&self, id: EntityId) -> bool {
        self.leaves.contains_key(&id)
    }

    /// Every object's newest action, by id.
    pub fn actions(&self) -> impl Iterator<Item = (EntityId, u8)> + '_ {
        self.actions.iter().map(|(id, a)| (*id, *a))
    }

    /// The newest action asked for `id`, if any.
    pub fn action(&self, id: EntityId) -> Option<u8> {
        self.actions.get(&id).copied()
    }

    /// Forgets leaves older than [`LEAVE_MEMORY`] ticks, and the actions of objects no
    /// longer kept (a dead or restarted gateway's players, who send no leave): the book
    /// holds only what live gateways' players need.
    pub fn expire(&mut self, now: u64) {
        self.leaves.retain(|_, at| now.saturating_sub(*at) <= LEAVE_MEMORY);
        let (gateways, since) = (&self.gateways, self.since);
        self.actions.retain(|id, _| keeps(gateways, since, *id, now));
    }

    /// Objects the book holds an action for.
    pub fn tracked(&self) -> usize {
        self.actions.len()
    }
}

impl IntentBook {
    /// The book's whole state as bytes (little-endian; read back by
    /// [`IntentBook::restore`]): what a replay from a checkpoint needs besides the
    /// objects, since a book remembers actions, leaves and gateways from before.
    pub fn snapshot(&self) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&self.since.to_le_bytes());
        let mut gateways: Vec<_> = self.last.iter().collect();
        gateways.sort_by_key(|(g, _)| **g);
        b.extend_from_slice(&(gateways.len() as u32).to_le_bytes());
        for (g, (incarnation, tick, kind)) in gateways {
            let heard = self.gateways.get(g).map_or((0, 0), |h| (h.incarnation, h.at));
            b.extend_from_slice(&g.to_le_bytes());
            for v in [*incarnation, *tick, heard.0, heard.1] {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.push(*kind as u8);
        }
        b.extend_from_slice(&(self.actions.len() as u32).to_le_bytes());
        for (id, a) in &self.actions {
            b.extend_from_slice(&id.0.to_le_bytes());
            b.push(*a);
        }
        b.extend_from_slice(&(self.leaves.len() as u32).to_le_bytes());
        for (id, at) in &self.leaves {
            b.extend_from_slice(&id.0.to_le_bytes());
            b.extend_from_slice(&at.to_le_bytes());
        }
        b.extend_from_slice(&(self.joins.len() as u32).to_le_bytes());
        for j in &self.joins {
            crate::wire::put_record(&mut b, crate::wire::BorderRecord::seen(*j));
        }
        b
    }

    /// A book from [`IntentBook::snapshot`]'s bytes; a clear error on anything else.
    pub fn restore(bytes: &[u8]) -> Result<IntentBook, String> {
        let mut r = Reader { b: bytes, at: 0 };
        let mut book = IntentBook::new(r.u64()?);
        for _ in 0..r.count(35)? {
            let g = r.u16()?;
            let (incarnation, tick, heard, at) = (r.u64()?, r.u64()?, r.u64()?, r.u64()?);
            let kind = match r.u8()? {
                0 => IntentKind::Join,
                1 => IntentKind::Action,
                2 => IntentKind::Leave,
                k => return Err(format!("intent kind {k}")),
            };
            book.last.insert(g, (incarnation, tick, kind));
            book.gateways.insert(g, Heard { incarnation: heard, at });
        }
        for _ in 0..r.count(5)? {
            let (id, a) = (r.u32()?, r.u8()?);
            if myriad_core::Action::from_bits(a).is_none() {
                return Err(format!("action {a}"));
            }
            book.actions.insert(EntityId(id), a);
        }
        for _ in 0..r.count(12)? {
            let (id, at) = (r.u32()?, r.u64()?);
            book.leaves.insert(EntityId(id), at);
        }
        for i in 0..r.count(crate::wire::RECORD_LEN)? {
            let rec = crate::wire::record(i, r.take(crate::wire::RECORD_LEN)?).map_err(|e| e.to_string())?;
            book.joins.push(rec.state);
        }
        if r.at != bytes.len() {
            return Err(format!("{} bytes after the book", bytes.len() - r.at));
        }
        Ok(book)
    }
}

/// Reads a snapshot, failing on a short one.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let s = self.b.get(self.at..self.at + n).ok_or_else(|| format!("the book ends at byte {}", self.b.len()))?;
        self.at += n;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, String> {
        Ok(u16::from_le_bytes(self.take(2)?.try_into().expect("2 bytes")))
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    /// A count of items of `size` bytes each, no more than the bytes left can hold (a
    /// corrupt count never makes a large allocation).
    fn count(&mut self, size: usize) -> Result<usize, String> {
        let n = self.u32()? as usize;
        if n.saturating_mul(size) > self.b.len() - self.at {
            return Err(format!("{n} items of {size} bytes in {} bytes", self.b.len() - self.at));
        }
        Ok(n)
    }
}

/// [`IntentBook::keeps`], on the book's parts.
fn keeps(gateways: &HashMap<u16, Heard>, since: u64, id: EntityId, now: u64) -> bool {
    let Some(g) = gateway_of(id) else { return true };
    match gateways.get(&g) {
        Some(h) => now.saturating_sub(h.at) <= GATEWAY_TIMEOUT && incarnation_ids(g, h.incarnation).contains(&id.0),
        None => now.saturating_sub(since) <= GATEWAY_TIMEOUT,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::{ObjectKind, ShapeKind, Vec3};

    fn player(id: u32, action: u8) -> ObjectState {
        ObjectState {
            id: EntityId(id),
            kind: ObjectKind::User,
            shape: ShapeKind::Capsule,
            half: Vec3::new(0.5, 1.0, 0.5),
            radius: 0.5,
            pos: Vec3::new(1.0, 1.0, 1.0),
            prev: Vec3::new(1.0, 1.0, 1.0),
            action,
            flags: 0,
        }
    }

    fn msg(tick: u64, kind: IntentKind, objects: Vec<ObjectState>) -> Intents {
        Intents { incarnation: 5, tick, gateway: 1, kind, objects }
    }

    /// The id of gateway 1's player `n` (incarnation 5).
    fn p(n: u32) -> u32 {
        incarnation_ids(1, 5).start + n
    }

    #[test]
    fn keeps_the_newest_action_and_refuses_replays() {
        let mut b = IntentBook::default();
        b.offer(msg(1, IntentKind::Join, vec![player(p(7), 0)]), 0).unwrap();
        assert_eq!(b.take_joins().len(), 1);
        assert!(b.take_joins().is_empty(), "a join is taken once");
        b.offer(msg(2, IntentKind::Action, vec![player(p(7), 3)]), 0).unwrap();
        assert_eq!(b.action(EntityId(p(7))), Some(3));
        assert_eq!(b.offer(msg(2, IntentKind::Action, vec![player(p(7), 9)]), 0), Err(Refused::Stale));
        assert_eq!(b.offer(msg(1, IntentKind::Leave, vec![player(p(7), 0)]), 0), Err(Refused::Stale));
        assert_eq!(b.action(EntityId(p(7))), Some(3), "a refused message changes nothing");
        // A restarted gateway (a newer incarnation) starts its ticks again.
        b.offer(Intents { incarnation: 6, ..msg(0, IntentKind::Action, vec![player(p(7), 4)]) }, 0).unwrap();
        assert_eq!(b.action(EntityId(p(7))), Some(4));
    }

    #[test]
    fn a_dead_or_restarted_gateways_players_are_not_kept() {
        let ids = incarnation_ids(1, 5);
        let (a, b) = (EntityId(ids.start), EntityId(ids.start + 1));
        let mut book = IntentBook::new(100);
        assert!(book.keeps(EntityId(5), 10_000), "not a player of any gateway");
        assert!(book.keeps(a, 100 + GATEWAY_TIMEOUT), "a gateway not heard yet has its timeout");
        assert!(!book.keeps(a, 101 + GATEWAY_TIMEOUT));
        book.offer(msg(1, IntentKind::Join, vec![player(a.0, 0), player(b.0, 0)]), 200).unwrap();
        assert!(book.keeps(a, 200 + GATEWAY_TIMEOUT) && book.keeps(b, 200));
        assert!(!book.keeps(a, 201 + GATEWAY_TIMEOUT), "silent for longer than the timeout: dead");
        // The gateway restarts (incarnation 6000 ms: another slot): its earlier players go.
        book.offer(Intents { incarnation: 6_000, ..msg(0, IntentKind::Action, vec![]) }, 220).unwrap();
        assert!(!book.keeps(a, 220) && !book.keeps(b, 220));
        assert!(book.keeps(EntityId(incarnation_ids(1, 6_000).start), 220));
    }

    #[test]
    fn a_dead_gateways_players_leave_no_actions_behind() {
        let ids = incarnation_ids(2, 5);
        let mut book = IntentBook::new(0);
        let players: Vec<_> = (0..100).map(|i| player(ids.start + i, 4)).collect();
        book.offer(Intents { gateway: 2, ..msg(1, IntentKind::Join, players) }, 10).unwrap();
        book.offer(msg(1, IntentKind::Action, vec![player(p(7), 1)]), 100).unwrap();
        book.expire(10 + GATEWAY_TIMEOUT);
        assert_eq!(book.tracked(), 101);
        // Gateway 2 dies (no leave, no message): its players' actions go, gateway 1's stay.
        book.expire(11 + GATEWAY_TIMEOUT);
        assert_eq!(book.tracked(), 1);
        assert_eq!(book.action(EntityId(p(7))), Some(1));
    }

    #[test]
    fn a_gateway_speaks_only_for_its_own_players() {
        let mut b = IntentBook::default();
        let npc = player(12, 3);
        let other = player(incarnation_ids(2, 5).start, 3);
        for objects in [vec![npc], vec![player(p(1), 0), other]] {
            assert_eq!(b.offer(msg(1, IntentKind::Action, objects), 0), Err(Refused::Foreign));
        }
        assert_eq!(b.tracked(), 0, "nothing of a refused message is taken");
        b.offer(msg(1, IntentKind::Action, vec![player(p(1), 3)]), 0).unwrap();
    }

    #[test]
    fn a_snapshot_restores_the_same_book_and_refuses_damage() {
        let mut b = IntentBook::new(7);
        b.offer(msg(1, IntentKind::Join, vec![player(p(1), 2), player(p(2), 0)]), 10).unwrap();
        b.offer(msg(2, IntentKind::Action, vec![player(p(2), 4)]), 11).unwrap();
        b.offer(msg(3, IntentKind::Leave, vec![player(p(3), 0)]), 12).unwrap();
        let bytes = b.snapshot();
        let mut r = IntentBook::restore(&bytes).unwrap();
        assert_eq!(r.snapshot(), bytes, "restored, the book says the same");
        assert_eq!((r.since, r.joins.len(), r.action(EntityId(p(2))), r.left(EntityId(p(3)))), (7, 2, Some(4), true));
        assert_eq!(r.offer(msg(3, IntentKind::Action, vec![]), 13), Err(Refused::Stale), "its order too");
        for cut in 0..bytes.len() {
            assert!(IntentBook::restore(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(IntentBook::restore(&longer).is_err());
        let mut huge = bytes.clone();
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(IntentBook::restore(&huge).is_err(), "a corrupt count is refused, not allocated");
    }

    #[test]
    fn a_leave_outlives_a_hand_off_then_expires() {
        let mut b = IntentBook::default();
        b.offer(msg(1, IntentKind::Action, vec![player(p(7), 3)]), 10).unwrap();
        b.offer(msg(2, IntentKind::Leave, vec![player(p(7), 0)]), 10).unwrap();
        assert!(b.left(EntityId(p(7))));
        assert_eq!(b.action(EntityId(p(7))), None);
        b.offer(msg(3, IntentKind::Action, vec![player(p(7), 5)]), 11).unwrap();
        assert_eq!(b.action(EntityId(p(7))), None, "no action for an object that left");
        b.expire(10 + LEAVE_MEMORY);
        assert!(b.left(EntityId(p(7))));
        b.expire(11 + LEAVE_MEMORY);
        assert!(!b.left(EntityId(p(7))));
    }
}
