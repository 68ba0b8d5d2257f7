//! The tick's side of the admin API never waits: a held snapshot lock skips the
//! snapshot, an empty or busy command channel costs a `try_recv`, and a tick carries out
//! at most a queue's worth of commands.

use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_physics::{Backend, BackendKind, ZoneCuts, create_cpu_backend};
use myriad_protocol::DisconnectReason;
use myriad_store::{MapId, UserId};
use tokio::sync::{mpsc, oneshot};

use super::commands::{AdminCommand, COMMAND_QUEUE, TickAdmin};
use super::{AdminShared, Role};
use crate::session::{JoinContext, Sessions};

fn world() -> myriad_core::World {
    myriad_core::ScenarioSpec::custom(3).counts(10, 0, 0).map_size(64.0, 17).build().unwrap()
}

const CTX: JoinContext = JoinContext { tick: 0, dilation_permille: 1000 };

#[test]
fn a_held_snapshot_lock_skips_the_snapshot_instead_of_waiting() {
    let shared = Arc::new(AdminShared::new(Role::Server));
    let (_tx, rx) = mpsc::channel(COMMAND_QUEUE);
    let mut admin = TickAdmin::new(rx, shared.clone());
    let mut w = world();
    let mut sessions = Sessions::new(4, MapId(1));
    sessions.join(&mut w, UserId(1), "u1".into(), None, CTX).unwrap();
    let cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
    // Nobody asked: no snapshot is taken at all.
    admin.publish(&mut sessions, &w, cpu.as_ref());
    assert!(shared.snapshot.lock().unwrap().is_none());
    shared.want();
    let held = shared.snapshot.lock().unwrap();
    let t = Instant::now();
    admin.publish(&mut sessions, &w, cpu.as_ref());
    assert!(t.elapsed() < Duration::from_millis(50), "the tick did not wait for the lock");
    assert!(held.is_none(), "skipped while the lock was held");
    drop(held);
    admin.publish(&mut sessions, &w, cpu.as_ref());
    let snap = shared.snapshot.lock().unwrap().clone().expect("published once the lock was free");
    assert_eq!(snap.players.len(), 1);
    assert_eq!(snap.players[0].account, "u1");
    assert_eq!(snap.density.iter().sum::<u32>(), 10, "every NPC counted once");
    assert_eq!(snap.cuts, None, "a world stepped here has no zone cuts");
}

/// A backend whose world is split into zones elsewhere (as a gateway's is).
struct Zoned(Box<dyn Backend>, ZoneCuts);

impl Backend for Zoned {
    fn kind(&self) -> BackendKind {
        BackendKind::Zones
    }
    fn description(&self) -> String {
        "zoned".into()
    }
    fn step(
        &mut self,
        world: &mut myriad_core::World,
        k: &myriad_physics::TickConstants,
    ) -> Result<myriad_physics::StepReport, myriad_physics::PhysicsError> {
        self.0.step(world, k)
    }
    fn query_aoi(
        &mut self,
        world: &myriad_core::World,
        boxes: &[myriad_core::Aabb],
        out: &mut myriad_physics::AoiResults,
    ) -> Result<(), myriad_physics::PhysicsError> {
        self.0.query_aoi(world, boxes, out)
    }
    fn zone_cuts(&self) -> Option<ZoneCuts> {
        Some(self.1.clone())
    }
}

#[test]
fn a_snapshot_carries_the_zone_cuts_the_backend_knows() {
    let shared = Arc::new(AdminShared::new(Role::Gateway));
    let (_tx, rx) = mpsc::channel(COMMAND_QUEUE);
    let mut admin = TickAdmin::new(rx, shared.clone());
    let w = world();
    let mut sessions = Sessions::new(4, MapId(1));
    let cuts =
        ZoneCuts { xs: vec![0.0, 20.0, 64.0], zs: vec![0.0, 64.0], run: 2, zone_tick: Some(140), since_tick: 120 };
    let zoned = Zoned(create_cpu_backend(BackendKind::Cpu).unwrap(), cuts.clone());
    shared.want();
    admin.publish(&mut sessions, &w, &zoned);
    let snap = shared.snapshot.lock().unwrap().clone().expect("published");
    assert_eq!(snap.cuts, Some(cuts));
}

#[test]
fn commands_end_sessions_and_a_tick_takes_at_most_a_queue_of_them() {
    let shared = Arc::new(AdminShared::new(Role::Server));
    let (tx, rx) = mpsc::channel(COMMAND_QUEUE);
    let mut admin = TickAdmin::new(rx, shared);
    let mut w = world();
    let mut sessions = Sessions::new(4, MapId(1));
    sessions.join(&mut w, UserId(1), "u1".into(), None, CTX).unwrap();
    let mut left = Vec::new();
    // An empty channel: nothing to do.
    admin.drain(&mut sessions, &mut w, &mut left);
    let (reply, answer) = oneshot::channel();
    tx.try_send(AdminCommand::End { account: "U1".into(), reason: DisconnectReason::Kicked, reply }).unwrap();
    let mut replies = Vec::new();
    for _ in 1..COMMAND_QUEUE {
        let (reply, answer) = oneshot::channel();
        tx.try_send(AdminCommand::End { account: "nobody".into(), reason: DisconnectReason::Kicked, reply }).unwrap();
        replies.push(answer);
    }
    let (reply, last) = oneshot::channel();
    assert!(
        tx.try_send(AdminCommand::End { account: "x".into(), reason: DisconnectReason::Kicked, reply }).is_err(),
        "the queue is bounded: the admin is refused, the tick is not asked to wait"
    );
    drop(last);
    admin.drain(&mut sessions, &mut w, &mut left);
    assert_eq!(answer.blocking_recv(), Ok(true), "the account's name is compared without case");
    assert_eq!(sessions.len(), 0);
    assert_eq!(left.len(), 1, "its final state goes to the persister");
    assert!(replies.into_iter().all(|mut r| r.try_recv() == Ok(false)));
}
