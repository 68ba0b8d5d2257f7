//! Myriad against Rapier (rapier3d 0.36), side by side in one process on one machine.
//!
//! 1. **Broad phase on identical boxes.** For each set (the reference scenarios, the
//!    clustered one, a duplicate-heavy lattice), our LBVH broad phase and Rapier's
//!    `BroadPhaseBvh` get the very same AABBs (`common/rapier_side.rs` explains how). Pairs
//!    found must be equal as sets; times are medians over repeated runs after a warm-up,
//!    for a full build and for the incremental update after one tick of motion. Ours runs
//!    on all cores and on one; Rapier's default build is single-threaded.
//! 2. **Whole step, for orientation only.** The same world stepped by Myriad's `cpu`
//!    backend and by Rapier's pipeline. These are *different physics models*: Rapier
//!    solves full rigid-body dynamics with a constraint solver, Myriad integrates Verlet
//!    with impulse responses; the numbers say where each stands, not who is faster at the
//!    same job.
//!
//! Run with `cargo bench -p myriad-peers --bench rapier -- [flags]` (`--help` lists them).
//! Prints markdown; `--json PATH` also writes the rows.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use myriad_core::rng::Stream;
use myriad_core::{PhysicsConfig, ScenarioSpec, World};
use myriad_peers::{AabbSet, Lattice, OurBroadPhase, PairDiff, Pairs};
use myriad_physics::{Backend, BackendKind, TickConstants, create_cpu_backend};
use rayon::{ThreadPool, ThreadPoolBuilder};
use serde::Serialize;

#[path = "../common/rapier_side.rs"]
mod rapier_side;

use rapier_side::{RapierBroad, RapierWorld, Skin};

/// Flags of the bench.
#[derive(Parser, Debug, Serialize)]
#[command(about = "Myriad against Rapier: broad phase on identical boxes, and the whole step for orientation")]
struct Args {
    /// Broad-phase sets, comma-separated: 1, 2, 3, clustered, lattice.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,clustered,lattice")]
    scenario: Vec<String>,
    /// Measured ticks: incremental broad-phase updates and whole steps (after the warm-up).
    #[arg(long, default_value_t = 30)]
    ticks: usize,
    /// Measured full builds of each broad phase (after the warm-up).
    #[arg(long, default_value_t = 7)]
    builds: usize,
    /// Runs of each kind discarded before measuring.
    #[arg(long, default_value_t = 3)]
    warmup: usize,
    /// Scenarios for the whole-step comparison, comma-separated (1, 2, 3, clustered);
    /// empty for none.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    step_scenario: Vec<String>,
    /// Seed of the scenarios.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Also write the results as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// User + system CPU time of this process so far, in ms.
fn process_cpu_ms() -> f64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a complete rusage into the pointer on success.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } != 0 {
        return 0.0;
    }
    // SAFETY: initialised by the successful call above.
    let u = unsafe { usage.assume_init() };
    let ms = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
    ms(u.ru_utime) + ms(u.ru_stime)
}

/// Wall and CPU time of repeated runs of one thing.
#[derive(Clone, Debug, Default, Serialize)]
struct Timing {
    /// Wall time per run, ms.
    wall_ms: Vec<f64>,
    /// Process CPU time over all measured runs, ms.
    cpu_total_ms: f64,
}

impl Timing {
    /// Times `f`; `measured` says whether this run counts (false during the warm-up).
    fn run<R>(&mut self, measured: bool, f: impl FnOnce() -> R) -> R {
        let cpu = process_cpu_ms();
        let start = Instant::now();
        let r = f();
        let wall = start.elapsed().as_secs_f64() * 1e3;
        if measured {
            self.cpu_total_ms += process_cpu_ms() - cpu;
            self.wall_ms.push(wall);
        }
        r
    }

    fn median(&self) -> f64 {
        let mut v = self.wall_ms.clone();
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        let m = v.len() / 2;
        if v.len() % 2 == 1 { v[m] } else { (v[m - 1] + v[m]) / 2.0 }
    }

