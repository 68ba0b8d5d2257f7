//! The tick, driven through the in-memory transport: real sessions, sealed datagrams,
//! the real receive, step, outbound and send, no sockets.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use myriad_core::{Action, ScenarioSpec};
use myriad_physics::{BackendKind, create_cpu_backend};
use myriad_protocol::{
    ActionMask, ClientMessage, ClientSession, DisconnectReason, Opened, PlayerInput, RecordState, ServerMessage,
    StateRecord, UpdateReceiver,
};
use myriad_store::{PlayerState, UserId};

use super::{Command, StateSink, TickLoop};
use crate::config::ServerConfig;
use crate::transport::{GateCounts, Lane, MemoryTransport, Sent, Transport};

/// Collects the states the tick persists.
#[derive(Clone, Default)]
struct Saved(Arc<Mutex<Vec<PlayerState>>>);

impl StateSink for Saved {
    fn submit(&self, states: &[PlayerState]) -> Result<(), String> {
        self.0.lock().unwrap().extend_from_slice(states);
        Ok(())
    }
}

struct Rig {
    tick: TickLoop,
    net: MemoryTransport,
    commands: std::sync::mpsc::Sender<Command>,
    saved: Saved,
}

struct Client {
    session: ClientSession,
    addr: SocketAddr,
    entity: u64,
    frame: u32,
}

fn rig(config: ServerConfig) -> Rig {
    let net = MemoryTransport::new("127.0.0.1:7777".parse().unwrap());
    rig_on(config, Box::new(net.clone()), net)
}

/// A rig whose tick receives through `transport`, which hands over what reaches `net`.
fn rig_on(config: ServerConfig, transport: Box<dyn Transport>, net: MemoryTransport) -> Rig {
    let world = ScenarioSpec::custom(11).counts(300, 0, 30).map_size(96.0, 33).build().unwrap();
    let (commands, receiver) = std::sync::mpsc::channel();
    let saved = Saved::default();
    let backend = create_cpu_backend(BackendKind::Cpu).unwrap();
    let tick = TickLoop::builder(config, world, backend, transport)
        .commands(receiver)
        .persister(Box::new(saved.clone()), myriad_store::MapId(1))
        .build();
    Rig { tick, net, commands, saved }
}

impl Rig {
    /// Logs `user` in through the join channel (one tick), then sends `Ready` from
    /// `port` (one more tick).
    fn join(&mut self, user: i64, port: u16) -> Client {
        let (reply, mut answer) = tokio::sync::oneshot::channel();
        let cmd = Command::Join { user_id: UserId(user), username: format!("user{user}"), state: None, reply };
        self.commands.send(cmd).unwrap();
        self.tick.tick_once();
        let joined = answer.try_recv().unwrap().unwrap();
        let mut c = Client {
            session: ClientSession::new(&joined.keys),
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
            entity: joined.entity,
            frame: 0,
        };
        self.send(&mut c, &ClientMessage::Ready);
        self.tick.tick_once();
        c
    }

    fn seal(c: &mut Client, msg: &ClientMessage) -> Vec<u8> {
        let mut d = Vec::new();
        c.session.seal(msg, &mut d).unwrap();
        d
    }

    fn send(&self, c: &mut Client, msg: &ClientMessage) -> Vec<u8> {
        let d = Self::seal(c, msg);
        self.net.push(c.addr, d.clone());
        d
    }

    fn action(&self, c: &mut Client, mask: u8) -> Vec<u8> {
        c.frame += 1;
        let input = PlayerInput { mask: ActionMask::new(mask).unwrap(), client_frame: c.frame };
        self.send(c, &ClientMessage::Action { input, acks: None })
    }

    fn action_of(&self, c: &Client) -> Action {
        let d = &self.tick.world().dynamics;
        Action::from_bits_truncate(d.actions()[d.slot(myriad_core::EntityId(c.entity as u32)).unwrap()])
    }

