//! The step shared by the CPU backends, stage by stage (docs/design.md, the tick: in
//! the reference's order): object boxes and dynamic tree, broad phase static, broad
//! phase dynamic, narrow phase static, narrow phase dynamic, then per object: NPC
//! action, gathered responses, forces, integration, limits.
//!
//! Pair lists are canonical: static pairs sorted by (object, primitive), dynamic pairs by
//! (lower slot, higher slot). Responses are summed per object in the order fixed by
//! [`crate::response`].

use std::time::Instant;

use myriad_core::world::{Dynamics, Statics, flags};
use myriad_core::{Aabb, ObjectKind, Vec3, World};
use rayon::prelude::*;

use crate::backend::{Stage, StepReport};
use crate::consts::TickConstants;
use crate::integrate::{NpcTurn, enforce_limits, integrate};
use crate::narrow::{Body, contact};
use crate::response::{Accum, Response, respond};

/// Whether a stage runs on the calling thread or on rayon's pool.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Exec {
    Serial,
    Parallel,
}

/// How a backend finds candidate pairs.
pub(crate) trait BroadPhase {
    /// Prepares for this tick's queries (builds the dynamic tree, if any).
    fn build_dynamic(&mut self, world: &World, aabbs: &[Aabb]);
    /// Appends every `(object << 32 | primitive)` whose boxes overlap, sorted ascending.
    fn static_pairs(&mut self, world: &World, aabbs: &[Aabb], out: &mut Vec<u64>);
    /// Appends every `(a << 32 | b)`, `a < b`, whose boxes overlap, sorted ascending.
    fn dynamic_pairs(&mut self, aabbs: &[Aabb], out: &mut Vec<u64>);
    /// The step has written the world (what a tree kept from tick to tick must know).
    fn stepped(&mut self, _world: &World) {}
}

/// Buffers reused from tick to tick.
#[derive(Default)]
pub(crate) struct Scratch {
    pub aabbs: Vec<Aabb>,
    static_pairs: Vec<u64>,
    dynamic_pairs: Vec<u64>,
    /// Static contacts: (object, response), sorted by (object, primitive).
    static_resp: Vec<(u32, Response)>,
    /// Dynamic contacts: (a, b, response), sorted by (a, b).
    dynamic_resp: Vec<(u32, u32, Response)>,
    /// Indices into `dynamic_resp` sorted by (b, a).
    by_b: Vec<u32>,
    static_off: Vec<u32>,
    a_off: Vec<u32>,
    b_off: Vec<u32>,
    /// Write cursors of the counting sort by b.
    fill: Vec<u32>,
}

#[inline]
pub(crate) fn dynamic_body(d: &Dynamics, i: usize) -> Body {
    Body { kind: d.shapes()[i], pos: d.positions()[i], half: d.half_extents()[i], radius: d.radii()[i] }
}

#[inline]
pub(crate) fn static_body(s: &Statics, i: usize) -> Body {
    Body { kind: s.shapes()[i], pos: s.positions()[i], half: s.half_extents()[i], radius: s.radii()[i] }
}

/// Object boxes at the current positions.
pub(crate) fn dynamic_aabbs(exec: Exec, d: &Dynamics, out: &mut Vec<Aabb>) {
    out.clear();
    let f = |(p, h): (&Vec3, &Vec3)| Aabb::from_center_half(*p, *h);
    match exec {
        Exec::Serial => out.extend(d.positions().iter().zip(d.half_extents()).map(f)),
        Exec::Parallel => out.par_extend(d.positions().par_iter().zip(d.half_extents().par_iter()).map(f)),
    }
}

/// Keeps the items `f` maps to `Some`, in input order.
fn filter_map<T: Sync, U: Send>(exec: Exec, input: &[T], out: &mut Vec<U>, f: impl Fn(&T) -> Option<U> + Sync + Send) {
    out.clear();
    match exec {
        Exec::Serial => out.extend(input.iter().filter_map(f)),
        Exec::Parallel => out.par_extend(input.par_iter().filter_map(f)),
    }
}

/// `offsets[k]..offsets[k + 1]` is the run of `keys` equal to `k`, for sorted `keys`.
fn run_offsets(n: usize, keys: impl Iterator<Item = u32>, offsets: &mut Vec<u32>) {
    offsets.clear();
    offsets.resize(n + 1, 0);
    for k in keys {
        offsets[k as usize + 1] += 1;
    }
    for k in 0..n {
        offsets[k + 1] += offsets[k];
    }
}