    /// CPU time per measured run (all threads of the process), ms.
    fn cpu_per_run(&self) -> f64 {
        self.cpu_total_ms / self.wall_ms.len().max(1) as f64
    }
}

/// A timing as it goes into the JSON.
#[derive(Clone, Debug, Serialize)]
struct Measured {
    median_ms: f64,
    cpu_ms_per_run: f64,
    runs: usize,
}

impl From<&Timing> for Measured {
    fn from(t: &Timing) -> Measured {
        Measured { median_ms: t.median(), cpu_ms_per_run: t.cpu_per_run(), runs: t.wall_ms.len() }
    }
}

/// One broad-phase set, full build and incremental.
#[derive(Clone, Debug, Serialize)]
struct BroadRow {
    set: String,
    dynamic: usize,
    static_prims: usize,
    /// Full build: ours (all threads, one thread), Rapier exact.
    full_ours_all: Measured,
    full_ours_one: Measured,
    full_rapier: Measured,
    full_pairs_dynamic: [usize; 2],
    full_pairs_static: [usize; 2],
    full_equal: bool,
    /// Incremental: one tick of motion, then each side's update.
    moved_median: usize,
    inc_ours_all: Measured,
    inc_ours_one: Measured,
    inc_rapier: Measured,
    inc_rapier_default_skin: Measured,
    inc_pairs_dynamic: [usize; 2],
    inc_pairs_static: [usize; 2],
    /// Ticks whose pair sets were equal, of those compared.
    inc_equal_ticks: usize,
    inc_ticks: usize,
    /// Rapier with its default skin, last tick: pair counts and whether they include ours.
    default_skin_pairs: [usize; 2],
    default_skin_superset: bool,
}

/// One whole-step comparison.
#[derive(Clone, Debug, Serialize)]
struct StepRow {
    scenario: String,
    dynamic: usize,
    static_prims: usize,
    terrain: String,
    ours_all: Measured,
    ours_one: Measured,
    rapier: Measured,
    ours_threads: usize,
    rapier_threads: &'static str,
    ours_contacts_last: u64,
    rapier_contact_pairs_last: usize,
}

#[derive(Serialize)]
struct Report<'a> {
    args: &'a Args,
    threads_all: usize,
    rapier: &'static str,
    broad: Vec<BroadRow>,
    step: Vec<StepRow>,
}

fn pool(threads: usize) -> ThreadPool {
    ThreadPoolBuilder::new().num_threads(threads).build().expect("a rayon pool")
}

fn spec(name: &str, seed: u64) -> Option<ScenarioSpec> {
    match name {
        "1" | "2" | "3" => ScenarioSpec::reference(name.parse().ok()?, seed).ok(),
        "clustered" => Some(ScenarioSpec::clustered(seed)),
        _ => None,
    }
}

/// The lattice set: scenario 2's counts on a 48³ lattice (~0.5 objects per point).
fn lattice(seed: u64) -> Lattice {
    Lattice { dynamic: 55_000, statics: 15_000, side: 48, seed }
}

/// What moves the boxes from one tick to the next.
enum Motion {
    /// A world stepped by our `cpu` backend (on the global pool, not timed).
    World(Box<World>, Box<dyn Backend>, TickConstants),
    /// Lattice boxes hopping one lattice step (so every face stays on the half-grid).
    Lattice(Stream),
}

impl Motion {
    fn advance(&mut self, set: &mut AabbSet) {
        match self {
            Motion::World(w, backend, k) => {
                backend.step(w, k).expect("a cpu step");
                set.set_dynamic_centres(w.dynamics.positions());
            }
            Motion::Lattice(rng) => {
                for c in &mut set.dynamic_centres {
                    // A third of the boxes hop, along a random axis, and stay on the lattice.
                    if rng.below(3) == 0 {
                        let axis = rng.below(3) as usize;
                        let step = if rng.below(2) == 0 { -1.0 } else { 1.0 };
                        let lo = Lattice::ORIGIN[axis];
                        c[axis] = (c[axis] + step).clamp(lo, lo + 47.0);
                    }
                }
            }
        }
    }
}

