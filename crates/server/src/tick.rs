//! The authoritative tick loop: one thread that owns the world.
//!
//! # How it works
//!
//! [`TickLoop::tick_once`] is one tick, top to bottom:
//!
//! 1. joins from the login service are admitted (or refused: server full);
//! 2. `receive`: queued datagrams are opened and applied ([`crate::inbound`]); silent
//!    sessions expire ([`crate::session`]); sessions an operator ended through the admin
//!    API leave ([`crate::admin`], a bounded channel drained without waiting);
//! 3. the backend steps the world (stages `upload` … `forces`); the step alone
//!    advances `world.tick`;
//! 4. `packets`: the outbound builds and seals every active player's updates
//!    ([`crate::outbound`]) and hands each player over as soon as its datagrams are
//!    final;
//! 5. `send`: control replies go out through the transport, and each player handed over
//!    on one of its lanes (sockets), from several threads at once
//!    ([`crate::transport`]); this overlaps step 4 where the outbound hands players over
//!    in chunks, so `send` is the mean lane's time in the transport and `packets` the
//!    rest of the two;
//! 6. final states of players who left go to the persister.
//!
//! [`TickLoop::run`] adds pacing, the periodic persistence checkpoint, time dilation and
//! metrics around it.
//!
//! Each piece of state has one owner: the world and backend here, sessions in
//! [`Sessions`] (each player's sealer and [`Subscriber`](myriad_interest::Subscriber)
//! with it), the interest state in the outbound that selects (the host outbound keeps
//! each player's rotation in its subscriber; the device outbound keeps every player's
//! staleness resident on the device, the subscriber only the index to find it by),
//! datagrams in flight in the transport.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

use rayon::prelude::*;

use myriad_core::{Vec3, World};
use myriad_interest::TickInfo;
use myriad_physics::{Backend, TickConstants};
use myriad_protocol::{DisconnectReason, ServerInfo, ServerMessage};
use myriad_store::{MapId, Persister, PlayerState, UserId};

#[cfg(test)]
#[path = "tick_tests.rs"]
mod tests;

use crate::admin::TickAdmin;
use crate::config::ServerConfig;
use crate::dilation::DilationController;
use crate::gate::Gate;
use crate::inbound::{self, ReceiveBuffers};
use crate::outbound::{Job, Outbound, Ready, Recipient, recycle};
use crate::registry::SessionRegistry;
use crate::session::{JoinContext, JoinResult, Sessions, missing_entity};
use crate::stages::{TickStage, TickWork};
use crate::status::{ServerShared, StatusWindow};
use crate::transport::{Lane, Sent, Transport};

/// What the login service asks of the tick loop.
pub(crate) enum Command {
    /// Admit an authenticated user (or replace its current session).
    Join {
        user_id: UserId,
        username: String,
        state: Option<PlayerState>,
        reply: tokio::sync::oneshot::Sender<JoinResult>,
    },
}

/// Where the tick sends player states to be persisted (the database writer, or a
/// test's list).
pub(crate) trait StateSink: Send {
    /// Queues `states` for writing; never blocks the tick.
    fn submit(&self, states: &[PlayerState]) -> Result<(), String>;
    /// Queues `states` and has them written now: the periodic checkpoint. The tick's
    /// clock alone decides when positions are taken, and each checkpoint is committed
    /// right after (one write later), so a crash loses at most `persist_interval_ms`
    /// plus one tick plus one write.
    fn checkpoint(&self, states: &[PlayerState]) -> Result<(), String> {
        self.submit(states)
    }
    /// The writer's counters, for the metrics (none for a sink without them).
    fn stats(&self) -> Option<myriad_store::PersisterStats> {
        None
    }
}

impl StateSink for Persister {
    fn submit(&self, states: &[PlayerState]) -> Result<(), String> {
        self.submit_many(states).map(|_| ()).map_err(|e| e.to_string())
    }
    fn checkpoint(&self, states: &[PlayerState]) -> Result<(), String> {
        Persister::checkpoint(self, states).map(|_| ()).map_err(|e| e.to_string())
    }
    fn stats(&self) -> Option<myriad_store::PersisterStats> {
        Some(Persister::stats(self))
    }
}

