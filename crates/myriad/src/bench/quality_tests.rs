//! The probe on a small world in process: what its figures mean, not how fast.

use myriad_core::ScenarioSpec;
use myriad_physics::BackendKind;
use myriad_server::ServerConfig;

use super::*;

/// The largest error of a state drawn exactly: quantization to 1/64 unit rounds each
/// axis by at most 1/128.
const QUANTIZATION: f32 = 0.0136;

fn run(aoi_size: f32, max_datagrams_per_player: usize, delay_ticks: f64) -> (QualitySummary, usize) {
    let world = ScenarioSpec::custom(11).counts(1_200, 40, 300).map_size(256.0, 129).build().unwrap();
    let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
    let config = ServerConfig { aoi_size, max_datagrams_per_player, ..ServerConfig::default() };
    let mut bench = TickBench::new(config, world, backend).unwrap();
    let interpolation = Interpolation { delay_ticks, ..Interpolation::default() };
    let config = QualityConfig { players: 16, every: 2, seed: 3, aoi_size, tick_rate_hz: 30, interpolation };
    let mut probe = QualityProbe::new(&bench, config);
    for _ in 0..4 {
        bench.tick_with(|bot, u| probe.on_update(bot, u)).unwrap();
    }
    probe.start_measuring();
    for _ in 0..24 {
        bench.tick_with(|bot, u| probe.on_update(bot, u)).unwrap();
        probe.after_tick(bench.world());
    }
    (probe.summary(), probe.players())
}

#[test]
fn within_budget_every_state_is_fresh_and_drawn_where_it_was() {
    // A 40-unit AOI holds a few dozen objects: every one is sent every tick.
    let (s, players) = run(40.0, 2, 2.0);
    assert_eq!(players, 16);
    assert!(s.staleness_all_ms.samples > 100, "{s:?}");
    assert!(s.staleness_near_ms.samples > 0 && s.staleness_near_ms.samples <= s.staleness_all_ms.samples);
    assert_eq!((s.staleness_all_ms.max, s.missing_all), (0.0, 0), "every object of the AOI is sent every tick: {s:?}");
    // Each truth is compared once the render time reached it: the drawn state is the
    // one of that very tick, off only by quantization.
    assert!(s.error_all.samples > 100, "{s:?}");
    assert!(s.error_all.max <= f64::from(QUANTIZATION), "{s:?}");
}

#[test]
fn over_budget_far_objects_age_and_are_drawn_off() {
    // A 200-unit AOI holds most of the map, one datagram a tick carries about a hundred
    // records: the nearest go every tick, the rest in turns.
    let (s, _) = run(200.0, 1, 2.0);
    let tick_ms = 1000.0 / 30.0;
    assert!(s.staleness_all_ms.p99 >= tick_ms, "some objects wait for their turn: {s:?}");
    assert!(s.staleness_near_ms.p50 <= s.staleness_all_ms.p50, "{s:?}");
    assert!(s.error_all.p99 > f64::from(QUANTIZATION), "stale objects are drawn off: {s:?}");
    // Staleness is a whole number of ticks (on the server's clock, no network delay).
    for v in [s.staleness_all_ms.p50, s.staleness_all_ms.p99, s.staleness_all_ms.max] {
        let ticks = v / tick_ms;
        assert!((ticks - ticks.round()).abs() < 0.01, "{v} ms is not whole ticks: {s:?}");
    }
}

#[test]
fn without_render_delay_the_newest_state_is_drawn_at_once() {
    // No delay: the render time is the newest tick, so the comparison happens the same
    // tick and still finds that tick's state.
    let (s, _) = run(40.0, 2, 0.0);
    assert!(s.error_all.samples > 100 && s.error_all.max <= f64::from(QUANTIZATION), "{s:?}");
}