fn check_equal(what: &str, ours: &Pairs, theirs: &Pairs) -> bool {
    let dd = PairDiff::of(&ours.dynamic, &theirs.dynamic);
    let ds = PairDiff::of(&ours.statics, &theirs.statics);
    if dd.is_empty() && ds.is_empty() {
        return true;
    }
    eprintln!(
        "  MISMATCH {what}: dynamic only ours {} only Rapier {}; static only ours {} only Rapier {} (first: {:?} {:?})",
        dd.only_first.len(),
        dd.only_second.len(),
        ds.only_first.len(),
        ds.only_second.len(),
        dd.only_first.iter().chain(&ds.only_first).next().map(|p| myriad_peers::unpack(*p)),
        dd.only_second.iter().chain(&ds.only_second).next().map(|p| myriad_peers::unpack(*p)),
    );
    false
}

fn broad_phase(name: &str, args: &Args, all: &ThreadPool, one: &ThreadPool) -> BroadRow {
    let started = Instant::now();
    let (mut set, mut motion) = if name == "lattice" {
        (lattice(args.seed).build("lattice"), Motion::Lattice(Stream::new(args.seed, 0x6d6f7665)))
    } else {
        let spec = spec(name, args.seed).unwrap_or_else(|| panic!("unknown set {name:?}"));
        let world = spec.build().expect("a generated world");
        let set = AabbSet::from_world(name, &world);
        let backend = create_cpu_backend(BackendKind::Cpu).expect("the cpu backend");
        (set, Motion::World(Box::new(world), backend, TickConstants::new(&PhysicsConfig::default(), 1.0)))
    };
    eprintln!(
        "set {name}: {} dynamic, {} static boxes, made in {:.1} s",
        set.dynamic_len(),
        set.static_len(),
        started.elapsed().as_secs_f64()
    );

    // Full build: a fresh structure each run, built from the boxes alone.
    let (mut t_all, mut t_one, mut t_rapier) = (Timing::default(), Timing::default(), Timing::default());
    let mut ours = Pairs::default();
    for run in 0..args.warmup + args.builds {
        let measured = run >= args.warmup;
        for (pool, t) in [(all, &mut t_all), (one, &mut t_one)] {
            pool.install(|| {
                t.run(measured, || {
                    let mut bp = OurBroadPhase::default();
                    bp.build_statics(&set);
                    bp.pairs(&set, &mut ours);
                    bp
                })
            });
        }
    }
    let mut rapier = RapierBroad::new(&set, Skin::Exact);
    if let Err(e) = rapier.check_aabbs(&set) {
        panic!("set {name}: Rapier was not given our boxes: {e}");
    }
    for run in 0..args.warmup + args.builds {
        rapier.reset();
        t_rapier.run(run >= args.warmup, || rapier.update_all());
    }
    rapier.apply_events();
    let (theirs, static_static) = rapier.pairs();
    assert_eq!(static_static, 0, "collision groups must drop static-static pairs");
    let full_equal = check_equal(&format!("{name} full build"), &ours, &theirs);
    eprintln!(
        "  full build: ours {:.2} ms ({} thr), {:.2} ms (1 thr); Rapier {:.2} ms; pairs {}+{} vs {}+{}",
        t_all.median(),
        all.current_num_threads(),
        t_one.median(),
        t_rapier.median(),
        ours.dynamic.len(),
        ours.statics.len(),
        theirs.dynamic.len(),
        theirs.statics.len()
    );
    let full = (ours.dynamic.len(), ours.statics.len(), theirs.dynamic.len(), theirs.statics.len());

    // Incremental: set things moving first, then per tick each side's update.
    for _ in 0..5 {
        motion.advance(&mut set);
    }
    let mut ours_all = OurBroadPhase::default();
    let mut ours_one = OurBroadPhase::default();
    all.install(|| ours_all.build_statics(&set));
    one.install(|| ours_one.build_statics(&set));
    let mut exact = RapierBroad::new(&set, Skin::Exact);
    exact.update_all();
    exact.apply_events();
    let mut loose = RapierBroad::new(&set, Skin::Default);
    loose.update_all();
    loose.apply_events();
    let (mut i_all, mut i_one, mut i_exact, mut i_loose) =
        (Timing::default(), Timing::default(), Timing::default(), Timing::default());
    let (mut equal_ticks, mut moved) = (0, Vec::new());
    let mut ours_one_pairs = Pairs::default();
    let (mut last_ours, mut last_theirs) = (Pairs::default(), Pairs::default());
    for tick in 0..args.warmup + args.ticks {
        let measured = tick >= args.warmup;
        motion.advance(&mut set);
        all.install(|| i_all.run(measured, || ours_all.pairs(&set, &mut last_ours)));
        one.install(|| i_one.run(measured, || ours_one.pairs(&set, &mut ours_one_pairs)));
        let n_moved = exact.move_dynamics(&set.dynamic_centres);
        i_exact.run(measured, || exact.update_moved());
        exact.apply_events();
        loose.move_dynamics(&set.dynamic_centres);
        i_loose.run(measured, || loose.update_moved());
        loose.apply_events();
        if measured {
            moved.push(n_moved);
            let (theirs, _) = exact.pairs();
            let same = ours_one_pairs == last_ours
                && check_equal(&format!("{name} incremental tick {tick}"), &last_ours, &theirs);
            equal_ticks += usize::from(same);
            last_theirs = theirs;
        }
    }
    let (last_loose, _) = loose.pairs();
    let default_skin_superset = PairDiff::of(&last_ours.dynamic, &last_loose.dynamic).only_first.is_empty()
        && PairDiff::of(&last_ours.statics, &last_loose.statics).only_first.is_empty();
    moved.sort_unstable();
    eprintln!(
        "  incremental: ours {:.2} ms ({} thr), {:.2} ms (1 thr); Rapier {:.2} ms exact, {:.2} ms default skin; \
         {equal_ticks}/{} ticks equal",
        i_all.median(),
        all.current_num_threads(),
        i_one.median(),
        i_exact.median(),
        i_loose.median(),
        args.ticks
    );
    BroadRow {
        set: name.into(),
        dynamic: set.dynamic_len(),
        static_prims: set.static_len(),
        full_ours_all: (&t_all).into(),
        full_ours_one: (&t_one).into(),
        full_rapier: (&t_rapier).into(),
        full_pairs_dynamic: [full.0, full.2],
        full_pairs_static: [full.1, full.3],
        full_equal,
        moved_median: moved.get(moved.len() / 2).copied().unwrap_or(0),
        inc_ours_all: (&i_all).into(),
        inc_ours_one: (&i_one).into(),
        inc_rapier: (&i_exact).into(),
        inc_rapier_default_skin: (&i_loose).into(),
        inc_pairs_dynamic: [last_ours.dynamic.len(), last_theirs.dynamic.len()],
        inc_pairs_static: [last_ours.statics.len(), last_theirs.statics.len()],
        inc_equal_ticks: equal_ticks,
        inc_ticks: args.ticks,
        default_skin_pairs: [last_loose.dynamic.len(), last_loose.statics.len()],
        default_skin_superset,
    }
}