    /// Everything sent to `c` since the last call, opened with its session.
    fn received(&self, sent: &[(SocketAddr, Vec<u8>)], c: &mut Client) -> Vec<Opened<ServerMessage>> {
        sent.iter()
            .filter(|(to, _)| *to == c.addr)
            .map(|(_, d)| c.session.open(&mut d.clone()).expect("every datagram opens"))
            .collect()
    }
}

#[test]
fn the_tick_counter_advances_once_per_tick() {
    let mut r = rig(ServerConfig::default());
    for expected in 1..=5 {
        r.tick.tick_once();
        assert_eq!(r.tick.world().tick, expected);
    }
}

#[test]
fn an_action_is_applied_on_the_next_tick() {
    let mut r = rig(ServerConfig::default());
    let mut c = r.join(1, 40_001);
    assert_eq!(r.action_of(&c), Action::NONE);
    let d = &r.tick.world().dynamics;
    let start = d.positions()[d.slot(myriad_core::EntityId(c.entity as u32)).unwrap()];
    r.action(&mut c, ActionMask::FORWARD);
    assert_eq!(r.action_of(&c), Action::NONE, "nothing happens before the tick");
    let work = r.tick.tick_once();
    assert_eq!(work.actions, 1);
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD);
    for _ in 0..20 {
        r.tick.tick_once();
    }
    let d = &r.tick.world().dynamics;
    let end = d.positions()[d.slot(myriad_core::EntityId(c.entity as u32)).unwrap()];
    assert!(end.z > start.z + 0.5, "forward is +z: {start} -> {end}");
    // An older frame arriving late is ignored.
    c.frame = c.frame.wrapping_sub(5);
    r.action(&mut c, ActionMask::BACK);
    assert_eq!(r.tick.tick_once().actions, 0);
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD);
}

#[test]
fn a_jump_in_any_action_of_a_tick_is_not_cancelled_by_a_newer_one() {
    let mut r = rig(ServerConfig::default());
    let mut c = r.join(1, 40_001);
    // A tap of jump shorter than a frame: one action with it, the next without, both
    // taken in the same tick.
    r.action(&mut c, ActionMask::FORWARD | ActionMask::JUMP);
    r.action(&mut c, ActionMask::FORWARD);
    assert_eq!(r.tick.tick_once().actions, 2);
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD | Action::JUMP, "the jump stays asked for");
    // In the next tick the newest action counts as it is.
    r.action(&mut c, ActionMask::FORWARD);
    r.tick.tick_once();
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD);
}

#[test]
fn replayed_and_forged_datagrams_change_nothing() {
    let mut r = rig(ServerConfig::default());
    let mut c = r.join(1, 40_001);
    let first = r.action(&mut c, ActionMask::FORWARD);
    assert_eq!(r.tick.tick_once().actions, 1);
    r.net.take_sent();
    let hash_of = |r: &Rig| r.tick.world().state_hash();

    // A twin that receives nothing steps in lockstep: any change from a bad datagram
    // would show in the hash.
    let mut twin = rig(ServerConfig::default());
    let mut tc = twin.join(1, 40_001);
    twin.action(&mut tc, ActionMask::FORWARD);
    twin.tick.tick_once();
    twin.net.take_sent();
    assert_eq!(hash_of(&r), hash_of(&twin));

    let attacker: SocketAddr = "127.0.0.1:50000".parse().unwrap();
    // The same datagram again, from the player's address and from another one.
    r.net.push(c.addr, first.clone());
    r.net.push(attacker, first.clone());
    // A forged one: the live session id and a fresh sequence, but a wrong tag.
    let mut forged = Rig::seal(
        &mut c,
        &ClientMessage::Action {
            input: PlayerInput { mask: ActionMask::new(ActionMask::BACK).unwrap(), client_frame: 99 },
            acks: None,
        },
    );
    let n = forged.len();
    forged[n - 1] ^= 1;
    r.net.push(attacker, forged);
    // Garbage and a truncated header.
    r.net.push(attacker, vec![0xff; 40]);
    r.net.push(attacker, first[..10].to_vec());

    let work = r.tick.tick_once();
    twin.tick.tick_once();
    assert_eq!(work.received, 5);
    assert_eq!(work.actions, 0);
    assert_eq!(hash_of(&r), hash_of(&twin), "the world is as if nothing arrived");
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD);
    let sent = r.net.take_sent();
    assert!(sent.iter().all(|(to, _)| *to != attacker), "nothing goes to the sender of bad datagrams");
    let p = r.tick.sessions().iter().next().unwrap();
    assert_eq!(p.addr, Some(c.addr), "the player's address did not move");
}