/// Builds a [`TickLoop`]: the world, the backend and the transport are required; the
/// rest has defaults (no persister, map 0, no login service, fresh shared state). The
/// outbound is [`crate::outbound::create`]'s for the config.
pub(crate) struct TickLoopBuilder {
    config: ServerConfig,
    world: World,
    backend: Box<dyn Backend>,
    transport: Box<dyn Transport>,
    persister: Option<Box<dyn StateSink>>,
    map_id: MapId,
    commands: Option<Receiver<Command>>,
    shared: Option<Arc<ServerShared>>,
    registry: Option<Box<dyn SessionRegistry>>,
    admin: Option<TickAdmin>,
    replicas: Option<myriad_cuda::replica::DeviceReplicas>,
}

impl TickLoopBuilder {
    /// The players' replicas on the backend's device (a CUDA backend's): the outbound
    /// then chooses records there unless the config says `outbound = "host"`.
    pub fn device_replicas(mut self, replicas: Option<myriad_cuda::replica::DeviceReplicas>) -> Self {
        self.replicas = replicas;
        self
    }

    /// The admin API's commands and snapshots ([`crate::admin`]).
    pub fn admin(mut self, admin: Option<TickAdmin>) -> Self {
        self.admin = admin;
        self
    }

    /// Sessions shared with other servers (a zones gateway's cluster).
    pub fn registry(mut self, registry: Box<dyn SessionRegistry>) -> Self {
        self.registry = Some(registry);
        self
    }

    /// Where player positions go (the database writer), and the map they are on.
    pub fn persister(mut self, persister: Box<dyn StateSink>, map_id: MapId) -> Self {
        self.persister = Some(persister);
        self.map_id = map_id;
        self
    }

    /// The channel of join requests from the login service.
    pub fn commands(mut self, commands: Receiver<Command>) -> Self {
        self.commands = Some(commands);
        self
    }

    /// State shared with the server handle and the login service.
    pub fn shared(mut self, shared: Arc<ServerShared>) -> Self {
        self.shared = Some(shared);
        self
    }

    /// The tick loop.
    pub fn build(self) -> TickLoop {
        let config = self.config;
        let nominal = Duration::from_secs_f64(1.0 / f64::from(config.tick_rate));
        let outbound = crate::outbound::create(&config, self.replicas);
        // Without a login service nothing joins: a receiver whose sender is gone reads
        // as empty.
        let commands = self.commands.unwrap_or_else(|| std::sync::mpsc::channel().1);
        TickLoop {
            constants: TickConstants::new(&config.physics(), 1.0),
            // One gate per place datagrams are received: here only when the transport
            // does not gate on a thread of its own.
            gate: (!self.transport.gates()).then(|| Gate::new(config.receive_limits())),
            receive_buffers: ReceiveBuffers::default(),
            recipient_store: Vec::new(),
            centres: Centres::default(),
            dilation: DilationController::new(nominal, config.dilation, config.dilation_min_permille),
            sessions: Sessions::new(config.max_players as usize, self.map_id),
            world: self.world,
            backend: self.backend,
            transport: self.transport,
            outbound,
            persister: self.persister,
            commands,
            shared: self.shared.unwrap_or_default(),
            registry: self.registry,
            admin: self.admin,
            window: StatusWindow::default(),
            config,
        }
    }
}

/// The slots whose positions a tick reads for its recipients' centres, and the
/// positions read (`Dynamics::positions_at`), kept from tick to tick for their memory.
#[derive(Default)]
struct Centres {
    slots: Vec<u32>,
    centres: Vec<Vec3>,
}

/// The tick loop; see the module docs.
pub(crate) struct TickLoop {
    config: ServerConfig,
    world: World,
    backend: Box<dyn Backend>,
    transport: Box<dyn Transport>,
    outbound: Box<dyn Outbound>,
    sessions: Sessions,
    persister: Option<Box<dyn StateSink>>,
    commands: Receiver<Command>,
    shared: Arc<ServerShared>,
    dilation: DilationController,
    window: StatusWindow,
    /// The physics constants of every step (the configuration does not change).
    constants: TickConstants,
    /// The receive gate when the transport does not gate on a thread of its own
    /// (`receive_*` keys); `None` when it does.
    gate: Option<Gate>,
    /// What a receive works in (kept for its memory).
    receive_buffers: ReceiveBuffers,
    /// The recipients' memory, empty between ticks (each tick borrows the sessions
    /// anew; [`recycle`] gives it the next tick's lifetime).
    recipient_store: Vec<Option<Recipient<'static>>>,
    /// The recipients' slots and centres (kept for their memory).
    centres: Centres,
    /// Sessions shared with other servers, if any.
    registry: Option<Box<dyn SessionRegistry>>,
    /// The admin API's side of the tick, when it runs.
    admin: Option<TickAdmin>,
}

