//! The server driven by an [`ActionScript`] through an in-memory transport: the check
//! that the server's tick and `myriad sim --actions` compute the same world.
//!
//! Every object the script drives becomes a player with a fresh session (admitted as a
//! login would, minus TLS), played by a client that holds the session's client half.
//! Before each tick the clients seal the script's actions of that tick and push them
//! into the transport; the server receives, opens and applies them through its real
//! receive path, steps, builds and seals updates, which the clients open. Nothing but
//! the datagrams reaches the world, so the final state hash equals `myriad sim`'s on
//! the same scenario, seed, ticks and script exactly when the server applies actions on
//! the next tick and counts ticks as the simulation does.
//!
//! ```
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use myriad_core::{ActionScript, PhysicsConfig, ScenarioSpec};
//! use myriad_physics::{BackendKind, TickConstants, create_cpu_backend};
//!
//! let mut spec = ScenarioSpec::custom(5);
//! (spec.dynamic, spec.users, spec.static_objects, spec.world_size, spec.terrain_samples) = (200, 10, 20, 64.0, 17);
//! let world = spec.build()?;
//! let script = ActionScript::walkers(&world, 10, 40, 1);
//!
//! // The simulation, as `myriad sim --actions` runs it.
//! let mut sim = world.clone();
//! let mut backend = create_cpu_backend(BackendKind::Cpu)?;
//! let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
//! for _ in 0..40 {
//!     script.apply(&mut sim)?;
//!     backend.step(&mut sim, &k)?;
//! }
//!
//! // The server, fed the same actions as sealed datagrams.
//! let run = myriad_server::scripted::run(
//!     myriad_server::ServerConfig::default(),
//!     world,
//!     create_cpu_backend(BackendKind::Cpu)?,
//!     &script,
//!     40,
//! )?;
//! assert_eq!(run.world.tick, 40);
//! assert_eq!(run.world.state_hash(), sim.state_hash());
//! # Ok(()) }
//! ```

use std::collections::HashMap;
use std::net::SocketAddr;

use myriad_core::{ActionScript, World};
use myriad_physics::Backend;
use myriad_protocol::{
    ActionMask, ClientMessage, ClientSession, PlayerInput, ServerMessage, StateRecord, UpdateHeader, UpdateReceiver,
};
use myriad_store::UserId;

use crate::config::ServerConfig;
use crate::error::ServerError;
use crate::tick::TickLoop;
use crate::transport::MemoryTransport;

/// What a scripted run ended with.
#[derive(Debug)]
pub struct ScriptedRun {
    /// The world after the last tick.
    pub world: World,
    /// Actions the server applied to the world.
    pub actions_applied: u64,
    /// Datagrams the clients received and opened.
    pub datagrams_opened: u64,
    /// Datagrams a client received but could not open (always 0 unless broken).
    pub rejected: u64,
    /// State updates that lacked the receiving player's own object (always 0).
    pub updates_without_own: u64,
    /// Delta records a client could not resolve (always 0: a client acknowledges only
    /// datagrams it resolved whole, with its next action).
    pub unresolved: u64,
    /// A hash of every state every client received: per tick, each player's records
    /// resolved against its baselines (with their update's header: tick, dilation,
    /// origin) sorted by id, players in entity order. Two runs whose clients saw the same
    /// thing have the same hash, however the server ordered its datagrams.
    pub records_hash: u64,
    /// Bytes of the datagrams sent to the clients, per tick.
    pub bytes_out: Vec<u64>,
}

struct Client {
    session: ClientSession,
    entity: u64,
    frame: u32,
    /// Its baselines and acknowledgements.
    receiver: UpdateReceiver,
}