#[test]
fn a_second_login_replaces_the_first_session() {
    let mut r = rig(ServerConfig::default());
    let mut old = r.join(7, 40_001);
    r.net.take_sent();
    let mut new = r.join(7, 40_002);
    assert_eq!(new.entity, old.entity, "the object stays");
    assert_eq!(r.tick.sessions().len(), 1);
    let sent = r.net.take_sent();
    let to_old = r.received(&sent, &mut old);
    assert!(
        to_old.iter().any(|o| o.message == ServerMessage::Disconnect(DisconnectReason::Replaced)),
        "the old session is told it was replaced"
    );
    // The old session's keys no longer move the object; the new one's do.
    r.action(&mut old, ActionMask::LEFT);
    assert_eq!(r.tick.tick_once().actions, 0);
    r.action(&mut new, ActionMask::RIGHT);
    assert_eq!(r.tick.tick_once().actions, 1);
    assert_eq!(r.action_of(&new).bits(), Action::RIGHT);
}

#[test]
fn a_silent_session_expires_and_its_player_is_saved() {
    let config = ServerConfig { session_timeout_s: 1.0, ..ServerConfig::default() };
    let mut r = rig(config);
    let mut c = r.join(3, 40_001);
    let objects = r.tick.world().dynamics.len();
    r.saved.0.lock().unwrap().clear();
    r.net.take_sent();
    std::thread::sleep(Duration::from_millis(1100));
    r.tick.tick_once();
    assert_eq!(r.tick.sessions().len(), 0);
    assert_eq!(r.tick.world().dynamics.len(), objects - 1, "its object left the world");
    let saved = r.saved.0.lock().unwrap().clone();
    assert_eq!(saved.len(), 1);
    assert_eq!(saved[0].user_id, UserId(3));
    let sent = r.net.take_sent();
    let got = r.received(&sent, &mut c);
    assert!(got.iter().any(|o| o.message == ServerMessage::Disconnect(DisconnectReason::Timeout)));
}

#[test]
fn every_update_datagram_of_a_player_contains_its_own_object() {
    // A big view and a budget larger than two datagrams: the view spans both.
    let config = ServerConfig {
        aoi_size: 400.0,
        max_datagrams_per_player: 2,
        send_budget_kbps: 2000.0,
        ..ServerConfig::default()
    };
    let mut r = rig(config);
    let mut clients: Vec<Client> = (0..4).map(|i| r.join(i + 1, 40_001 + i as u16)).collect();
    let mut updates = 0;
    let mut multi = 0;
    for _ in 0..10 {
        r.tick.tick_once();
        let sent = r.net.take_sent();
        for c in &mut clients {
            let mut this_tick = 0;
            for o in r.received(&sent, c) {
                if let ServerMessage::StateUpdate(u) = o.message {
                    updates += 1;
                    this_tick += 1;
                    assert!(u.records.iter().any(|rec| rec.id == c.entity), "datagram without the player's own object");
                }
            }
            assert!(this_tick >= 1, "an update every tick");
            multi += usize::from(this_tick > 1);
        }
    }
    assert!(updates > 40 && multi > 0, "the view spans several datagrams: {updates} updates, {multi} multi");
}

/// Opens what `sent` holds for `c` and resolves its updates against `baselines`,
/// recording in `acks` the datagrams whose every record resolved; returns the resolved
/// records, how many records were relative (`Delta` or `Same`) and how many could not
/// be resolved.
fn resolve(
    r: &Rig,
    sent: &[(SocketAddr, Vec<u8>)],
    c: &mut Client,
    receiver: &mut UpdateReceiver,
) -> (Vec<StateRecord>, usize, usize) {
    let (mut records, mut relative, mut unresolved) = (Vec::new(), 0, 0);
    for o in r.received(sent, c) {
        if let ServerMessage::StateUpdate(u) = o.message {
            relative += u.records.iter().filter(|x| !matches!(x.state, RecordState::Absolute { .. })).count();
            unresolved += receiver.receive_update(o.header.sequence, &u, &mut records);
        }
    }
    (records, relative, unresolved)
}