/// Runs one step; `broad` supplies the candidate pairs.
pub(crate) fn run_step(
    exec: Exec,
    world: &mut World,
    k: &TickConstants,
    broad: &mut impl BroadPhase,
    s: &mut Scratch,
) -> StepReport {
    let mut report = StepReport::default();
    let mut clock = Instant::now();
    let mut lap = |report: &mut StepReport, stage: Stage| {
        let now = Instant::now();
        report.stage_ms[stage as usize] += (now - clock).as_secs_f64() * 1e3;
        clock = now;
    };
    let n = world.dynamics.len();

    dynamic_aabbs(exec, &world.dynamics, &mut s.aabbs);
    broad.build_dynamic(world, &s.aabbs);
    lap(&mut report, Stage::BuildDynamicBvh);

    s.static_pairs.clear();
    broad.static_pairs(world, &s.aabbs, &mut s.static_pairs);
    report.static_pairs = s.static_pairs.len() as u64;
    lap(&mut report, Stage::BroadStatic);

    s.dynamic_pairs.clear();
    broad.dynamic_pairs(&s.aabbs, &mut s.dynamic_pairs);
    report.dynamic_pairs = s.dynamic_pairs.len() as u64;
    lap(&mut report, Stage::BroadDynamic);

    let d = &world.dynamics;
    let st = &world.statics;
    let velocity = |i: usize| d.positions()[i] - d.prev_positions()[i];
    filter_map(exec, &s.static_pairs, &mut s.static_resp, |&p| {
        let (obj, prim) = ((p >> 32) as usize, (p & 0xffff_ffff) as usize);
        let c = contact(&static_body(st, prim), &dynamic_body(d, obj))?;
        respond(&c, Vec3::ZERO, velocity(obj), 1.0, k).map(|r| (obj as u32, r))
    });
    report.static_contacts = s.static_resp.len() as u64;
    run_offsets(n, s.static_resp.iter().map(|r| r.0), &mut s.static_off);
    lap(&mut report, Stage::NarrowStatic);

    filter_map(exec, &s.dynamic_pairs, &mut s.dynamic_resp, |&p| {
        let (a, b) = ((p >> 32) as usize, (p & 0xffff_ffff) as usize);
        let c = contact(&dynamic_body(d, a), &dynamic_body(d, b))?;
        respond(&c, velocity(a), velocity(b), 0.5, k).map(|r| (a as u32, b as u32, r))
    });
    report.dynamic_contacts = s.dynamic_resp.len() as u64;
    run_offsets(n, s.dynamic_resp.iter().map(|r| r.0), &mut s.a_off);
    // A stable counting sort by b of a list sorted by (a, b) gives the (b, a) order.
    run_offsets(n, s.dynamic_resp.iter().map(|r| r.1), &mut s.b_off);
    s.by_b.clear();
    s.by_b.resize(s.dynamic_resp.len(), 0);
    s.fill.clear();
    s.fill.extend_from_slice(&s.b_off);
    for (i, r) in s.dynamic_resp.iter().enumerate() {
        let at = &mut s.fill[r.1 as usize];
        s.by_b[*at as usize] = i as u32;
        *at += 1;
    }
    lap(&mut report, Stage::NarrowDynamic);

    forces(exec, world, k, s);
    lap(&mut report, Stage::Forces);
    // The step is the single owner of the tick counter (see `Backend::step`).
    world.tick += 1;
    broad.stepped(world);
    report
}

/// Per object: NPC action, gathered responses, forces and integration, limits.
fn forces(exec: Exec, world: &mut World, k: &TickConstants, s: &Scratch) {
    let seed = world.seed;
    let turn = NpcTurn::at(world.tick, k.npc_period);
    let bounds = world.bounds;
    let terrain = &world.terrain;
    let st = world.dynamics.state_mut();
    let (half, kind, id) = (st.half, st.kind, st.id);
    let per_object = |i: usize, pos: &mut Vec3, prev: &mut Vec3, action: &mut u8, flag: &mut u8| {
        if kind[i] == ObjectKind::Npc {
            *action = turn.action(seed, id[i], *action);
        }
        let mut acc = Accum::default();
        for (_, r) in &s.static_resp[s.static_off[i] as usize..s.static_off[i + 1] as usize] {
            acc.add_as_b(r, k);
        }
        for &j in &s.by_b[s.b_off[i] as usize..s.b_off[i + 1] as usize] {
            acc.add_as_b(&s.dynamic_resp[j as usize].2, k);
        }
        for (_, _, r) in &s.dynamic_resp[s.a_off[i] as usize..s.a_off[i + 1] as usize] {
            acc.add_as_a(r, k);
        }
        acc.apply(pos, prev);
        let standing = *flag & flags::ON_TERRAIN != 0 || acc.supported;
        integrate(pos, prev, *action, standing, k);
        let on_terrain = enforce_limits(pos, prev, half[i], &bounds, terrain, k);
        *flag = on_terrain | if acc.supported { flags::SUPPORTED } else { 0 };
    };
    match exec {
        Exec::Serial => {
            for (i, (((pos, prev), action), flag)) in
                st.pos.iter_mut().zip(st.prev.iter_mut()).zip(st.action.iter_mut()).zip(st.flags.iter_mut()).enumerate()
            {
                per_object(i, pos, prev, action, flag);
            }
        }
        Exec::Parallel => {
            (st.pos, st.prev, st.action, st.flags)
                .into_par_iter()
                .enumerate()
                .for_each(|(i, (pos, prev, action, flag))| per_object(i, pos, prev, action, flag));
        }
    }
}