impl TickLoop {
    /// Starts building a tick loop.
    pub fn builder(
        config: ServerConfig,
        world: World,
        backend: Box<dyn Backend>,
        transport: Box<dyn Transport>,
    ) -> TickLoopBuilder {
        TickLoopBuilder {
            config,
            world,
            backend,
            transport,
            persister: None,
            map_id: MapId(0),
            commands: None,
            shared: None,
            registry: None,
            admin: None,
            replicas: None,
        }
    }

    /// The world.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Forgets what the outbound's profile gathered so far (`Outbound::restart_profile`;
    /// the device outbound under `MYRIAD_CUDA_PROFILE=1`): the tick benchmark's
    /// measurement starts here.
    pub fn restart_profile(&self) {
        self.outbound.restart_profile();
    }

    /// Ends the loop, keeping the world (the scripted harness's result).
    #[cfg(feature = "harness")]
    pub fn into_world(self) -> World {
        self.world
    }

    /// The sessions.
    #[cfg(test)]
    pub fn sessions(&self) -> &Sessions {
        &self.sessions
    }

    /// Runs until the shared stop flag is set; then disconnects everyone and hands their
    /// final positions to the persister (unless the stop is a simulated crash).
    pub fn run(mut self) {
        tracing::info!(backend = %self.backend.description(), outbound = %self.outbound.description(), "tick loop ready");
        if let Some(admin) = &self.admin {
            let _ = admin.shared().backend.set(self.backend.kind().to_string());
        }
        let persist_every = Duration::from_millis(self.config.persist_interval_ms);
        // One clock for the checkpoints: due every `persist_every` on the tick's clock,
        // never drifting by the tick's length (see `StateSink::checkpoint`).
        let mut next_persist = Instant::now() + persist_every;
        let mut next = Instant::now();
        let log_every = Duration::from_secs_f32(self.config.log_stages_every_s);
        let mut last_log = Instant::now();
        while !self.shared.stop.load(Ordering::Acquire) {
            let start = Instant::now();
            let work = self.tick_once();
            if Instant::now() >= next_persist {
                self.persist_all();
                next_persist += persist_every;
                // After a long stall, restart the schedule instead of checkpointing in a burst.
                next_persist = next_persist.max(Instant::now());
            }
            self.burn_artificial_load();
            let elapsed = start.elapsed();
            // A tick longer than twice the period the world is announced to run at (the
            // dilated one) is a stall that dilation did not cover.
            if elapsed > self.dilation.period() * 2 {
                metrics::counter!("myriad_slow_ticks_total").increment(1);
                tracing::debug!(tick_ms = ms(elapsed), "tick over twice its period");
            }
            if self.dilation.record(elapsed) {
                tracing::info!(dilation_permille = self.dilation.permille(), "time dilation changed");
                self.announce_server_info();
            }
            self.publish(&work, elapsed);
            if let Some(admin) = &mut self.admin {
                admin.publish(&mut self.sessions, &self.world, self.backend.as_ref());
            }
            if self.window.elapsed() >= Duration::from_secs(1) {
                let status = self.window.finish(
                    self.world.tick,
                    self.sessions.len(),
                    self.world.dynamics.len(),
                    self.dilation.permille(),
                );
                if log_every > Duration::ZERO && last_log.elapsed() >= log_every {
                    tracing::info!(target: "myriad::stages", "{}", status.stage_line());
                    last_log = Instant::now();
                }
                *self.shared.status.lock().unwrap_or_else(|p| p.into_inner()) = status;
                self.publish_persister_metrics();
            }
            next += self.dilation.period();
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                // Never try to catch up with a burst of ticks: that is what dilation is for.
                next = now;
            }
        }
        if self.shared.crash.load(Ordering::Acquire) {
            return;
        }
        self.sessions.disconnect_all(DisconnectReason::Shutdown);
        self.persist_all();
        self.send_control();
    }

    /// One tick's work (steps 1 to 6 of the module docs). Pacing, periodic persistence,
    /// dilation and metrics stay in [`TickLoop::run`], so the tick benchmark and the
    /// tests time and drive exactly this.
    pub fn tick_once(&mut self) -> TickWork {
        let mut work = TickWork::default();
        self.drain_commands();

        let t = Instant::now();
        let info = self.server_info();
        // A gating transport spends this tick's budgets from here on.
        self.publish_sessions();
        let now = Instant::now();
        self.outbound.profile("tick: publish the sessions", now - t);
        let inbound = inbound::receive(
            self.transport.as_mut(),
            &mut self.sessions,
            &mut self.world,
            info,
            self.gate.as_mut(),
            &mut self.receive_buffers,
            now,
        );
        let mut left: Vec<PlayerState> = inbound
            .leaving
            .iter()
            .filter_map(|&session| self.sessions.remove(&mut self.world, session, None))
            .collect();
        let received = Instant::now();
        let timeout = Duration::from_secs_f32(self.config.session_timeout_s);
        left.extend(self.sessions.expire(&mut self.world, now, timeout));
        let checked = Instant::now();
        let phases = [
            "tick: receive, phase 1 (admit)",
            "tick: receive, phase 2 (open and apply, each player's part)",
            "tick: receive, phase 2 (apply, the shared part)",
        ];
        for (span, took) in phases.into_iter().zip(inbound.phases) {
            self.outbound.profile(span, took);
        }
        self.outbound.profile(
            "tick: receive, the rest (transport, leaving)",
            (received - now).saturating_sub(inbound.phases.iter().sum()),
        );
        self.outbound.profile("tick: silence check", checked - received);
        // Sessions an operator ended (kick, ban, disable, delete): their Disconnects go
        // out with this tick's control replies.
        if let Some(admin) = &mut self.admin {
            admin.drain(&mut self.sessions, &mut self.world, &mut left);
        }
        // Accounts that logged in at another server of the cluster since: their sessions
        // here are replaced, as a second login here would replace them.
        if let Some(registry) = &mut self.registry {
            for name in registry.taken() {
                if let Some(session) = self.sessions.session_of(&name) {
                    tracing::info!(user = %name, "session replaced by a login at another server");
                    metrics::counter!("myriad_sessions_taken_total").increment(1);
                    left.extend(self.sessions.remove(&mut self.world, session, Some(DisconnectReason::Replaced)));
                }
            }
        }
        work.received = inbound.received;
        work.actions = inbound.actions;
        work.tag_checks = inbound.tag_checks;
        work.over_budget = inbound.over_budget;
        work.stages[TickStage::Receive] = ms(t.elapsed());

        match self.backend.step(&mut self.world, &self.constants) {
            Ok(report) => work.stages.set_physics(&report),
            Err(e) => {
                tracing::error!(error = %e, "physics step failed");
                metrics::counter!("myriad_physics_errors_total").increment(1);
            }
        }

        // Control replies first; then the updates, each run of players sent as soon as
        // the outbound has sealed it (`send` is the time in the transport, `packets` the
        // rest of the building).
        let t = Instant::now();
        let control = self.send_control();
        let control_ms = ms(t.elapsed());
        let t = Instant::now();
        let (updates, send_ms) = self.build_and_send(&mut work);
        work.stages[TickStage::Packets] = ms(t.elapsed()) - send_ms;
        work.stages[TickStage::Send] = control_ms + send_ms;
        work.bytes = control.bytes + updates.bytes;
        work.datagrams = (control.datagrams + updates.datagrams) as u64;

        if !left.is_empty() {
            self.persist(&left);
        }
        work
    }

    /// The ServerInfo every player is told (tick rate, current dilation).
    fn server_info(&self) -> ServerInfo {
        ServerInfo { tick_rate_hz: self.config.tick_rate.round() as u16, dilation_permille: self.dilation.permille() }
    }

    /// Queues ServerInfo for every ready player (sent with the next tick's datagrams):
    /// the protocol promises it whenever the tick rate or the dilation changes.
    fn announce_server_info(&mut self) {
        self.sessions.queue_to_active(&ServerMessage::ServerInfo(self.server_info()));
    }

    fn drain_commands(&mut self) {
        let mut replies = Vec::new();
        while let Ok(Command::Join { user_id, username, state, reply }) = self.commands.try_recv() {
            let ctx = JoinContext { tick: self.world.tick, dilation_permille: self.dilation.permille() };
            let claimed = self.registry.is_some().then(|| username.clone());
            let result = self.sessions.join(&mut self.world, user_id, username, state, ctx).map(|(joined, first)| {
                // First visit: record the spawn point now so the next login finds it.
                if let Some(first) = first {
                    self.persist(std::slice::from_ref(&first));
                }
                joined
            });
            if let (Ok(_), Some(name), Some(registry)) = (&result, claimed, &mut self.registry) {
                registry.claim(&name);
            }
            replies.push((reply, result));
        }
        if replies.is_empty() {
            return;
        }
        // A receiver thread must know a session before its keys leave the server, or the
        // client's first datagram could arrive before the session does.
        self.publish_sessions();
        for (reply, result) in replies {
            // The login task may have given up (client gone): nothing to undo, the
            // session times out unused.
            let _ = reply.send(result);
        }
    }

    /// Hands a gating transport the current tick and the sessions as they are now (the
    /// sessions only when they changed; a no-op for a transport that does not gate).
    fn publish_sessions(&mut self) {
        if self.transport.gates() {
            self.transport.publish(self.world.tick, self.sessions.changed_directory());
        }
    }

    /// Makes each entity, an object already in the world, a player with a fresh session
    /// of its user, as a login would (the tick benchmark's and the scripted harness's
    /// join). The sessions are published once, after all of them (once per player made
    /// a set-up of `n` players cost `n²`).
    pub fn adopt_all(&mut self, players: impl IntoIterator<Item = (UserId, myriad_core::EntityId)>) -> Vec<JoinResult> {
        let ctx = JoinContext { tick: self.world.tick, dilation_permille: self.dilation.permille() };
        let joined = players
            .into_iter()
            .map(|(user_id, entity)| self.sessions.adopt(&self.world, user_id, entity, ctx))
            .collect();
        self.publish_sessions();
        joined
    }

    /// Runs the outbound for every active player and sends each player's updates as soon
    /// as the outbound hands them over; returns what was sent and the milliseconds spent
    /// sending.
    fn build_and_send(&mut self, work: &mut TickWork) -> (Sent, f64) {
        let started = Instant::now();
        let dynamics = &self.world.dynamics;
        // In parallel: each player costs a few cache misses (its table entry, its slot,
        // found from where it was last tick unless objects came or went): 0.7 ms a tick
        // for 10,000 players on one core of the GPU host, 0.37 on its 16, when every slot
        // was a look-up in the map of every object. In last tick's memory (3.2 MB at
        // 50,000 players), chosen and then gathered in place.
        let mut chosen: Vec<Option<Recipient<'_>>> = recycle(std::mem::take(&mut self.recipient_store));
        self.sessions
            .par_iter_mut()
            .map(|p| {
                if !p.active() {
                    return None;
                }
                // The last tick's updates, sent by now (the admin API's bytes/s).
                p.bytes_sent += p.view.datagrams().total_bytes() as u64;
                let Some(slot) = dynamics.slot_hinted(p.entity, p.slot_hint) else {
                    missing_entity(p);
                    return None;
                };
                p.slot_hint = Some(slot as u32);
                Some(Recipient {
                    session_id: p.session_id,
                    object: slot as u32,
                    centre: Vec3::ZERO,
                    addr: p.addr,
                    view: &mut p.view,
                })
            })
            .collect_into_vec(&mut chosen);
        let passed = Instant::now();
        #[expect(clippy::filter_map_identity, reason = "`flatten` would not collect in place")]
        let mut recipients: Vec<Recipient<'_>> = chosen.into_iter().filter_map(|r| r).collect();
        // The centres in one read: when the step left the positions on the device (a GPU
        // backend), only the players' come back, not every object's.
        let Centres { slots, centres } = &mut self.centres;
        slots.clear();
        slots.extend(recipients.iter().map(|r| r.object));
        dynamics.positions_at(slots, centres);
        for (r, &c) in recipients.iter_mut().zip(centres.iter()) {
            r.centre = c;
        }
        let tick = TickInfo { tick: self.world.tick, dilation_permille: self.dilation.permille() };
        let sender = Sender::new(self.transport.lanes(), tick.tick);
        let (outbound, backend, world) = (&mut self.outbound, self.backend.as_mut(), &self.world);
        // On a thread of the pool: the outbound's parallel steps then start as the pool's
        // own work, not injected from outside (tens of microseconds each).
        let building = Instant::now();
        outbound.profile("tick: recipients, the pass over the sessions", passed - started);
        outbound.profile("tick: recipients, gathered", building - passed);
        let report =
            rayon::scope(|_| outbound.build(&mut Job { backend, world, tick, ready: &sender }, &mut recipients));
        outbound.profile("tick: outbound build (to its total)", building.elapsed());
        self.recipient_store = recycle(recipients);
        work.records = report.records;
        work.relative = report.relative;
        work.aoi_ms = report.aoi_ms;
        sender.finish()
    }

    /// Sends the queued control replies; returns what was sent.
    fn send_control(&mut self) -> Sent {
        let out: Vec<(std::net::SocketAddr, &[u8])> =
            self.sessions.control().iter().map(|(addr, d)| (*addr, d.as_slice())).collect();
        let transport = &mut self.transport;
        let sent = counted(&out, |out| transport.send(out));
        self.sessions.clear_control();
        sent
    }

    /// Queues player states for the persister, if there is one (players who left, a
    /// first visit's spawn point).
    fn persist(&self, states: &[PlayerState]) {
        if let Some(persister) = &self.persister
            && let Err(e) = persister.submit(states)
        {
            tracing::warn!(error = %e, "positions not queued for the database");
        }
    }

    /// The periodic checkpoint (and the final one at shutdown): every player's state,
    /// written right away.
    fn persist_all(&self) {
        if let Some(persister) = &self.persister
            && let Err(e) = persister.checkpoint(&self.sessions.states(&self.world))
        {
            tracing::warn!(error = %e, "positions not queued for the database");
        }
    }

    fn burn_artificial_load(&self) {
        let load = self.shared.artificial_load_us.load(Ordering::Relaxed);
        if load > 0 {
            // A test knob: burn CPU as if the tick had more work.
            let until = Instant::now() + Duration::from_micros(u64::from(load));
            while Instant::now() < until {
                std::hint::spin_loop();
            }
        }
    }

    /// The shared counters, the status window and the per-tick metrics.
    fn publish(&mut self, work: &TickWork, elapsed: Duration) {
        let defence = &self.shared.defence;
        defence.tag_checks.fetch_add(work.tag_checks, Ordering::Relaxed);
        defence.over_budget.fetch_add(work.over_budget, Ordering::Relaxed);
        self.shared.dilation_permille.store(u32::from(self.dilation.permille()), Ordering::Relaxed);
        self.shared.tick.store(self.world.tick, Ordering::Relaxed);
        self.shared.players.store(self.sessions.len(), Ordering::Relaxed);
        self.window.add(work, ms(elapsed));
        metrics::histogram!("myriad_tick_duration_seconds").record(elapsed.as_secs_f64());
        for (stage, v) in work.stages.iter() {
            metrics::histogram!("myriad_stage_duration_seconds", "stage" => stage.name()).record(v / 1000.0);
        }
        metrics::counter!("myriad_bytes_sent_total").increment(work.bytes);
        metrics::counter!("myriad_datagrams_sent_total").increment(work.datagrams);
        metrics::gauge!("myriad_players").set(self.sessions.len() as f64);
        metrics::gauge!("myriad_objects").set(self.world.dynamics.len() as f64);
        metrics::gauge!("myriad_time_dilation").set(self.dilation.factor());
        metrics::counter!("myriad_ticks_total").increment(1);
    }

    fn publish_persister_metrics(&self) {
        if let Some(p) = self.persister.as_ref().and_then(|p| p.stats()) {
            metrics::gauge!("myriad_persist_queued").set(p.queued as f64);
            metrics::gauge!("myriad_persist_rows_written").set(p.rows_written as f64);
            metrics::gauge!("myriad_persist_failures").set(p.failures as f64);
            metrics::gauge!("myriad_persist_dropped").set(p.dropped_total() as f64);
            metrics::gauge!("myriad_persist_healthy").set(if p.healthy { 1.0 } else { 0.0 });
        }
    }
}