#[test]
fn acknowledged_states_make_the_next_updates_relative() {
    let mut r = rig(ServerConfig { aoi_size: 400.0, send_budget_kbps: 2000.0, ..ServerConfig::default() });
    let mut acking = r.join(1, 40_001);
    let mut silent = r.join(2, 40_002);
    let mut receiver = UpdateReceiver::default();
    let (mut relative_acking, mut relative_silent, mut absolute_silent) = (0, 0, 0);
    for t in 0..40 {
        r.tick.tick_once();
        let sent = r.net.take_sent();
        let (records, relative, unresolved) = resolve(&r, &sent, &mut acking, &mut receiver);
        assert_eq!(unresolved, 0, "tick {t}: a client that acknowledges only what it resolved resolves everything");
        assert!(records.iter().any(|x| x.id == acking.entity), "tick {t}: the own object");
        if t >= 20 {
            relative_acking += relative;
        }
        // The other client receives but never acknowledges (its keep-alives say so).
        let (records, relative, _) = resolve(&r, &sent, &mut silent, &mut UpdateReceiver::default());
        relative_silent += relative;
        absolute_silent += records.len();
        let keep_alive = ClientMessage::KeepAlive { acks: receiver.acks() };
        r.send(&mut acking, &keep_alive);
        r.send(&mut silent, &ClientMessage::KeepAlive { acks: None });
    }
    assert!(relative_acking > 100, "deltas against acknowledged states: {relative_acking}");
    assert_eq!(relative_silent, 0, "nothing is relative to a state never acknowledged");
    assert!(absolute_silent > 100, "the silent client still gets absolute states: {absolute_silent}");
}

/// A datagram with `c`'s live session id and a fresh sequence number but a wrong tag:
/// what anyone who knows (or sniffed) a session id can send.
fn forged(c: &mut Client) -> Vec<u8> {
    let mut d = Rig::seal(c, &ClientMessage::KeepAlive { acks: None });
    let n = d.len();
    d[n - 1] ^= 1;
    d
}

// Issue 14: every datagram naming a live session cost a Poly1305 check; a flood of them
// from one socket brought the tick from 30 to 5 per second.
#[test]
fn a_flood_on_a_live_session_costs_at_most_its_budget_of_tag_checks() {
    let config = ServerConfig { receive_per_session: 8, receive_other_address: 2, ..ServerConfig::default() };
    let mut r = rig(config);
    let mut victim = r.join(1, 40_001);
    let mut attacker = r.join(2, 40_002);
    r.net.take_sent();
    // The attacker floods its own session from its own address, and the victim's
    // session from its own address too (a different address from the victim's).
    for _ in 0..500 {
        let d = forged(&mut attacker);
        r.net.push(attacker.addr, d);
        let d = forged(&mut victim);
        r.net.push(attacker.addr, d);
    }
    // The victim's own action arrives last, behind the whole flood.
    r.action(&mut victim, ActionMask::RIGHT);
    let work = r.tick.tick_once();
    assert_eq!(work.received, 1001);
    assert_eq!(
        work.tag_checks,
        8 + 2 + 1,
        "own budget of the attacker, other-address budget of the victim, the action"
    );
    assert_eq!(work.over_budget, 1001 - 11);
    assert_eq!(work.actions, 1, "the victim's own datagram still gets in");
    assert_eq!(r.action_of(&victim).bits(), Action::RIGHT);
    // The budget is per tick: the next tick serves both again.
    r.action(&mut victim, ActionMask::LEFT);
    r.action(&mut attacker, ActionMask::LEFT);
    let work = r.tick.tick_once();
    assert_eq!((work.tag_checks, work.actions, work.over_budget), (2, 2, 0));
}