fn whole_step(name: &str, args: &Args, all: &ThreadPool, one: &ThreadPool) -> StepRow {
    let spec = spec(name, args.seed).unwrap_or_else(|| panic!("unknown scenario {name:?}"));
    let world = spec.build().expect("a generated world");
    let config = PhysicsConfig::default();
    let k = TickConstants::new(&config, 1.0);
    let mut contacts = 0;
    let mut ours = |pool: &ThreadPool| {
        let mut w = world.clone();
        let mut backend = create_cpu_backend(BackendKind::Cpu).expect("the cpu backend");
        let mut t = Timing::default();
        pool.install(|| {
            for tick in 0..args.warmup + args.ticks {
                let r = t.run(tick >= args.warmup, || backend.step(&mut w, &k)).expect("a cpu step");
                contacts = r.static_contacts + r.dynamic_contacts;
            }
        });
        t
    };
    let ours_all = ours(all);
    let ours_one = ours(one);
    let built = Instant::now();
    let mut rapier = RapierWorld::from_world(&world, &config);
    eprintln!("step {name}: Rapier world built in {:.1} s", built.elapsed().as_secs_f64());
    let mut t_rapier = Timing::default();
    for tick in 0..args.warmup + args.ticks {
        t_rapier.run(tick >= args.warmup, || rapier.step());
    }
    eprintln!(
        "  whole step: ours {:.2} ms ({} thr), {:.2} ms (1 thr); Rapier {:.2} ms",
        ours_all.median(),
        all.current_num_threads(),
        ours_one.median(),
        t_rapier.median()
    );
    StepRow {
        scenario: name.into(),
        dynamic: world.dynamics.len(),
        static_prims: world.statics.prim_count(),
        terrain: format!("{}x{} samples", world.terrain.width(), world.terrain.depth()),
        ours_all: (&ours_all).into(),
        ours_one: (&ours_one).into(),
        rapier: (&t_rapier).into(),
        ours_threads: all.current_num_threads(),
        rapier_threads: "1 (default features, no `parallel`)",
        ours_contacts_last: contacts,
        rapier_contact_pairs_last: rapier.contact_pairs(),
    }
}