/// The tick's [`Ready`]: each lane sends the updates of the players handed to it on a
/// socket of its own, and counts what was sent and the time it took.
struct Sender<'t> {
    lanes: Vec<Mutex<&'t mut dyn Lane>>,
    tick: u64,
    bytes: AtomicU64,
    datagrams: AtomicU64,
    /// Nanoseconds spent in the transport, summed over the lanes.
    nanos: AtomicU64,
}

impl<'t> Sender<'t> {
    fn new(lanes: Vec<&'t mut dyn Lane>, tick: u64) -> Self {
        Sender {
            lanes: lanes.into_iter().map(Mutex::new).collect(),
            tick,
            bytes: AtomicU64::new(0),
            datagrams: AtomicU64::new(0),
            nanos: AtomicU64::new(0),
        }
    }

    /// What was sent, and the milliseconds of sending per lane (the lanes send at once,
    /// so this is the stage's share of the tick).
    fn finish(self) -> (Sent, f64) {
        let sent = Sent { datagrams: self.datagrams.into_inner() as usize, bytes: self.bytes.into_inner() };
        (sent, self.nanos.into_inner() as f64 / 1e6 / self.lanes.len().max(1) as f64)
    }

    /// The first lane from `preferred` on that no thread holds, or, when every lane is
    /// in use (more threads than sockets), `preferred` itself once it is free.
    fn free_lane(&self, preferred: usize) -> MutexGuard<'_, &'t mut dyn Lane> {
        let n = self.lanes.len();
        (0..n)
            .find_map(|i| match self.lanes[(preferred + i) % n].try_lock() {
                Ok(guard) => Some(guard),
                // A panic while sending left the socket as it was: keep using it.
                Err(TryLockError::Poisoned(p)) => Some(p.into_inner()),
                Err(TryLockError::WouldBlock) => None,
            })
            .unwrap_or_else(|| self.lanes[preferred % n].lock().unwrap_or_else(|p| p.into_inner()))
    }
}