#[test]
fn a_session_floods_only_itself() {
    let mut r = rig(ServerConfig { receive_per_session: 4, ..ServerConfig::default() });
    let mut a = r.join(1, 40_001);
    let mut b = r.join(2, 40_002);
    for _ in 0..100 {
        let d = forged(&mut a);
        r.net.push(a.addr, d);
    }
    r.action(&mut a, ActionMask::FORWARD);
    r.action(&mut b, ActionMask::FORWARD);
    let work = r.tick.tick_once();
    assert_eq!(work.tag_checks, 4 + 1);
    assert_eq!(work.actions, 1, "the flooder's own action is crowded out, the other player's is not");
    assert_eq!(r.action_of(&b).bits(), Action::FORWARD);
    assert_eq!(r.action_of(&a), Action::NONE);
}

#[test]
fn a_changed_dilation_is_announced_to_ready_players() {
    let mut r = rig(ServerConfig::default());
    let mut c = r.join(1, 40_001);
    r.tick.tick_once();
    r.net.take_sent();
    r.tick.announce_server_info();
    r.tick.tick_once();
    let sent = r.net.take_sent();
    let infos: Vec<_> =
        r.received(&sent, &mut c).into_iter().filter(|o| matches!(o.message, ServerMessage::ServerInfo(_))).collect();
    assert_eq!(infos.len(), 1, "one ServerInfo with the tick's updates");
}

/// A cluster's session registry, by hand: what was claimed, and names to hand back as
/// taken by another server.
#[derive(Clone, Default)]
struct Cluster(Arc<Mutex<(Vec<String>, Vec<String>)>>);

impl crate::registry::SessionRegistry for Cluster {
    fn claim(&mut self, username: &str) {
        self.0.lock().unwrap().0.push(username.to_string());
    }
    fn taken(&mut self) -> Vec<String> {
        std::mem::take(&mut self.0.lock().unwrap().1)
    }
}

#[test]
fn a_login_at_another_server_of_the_cluster_replaces_the_session() {
    let mut r = rig(ServerConfig::default());
    let cluster = Cluster::default();
    r.tick.registry = Some(Box::new(cluster.clone()));
    let mut c = r.join(5, 40_001);
    let _other = r.join(6, 40_002);
    assert_eq!(cluster.0.lock().unwrap().0, ["user5", "user6"], "every admitted session is claimed");
    r.net.take_sent();
    // Names compare without case; a name held by no session here changes nothing.
    cluster.0.lock().unwrap().1.extend(["USER5".to_string(), "nobody".to_string()]);
    r.tick.tick_once();
    assert_eq!(r.tick.sessions().len(), 1, "user5's session ended, user6's stays");
    let sent = r.net.take_sent();
    assert!(
        r.received(&sent, &mut c).iter().any(|o| o.message == ServerMessage::Disconnect(DisconnectReason::Replaced)),
        "the session is told it was replaced"
    );
    assert!(r.saved.0.lock().unwrap().iter().any(|s| s.user_id == UserId(5)), "its position is saved");
}

/// Enough datagrams for a batch's tag checks to run on the rayon pool.
const PARALLEL: usize = crate::inbound::PARALLEL_OPEN_MIN;

#[test]
fn a_parallel_batch_accepts_a_datagram_twice_in_it_once_and_a_forged_one_never() {
    let config = ServerConfig { receive_per_session: 1024, ..ServerConfig::default() };
    let mut r = rig(config);
    let mut c = r.join(1, 40_001);
    r.net.take_sent();
    for _ in 0..PARALLEL {
        r.send(&mut c, &ClientMessage::KeepAlive { acks: None });
    }
    // Copies in the same batch as their originals: a player's datagrams are opened one at
    // a time, so the window must refuse each second copy. (The action's copy would be
    // ignored as an old frame anyway; a keep-alive's would be answered twice.)
    let action = r.action(&mut c, ActionMask::LEFT);
    r.net.push(c.addr, action);
    let keep_alive = r.send(&mut c, &ClientMessage::KeepAlive { acks: None });
    r.net.push(c.addr, keep_alive);
    let mut forged = Rig::seal(
        &mut c,
        &ClientMessage::Action {
            input: PlayerInput { mask: ActionMask::new(ActionMask::BACK).unwrap(), client_frame: 99 },
            acks: None,
        },
    );
    let n = forged.len();
    forged[n - 1] ^= 1;
    r.net.push(c.addr, forged);

    let work = r.tick.tick_once();
    assert_eq!(work.received, PARALLEL as u64 + 5);
    assert_eq!(work.tag_checks, PARALLEL as u64 + 5, "all of them reached the opener, in one parallel batch");
    assert_eq!(work.actions, 1, "the action once, the copy and the forgery never");
    assert_eq!(r.action_of(&c).bits(), Action::LEFT);
    let sent = r.net.take_sent();
    let keep_alives = r.received(&sent, &mut c).iter().filter(|o| o.message == ServerMessage::KeepAlive).count();
    assert_eq!(keep_alives, PARALLEL + 1, "one reply per keep-alive, none for the copy");
}