fn ms(v: f64) -> String {
    if v >= 100.0 {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

fn ratio(ours: &Measured, theirs: &Measured) -> String {
    format!("{:.2}", ours.median_ms / theirs.median_ms)
}

fn markdown(report: &Report) -> String {
    let mut s = String::new();
    let n = report.threads_all;
    let a = report.args;
    let _ = writeln!(
        s,
        "#### Broad phase, full build (ms, median of {} builds after {} warm-up; ratio = ours / Rapier)\n",
        a.builds, a.warmup
    );
    let _ = writeln!(
        s,
        "| set | dynamic | static prims | pairs dyn-dyn ours / Rapier | pairs dyn-static ours / Rapier | equal | \
         ours {n} thr | ours 1 thr | Rapier 1 thr | ratio {n} thr | ratio 1 thr |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|:-:|---:|---:|---:|---:|---:|");
    for r in &report.broad {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} / {} | {} / {} | {} | {} | {} | {} | {} | {} |",
            r.set,
            r.dynamic,
            r.static_prims,
            r.full_pairs_dynamic[0],
            r.full_pairs_dynamic[1],
            r.full_pairs_static[0],
            r.full_pairs_static[1],
            if r.full_equal { "yes" } else { "**NO**" },
            ms(r.full_ours_all.median_ms),
            ms(r.full_ours_one.median_ms),
            ms(r.full_rapier.median_ms),
            ratio(&r.full_ours_all, &r.full_rapier),
            ratio(&r.full_ours_one, &r.full_rapier),
        );
    }
    let _ = writeln!(
        s,
        "\n#### Broad phase, incremental: one tick of motion, then each side's update \
         (ms, median of {} ticks after {} warm-up; ratio = ours / Rapier exact)\n",
        a.ticks, a.warmup
    );
    let _ = writeln!(
        s,
        "| set | moved (median) | pairs dyn-dyn ours / Rapier | pairs dyn-static ours / Rapier | equal ticks | \
         ours {n} thr | ours 1 thr | Rapier exact | Rapier default skin | ratio {n} thr | ratio 1 thr | \
         default-skin pairs (dyn-dyn + dyn-static) |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|:-:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &report.broad {
        let _ = writeln!(
            s,
            "| {} | {} | {} / {} | {} / {} | {}/{} | {} | {} | {} | {} | {} | {} | {} + {}{} |",
            r.set,
            r.moved_median,
            r.inc_pairs_dynamic[0],
            r.inc_pairs_dynamic[1],
            r.inc_pairs_static[0],
            r.inc_pairs_static[1],
            r.inc_equal_ticks,
            r.inc_ticks,
            ms(r.inc_ours_all.median_ms),
            ms(r.inc_ours_one.median_ms),
            ms(r.inc_rapier.median_ms),
            ms(r.inc_rapier_default_skin.median_ms),
            ratio(&r.inc_ours_all, &r.inc_rapier),
            ratio(&r.inc_ours_one, &r.inc_rapier),
            r.default_skin_pairs[0],
            r.default_skin_pairs[1],
            if r.default_skin_superset { " (⊇ ours)" } else { " (**misses some of ours**)" },
        );
    }
    let _ = writeln!(s, "\n#### Broad phase, CPU time per run (ms, all threads of the process, mean)\n");
    let _ = writeln!(
        s,
        "| set | full: ours {n} thr | full: ours 1 thr | full: Rapier | incr.: ours {n} thr | incr.: ours 1 thr | \
         incr.: Rapier exact | incr.: Rapier default skin |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
    for r in &report.broad {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            r.set,
            ms(r.full_ours_all.cpu_ms_per_run),
            ms(r.full_ours_one.cpu_ms_per_run),
            ms(r.full_rapier.cpu_ms_per_run),
            ms(r.inc_ours_all.cpu_ms_per_run),
            ms(r.inc_ours_one.cpu_ms_per_run),
            ms(r.inc_rapier.cpu_ms_per_run),
            ms(r.inc_rapier_default_skin.cpu_ms_per_run),
        );
    }
    if !report.step.is_empty() {
        let _ = writeln!(
            s,
            "\n#### Whole step, for orientation only: different physics models \
             (ms per step, median of {} steps after {} warm-up)\n",
            a.ticks, a.warmup
        );
        let _ = writeln!(
            s,
            "Rapier solves full rigid-body dynamics with a constraint solver; Myriad integrates Verlet with \
             impulse responses. Same objects, shapes, statics, terrain samples and gravity; not the same job.\n"
        );
        let _ = writeln!(
            s,
            "| scenario | dynamic | static prims | terrain | Myriad {n} thr | Myriad 1 thr | Rapier | \
             Myriad / Rapier ({n} thr) | Myriad / Rapier (1 thr) | CPU ms/step Myriad {n} thr / 1 thr / Rapier | \
             contacts Myriad / Rapier pairs |"
        );
        let _ = writeln!(s, "|---|---:|---:|---|---:|---:|---:|---:|---:|---|---|");
        for r in &report.step {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} / {} / {} | {} / {} |",
                r.scenario,
                r.dynamic,
                r.static_prims,
                r.terrain,
                ms(r.ours_all.median_ms),
                ms(r.ours_one.median_ms),
                ms(r.rapier.median_ms),
                ratio(&r.ours_all, &r.rapier),
                ratio(&r.ours_one, &r.rapier),
                ms(r.ours_all.cpu_ms_per_run),
                ms(r.ours_one.cpu_ms_per_run),
                ms(r.rapier.cpu_ms_per_run),
                r.ours_contacts_last,
                r.rapier_contact_pairs_last,
            );
        }
    }
    let _ =
        writeln!(s, "\nRapier: {}. Myriad: the `cpu` backend's LBVH, rayon pools of {n} and 1 threads.", report.rapier);
    s
}

fn main() {
    let args = Args::parse();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (all, one) = (pool(threads), pool(1));
    let mut report = Report {
        args: &args,
        threads_all: threads,
        rapier: "rapier3d 0.36 (parry3d 0.31), default features: single-threaded",
        broad: Vec::new(),
        step: Vec::new(),
    };
    for name in &args.scenario {
        report.broad.push(broad_phase(name, &args, &all, &one));
    }
    for name in args.step_scenario.iter().filter(|s| !s.is_empty()) {
        report.step.push(whole_step(name, &args, &all, &one));
    }
    print!("{}", markdown(&report));
    if let Some(path) = &args.json {
        let json = serde_json::to_string_pretty(&report).expect("serialisable rows");
        std::fs::write(path, json).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
        eprintln!("wrote {}", path.display());
    }
    let bad = report.broad.iter().filter(|r| !r.full_equal || r.inc_equal_ticks != r.inc_ticks).count();
    if bad > 0 {
        eprintln!("{bad} set(s) with differing pair sets");
        std::process::exit(1);
    }
}