impl Ready for Sender<'_> {
    fn lanes(&self) -> usize {
        self.lanes.len()
    }

    /// Sends `players`' updates, starting at a different player every tick: when the
    /// socket fills and the tail is dropped, the loss is spread over everyone instead of
    /// starving the same players tick after tick. A scrambled offset, not tick % n:
    /// shifting by one player per tick would keep starving almost the same tail.
    fn ready(&self, lane: usize, players: &[Recipient<'_>]) {
        let n = players.len();
        if n == 0 || self.lanes.is_empty() {
            return;
        }
        let first = ((self.tick.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 32) % n as u64) as usize;
        let out: Vec<(std::net::SocketAddr, &[u8])> = players[first..]
            .iter()
            .chain(&players[..first])
            .flat_map(|r| r.addr.into_iter().flat_map(|addr| r.view.datagrams().iter().map(move |d| (addr, d))))
            .collect();
        let t = Instant::now();
        let mut lane = self.free_lane(lane);
        let sent = counted(&out, |out| lane.transmit(out));
        drop(lane);
        self.nanos.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        self.bytes.fetch_add(sent.bytes, Ordering::Relaxed);
        self.datagrams.fetch_add(sent.datagrams as u64, Ordering::Relaxed);
    }
}

/// Sends `out` with `send` (a transport or one of its lanes); logs a failure and counts
/// what was dropped.
fn counted(
    out: &[(std::net::SocketAddr, &[u8])],
    send: impl FnOnce(&[(std::net::SocketAddr, &[u8])]) -> std::io::Result<Sent>,
) -> Sent {
    if out.is_empty() {
        return Sent::default();
    }
    let sent = match send(out) {
        Ok(sent) => sent,
        Err(e) => {
            tracing::warn!(error = %e, "send failed");
            Sent::default()
        }
    };
    if sent.datagrams < out.len() {
        metrics::counter!("myriad_packets_dropped_total", "reason" => "send_buffer_full")
            .increment((out.len() - sent.datagrams) as u64);
    }
    sent
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}