// The gate's budgets depend on the player's address, which an accepted datagram from a
// new address moves: what comes after it must be gated as if one at a time.
#[test]
fn a_parallel_batch_follows_an_address_that_moves_in_it() {
    let config = ServerConfig { receive_per_session: 1024, receive_other_address: 1, ..ServerConfig::default() };
    let mut r = rig(config);
    let mut c = r.join(1, 40_001);
    r.net.take_sent();
    for _ in 0..PARALLEL {
        r.send(&mut c, &ClientMessage::KeepAlive { acks: None });
    }
    // The player's NAT mapping changes: the rest comes from a new port.
    c.addr = SocketAddr::from(([127, 0, 0, 1], 40_101));
    for _ in 0..5 {
        r.send(&mut c, &ClientMessage::KeepAlive { acks: None });
    }
    let work = r.tick.tick_once();
    assert_eq!(work.over_budget, 0, "once the first from the new address is in, it is the player's own");
    assert_eq!(work.tag_checks, PARALLEL as u64 + 5);
    let p = r.tick.sessions().iter().next().unwrap();
    assert_eq!(p.addr, Some(c.addr));
}

/// A batch of many players' datagrams applies each player's part on the pool (module
/// docs of `inbound`): a player's datagrams, far apart in the batch, still apply in
/// arrival order (a newer frame wins, an older one is ignored, a jump taken in the tick
/// stays, a copy is refused), and what players share (the world's actions, the replies,
/// who leaves) is what one datagram at a time would give.
#[test]
fn a_parallel_batch_of_many_players_applies_each_players_datagrams_in_arrival_order() {
    many_players_in_one_batch(rig(ServerConfig { receive_per_session: 16, ..ServerConfig::default() }));
}

/// Behind a receiver thread (which gated already) the batch's sessions are looked up on
/// the pool too (phase 1): the same datagrams give the same decisions, and what has no
/// header or no session is still refused.
#[test]
fn behind_a_receiver_thread_a_large_batch_is_admitted_on_the_pool_in_arrival_order() {
    let net = MemoryTransport::new("127.0.0.1:7777".parse().unwrap());
    let transport = PreGated { net: net.clone(), taken: 0 };
    many_players_in_one_batch(rig_on(ServerConfig::default(), Box::new(transport), net));
}

/// The in-memory transport as if a receiver thread had gated what reaches it: everything
/// queued in one call, and no gate in the tick.
struct PreGated {
    net: MemoryTransport,
    taken: u64,
}

impl Transport for PreGated {
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &[u8])) -> std::io::Result<usize> {
        let mut n = 0;
        while let k @ 1.. = self.net.receive(each)? {
            n += k;
        }
        self.taken += n as u64;
        Ok(n)
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> std::io::Result<Sent> {
        self.net.send(out)
    }

    fn lanes(&mut self) -> Vec<&mut dyn Lane> {
        self.net.lanes()
    }

    fn local_addr(&self) -> SocketAddr {
        self.net.local_addr()
    }

    fn gates(&self) -> bool {
        true
    }

    fn gate_counts(&mut self) -> GateCounts {
        GateCounts { taken: std::mem::take(&mut self.taken), over_budget: 0 }
    }
}