/// Runs `ticks` server ticks on `world` with the script's actions; see the module docs.
/// Session timeouts are wall-clock and no part of the world, so the harness turns them
/// off (a slow machine must not change the result).
pub fn run(
    mut config: ServerConfig,
    world: World,
    backend: Box<dyn Backend>,
    script: &ActionScript,
    ticks: u64,
) -> Result<ScriptedRun, ServerError> {
    config.session_timeout_s = 1.0e9;
    config.validate()?;
    let transport = MemoryTransport::new(SocketAddr::from(([127, 0, 0, 1], 7777)));
    let mut tick = TickLoop::builder(config, world, backend, Box::new(transport.clone())).build();
    let mut clients: HashMap<SocketAddr, Client> = HashMap::new();
    let mut by_entity: HashMap<u32, SocketAddr> = HashMap::new();
    let entities = script.entities();
    let adopted = tick.adopt_all(entities.iter().enumerate().map(|(i, &entity)| (UserId(i as i64 + 1), entity)));
    for (i, (entity, joined)) in entities.into_iter().zip(adopted).enumerate() {
        let joined =
            joined.map_err(|r| ServerError::Internal(format!("admitting the player of entity {}: {r:?}", entity.0)))?;
        let addr = SocketAddr::from(([127, 0, 0, 1], 20_000 + i as u16));
        let mut client = Client {
            session: ClientSession::new(&joined.keys),
            entity: joined.entity,
            frame: 0,
            receiver: UpdateReceiver::default(),
        };
        push(&transport, addr, &mut client, &ClientMessage::Ready)?;
        clients.insert(addr, client);
        by_entity.insert(entity.0, addr);
    }
    let (mut actions_applied, mut datagrams_opened, mut rejected, mut updates_without_own) = (0, 0, 0, 0);
    let (mut unresolved, mut resolved) = (0, Vec::new());
    let (mut records_hash, mut bytes_out) = (std::hash::DefaultHasher::new(), Vec::new());
    for _ in 0..ticks {
        for a in script.at(tick.world().tick) {
            let addr = by_entity[&a.entity.0];
            let client = clients.get_mut(&addr).ok_or_else(|| ServerError::Internal("client lost".into()))?;
            client.frame = client.frame.wrapping_add(1);
            let input =
                PlayerInput { mask: ActionMask::new(a.action.bits()).unwrap_or_default(), client_frame: client.frame };
            let acks = client.receiver.acks();
            push(&transport, addr, client, &ClientMessage::Action { input, acks })?;
        }
        actions_applied += tick.tick_once().actions;
        let mut seen: std::collections::BTreeMap<u64, Vec<(UpdateHeader, StateRecord)>> = Default::default();
        bytes_out.push(0);
        for (to, mut datagram) in transport.take_sent() {
            let Some(client) = clients.get_mut(&to) else { continue };
            *bytes_out.last_mut().expect("pushed") += datagram.len() as u64;
            match client.session.open(&mut datagram) {
                Ok(opened) => {
                    datagrams_opened += 1;
                    if let ServerMessage::StateUpdate(u) = opened.message {
                        resolved.clear();
                        let missing = client.receiver.receive_update(opened.header.sequence, &u, &mut resolved);
                        unresolved += missing as u64;
                        if !u.records.iter().any(|r| r.id == client.entity) {
                            updates_without_own += 1;
                        }
                        let mine = seen.entry(client.entity).or_default();
                        mine.extend(resolved.iter().map(|r| (u.header, *r)));
                    }
                }
                Err(_) => rejected += 1,
            }
        }
        for (entity, mut records) in seen {
            records.sort_by_key(|(h, r)| (h.tick, r.id));
            std::hash::Hash::hash(&(entity, records), &mut records_hash);
        }
    }
    Ok(ScriptedRun {
        world: tick.into_world(),
        actions_applied,
        datagrams_opened,
        rejected,
        updates_without_own,
        unresolved,
        records_hash: std::hash::Hasher::finish(&records_hash),
        bytes_out,
    })
}

fn push(
    transport: &MemoryTransport,
    from: SocketAddr,
    client: &mut Client,
    msg: &ClientMessage,
) -> Result<(), ServerError> {
    let mut datagram = Vec::with_capacity(64);
    client.session.seal(msg, &mut datagram).map_err(|e| ServerError::Internal(format!("sealing: {e}")))?;
    transport.push(from, datagram);
    Ok(())
}