/// Players' datagrams in two rounds (each player's second long after its first), with
/// datagrams of no session and no header among them, in one receive; see the tests
/// above.
fn many_players_in_one_batch(mut r: Rig) {
    let n = PARALLEL + 21;
    let mut clients: Vec<Client> = (0..n).map(|i| r.join(i as i64 + 1, 41_000 + i as u16)).collect();
    r.net.take_sent();
    let input = |mask: u8, frame: u32| ClientMessage::Action {
        input: PlayerInput { mask: ActionMask::new(mask).unwrap(), client_frame: frame },
        acks: None,
    };
    // Its second datagram is a Disconnect instead of its second action (5 % 4 == 1).
    let leaver = 5;
    let mut copies = Vec::new();
    // Two rounds over every player, so that each player's second datagram comes long
    // after its first.
    for (i, c) in clients.iter_mut().enumerate() {
        match i % 4 {
            0 => drop(r.send(c, &input(ActionMask::FORWARD, 1))),
            1 => drop(r.send(c, &input(ActionMask::FORWARD | ActionMask::JUMP, 1))),
            2 => drop(r.send(c, &input(ActionMask::BACK, 2))),
            _ => copies.push((c.addr, r.send(c, &ClientMessage::KeepAlive { acks: None }))),
        }
    }
    // Strays: a session nobody holds, and no header at all.
    let stranger = SocketAddr::from(([127, 0, 0, 1], 40_999));
    let keys =
        myriad_protocol::SessionKeys { session_id: 987_654_321, client_to_server: [1; 32], server_to_client: [2; 32] };
    let mut nobody = ClientSession::new(&keys);
    let strays = 20;
    for _ in 0..strays / 2 {
        let mut d = Vec::new();
        nobody.seal(&ClientMessage::KeepAlive { acks: None }, &mut d).unwrap();
        r.net.push(stranger, d);
        r.net.push(stranger, b"junk".to_vec());
    }
    for (i, c) in clients.iter_mut().enumerate() {
        match i % 4 {
            _ if i == leaver => drop(r.send(c, &ClientMessage::Disconnect)),
            0 => {}
            1 => drop(r.send(c, &input(ActionMask::LEFT, 2))),
            2 => drop(r.send(c, &input(ActionMask::RIGHT, 1))),
            _ => {}
        }
    }
    for (addr, copy) in copies {
        r.net.push(addr, copy);
    }
    let count = |k: usize| (0..n).filter(|i| i % 4 == k).count();
    let work = r.tick.tick_once();
    let datagrams = (n + count(1) + count(2) + count(3)) as u64;
    assert_eq!(work.received, datagrams + strays);
    assert_eq!(work.tag_checks, datagrams, "every one reached the window, in one parallel batch");
    // Every first action, and the second where its frame is newer (the leaver's second
    // datagram is its Disconnect).
    let actions = count(0) + count(1) + count(2) + count(1) - 1;
    assert_eq!(work.actions, actions as u64, "every newer frame, no older one");
    let sent = r.net.take_sent();
    for (i, c) in clients.iter_mut().enumerate() {
        if i == leaver {
            continue;
        }
        let expected = match i % 4 {
            0 => Action::FORWARD,
            1 => Action::LEFT | Action::JUMP,
            2 => Action::BACK,
            _ => 0,
        };
        assert_eq!(r.action_of(c).bits(), expected, "player {i}");
        let replies = r.received(&sent, c).iter().filter(|o| o.message == ServerMessage::KeepAlive).count();
        assert_eq!(replies, usize::from(i % 4 == 3), "player {i}: one reply to its keep-alive, none to the copy");
    }
    assert_eq!(r.tick.sessions().len(), n - 1, "the player who asked to leave left");
}

/// The client resends Ready until its session starts (docs/protocol.md §7a), so a Ready
/// may arrive again, late or twice, after the player moved: it is the same Ready. No
/// second join, nothing reset (object, action, newest frame), no Disconnect; a replayed
/// copy of the datagram is dropped; each Ready is answered with ServerInfo, never with
/// more bytes than the address sent (protocol §6.2).
#[test]
fn a_repeated_ready_resets_nothing_and_is_answered_within_what_was_received() {
    let mut r = rig(ServerConfig::default());
    let mut c = r.join(1, 40_001);
    let infos = |got: &[Opened<ServerMessage>]| {
        got.iter().filter(|o| matches!(o.message, ServerMessage::ServerInfo(_))).count()
    };
    // Control replies to the player (not state updates) and what they said.
    let mut replies = 0;
    let mut take = |r: &mut Rig, c: &mut Client| {
        let sent = r.net.take_sent();
        replies += sent
            .iter()
            .filter(|(to, d)| *to == c.addr && d[1] != myriad_protocol::PacketKind::StateUpdate as u8)
            .map(|(_, d)| d.len())
            .sum::<usize>();
        r.received(&sent, c)
    };
    assert_eq!(infos(&take(&mut r, &mut c)), 0, "a 38-byte ServerInfo does not answer the 34-byte first Ready alone");
    let mut received = 34;
    received += r.action(&mut c, ActionMask::FORWARD).len();
    for _ in 0..10 {
        r.tick.tick_once();
    }
    assert_eq!(infos(&take(&mut r, &mut c)), 1, "the first Ready is answered once the action brought credit");
    let objects = r.tick.world().dynamics.len();
    let d = &r.tick.world().dynamics;
    let before = d.positions()[d.slot(myriad_core::EntityId(c.entity as u32)).unwrap()];

    let again = r.send(&mut c, &ClientMessage::Ready);
    r.net.push(c.addr, again.clone());
    received += again.len();
    let work = r.tick.tick_once();
    assert_eq!(work.tag_checks, 2, "both copies reached the window");
    assert_eq!(r.tick.sessions().len(), 1, "no second join");
    assert_eq!(r.tick.world().dynamics.len(), objects, "no second object");
    assert_eq!(r.action_of(&c).bits(), Action::FORWARD, "the held action stays");
    let p = r.tick.sessions().iter().next().unwrap();
    assert!(p.ready && p.addr == Some(c.addr));
    let got = take(&mut r, &mut c);
    assert_eq!(infos(&got), 1, "the resent Ready is answered; its replayed copy is not");
    assert!(got.iter().all(|o| !matches!(o.message, ServerMessage::Disconnect(_))));
    // The newest frame stays too: an action of an older frame is still ignored.
    c.frame -= 1;
    received += r.action(&mut c, ActionMask::BACK).len();
    assert_eq!(r.tick.tick_once().actions, 0);
    let d = &r.tick.world().dynamics;
    let after = d.positions()[d.slot(myriad_core::EntityId(c.entity as u32)).unwrap()];
    assert!(after.z > before.z, "it kept walking forward: {before} -> {after}");
    take(&mut r, &mut c);
    assert!(replies <= received, "replies {replies} B, received {received} B");
}

#[test]
fn a_lane_some_thread_holds_is_passed_over_for_a_free_one() {
    let addr = |port| SocketAddr::from(([127, 0, 0, 1], port));
    let mut lanes: Vec<MemoryTransport> = (1..=3).map(|port| MemoryTransport::new(addr(port))).collect();
    let queues = lanes.clone();
    // Which lane the last transmit went out on.
    let last = || queues.iter().position(|q| !q.take_sent().is_empty());
    let sender = super::Sender::new(lanes.iter_mut().map(|l| l as &mut dyn Lane).collect(), 5);
    let out = [(addr(9), &b"x"[..])];
    let busy = sender.lanes[1].lock().unwrap();
    sender.free_lane(1).transmit(&out).unwrap();
    assert_eq!(last(), Some(2), "lane 1 is held: the next free one");
    let busy_too = sender.lanes[2].lock().unwrap();
    sender.free_lane(2).transmit(&out).unwrap();
    assert_eq!(last(), Some(0), "lanes 1 and 2 are held: round to lane 0");
    drop((busy, busy_too));
    sender.free_lane(1).transmit(&out).unwrap();
    assert_eq!(last(), Some(1), "all free: the preferred lane");
}
