//! The probe on a small world in process: what its figures mean, not how fast.

use myriad_core::ScenarioSpec;
use myriad_interest::ReplicationConfig;
use myriad_physics::BackendKind;
use myriad_server::ServerConfig;

use super::*;

/// The largest error of a state drawn exactly: quantization to 1/64 unit rounds each
/// axis by at most 1/128.
const QUANTIZATION: f32 = 0.0136;

fn run(aoi_size: f32, max_datagrams_per_player: usize, delay_ticks: f64) -> (QualitySummary, usize) {
    let (probe, players, _) = run_probe(aoi_size, max_datagrams_per_player, delay_ticks, None);
    (probe.summary(), players)
}

fn run_probe(
    aoi_size: f32,
    max_datagrams_per_player: usize,
    delay_ticks: f64,
    shadow: Option<(ReplicationConfig, usize, Link)>,
) -> (QualityProbe, usize, f64) {
    let world = ScenarioSpec::custom(11).counts(1_200, 40, 300).map_size(256.0, 129).build().unwrap();
    let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
    let config = ServerConfig { aoi_size, max_datagrams_per_player, ..ServerConfig::default() };
    let mut bench = TickBench::new(config, world, backend).unwrap();
    let interpolation = Interpolation { delay_ticks, ..Interpolation::default() };
    let config = QualityConfig { players: 16, every: 2, seed: 3, aoi_size, tick_rate_hz: 30, interpolation, shadow };
    let mut probe = QualityProbe::new(&bench, config);
    // Long enough for a client three ticks away to hold its view.
    for _ in 0..10 {
        bench.tick_with(|bot, u| probe.on_update(bot, u)).unwrap();
        probe.after_tick(bench.world());
    }
    probe.start_measuring();
    let mut bytes = 0;
    for _ in 0..24 {
        bytes += bench.tick_with(|bot, u| probe.on_update(bot, u)).unwrap().work.bytes;
        probe.after_tick(bench.world());
    }
    let players = probe.players();
    // Bytes per player and second, over all players, at 30 ticks a second.
    let live = bytes as f64 / bench.players() as f64 / (24.0 / 30.0);
    (probe, players, live)
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

#[test]
fn protocol_2_beside_the_live_one_sends_less_and_keeps_near_objects_current() {
    let budget = ReplicationConfig { budget_bytes_per_tick: 32_000.0 / 30.0, ..ReplicationConfig::default() };
    let (probe, _, live_bytes) = run_probe(60.0, 2, 2.0, Some((budget, 2, Link::default())));
    let row = probe.shadow_row().expect("the shadows ran");
    assert_eq!(row.unresolved, 0, "every record resolved against a state the client held");
    assert!(row.relative_share > 0.3, "deltas were used: {row:?}");
    let (v2, live) = (&row.v2, &row.live);
    assert!(v2.staleness_near_ms.samples > 100 && v2.staleness_near_ms.samples == live.staleness_near_ms.samples);
    assert_eq!(v2.missing_near, 0, "{row:?}");
    // Near objects are sent at least every third tick: never more than two ticks old.
    assert!(v2.staleness_near_ms.max <= 2.0 * 1000.0 / 30.0 + 0.5, "{row:?}");
    // Interpolated between states at most three ticks apart, drawn within a unit.
    assert!(v2.error_near.p99 < 1.0, "{row:?}");
    assert!(row.bytes_per_player_s < live_bytes, "{} against {live_bytes}", row.bytes_per_player_s);
}

#[test]
fn protocol_2_through_loss_and_delay_only_waits() {
    let budget = ReplicationConfig { budget_bytes_per_tick: 32_000.0 / 30.0, ..ReplicationConfig::default() };
    let lossy = Link { loss: 0.05, delay_ms: 100.0, jitter_ms: 20.0 };
    let (clean, _, _) = run_probe(60.0, 2, 2.0, Some((budget, 2, Link::default())));
    let (probe, _, _) = run_probe(60.0, 2, 2.0, Some((budget, 2, lossy)));
    let (clean, row) = (clean.shadow_row().unwrap(), probe.shadow_row().unwrap());
    assert_eq!(row.unresolved, 0, "no record applied to a state the client lacked: {row:?}");
    // An object entering the view reaches the client a delay (or a loss) later: missing
    // meanwhile, about one sample in a hundred in this small world of walking players.
    assert!(row.v2.missing_all * 100 < 3 * row.v2.staleness_all_ms.samples, "{row:?}");
    // Three ticks each way and a lost datagram now and then: a near object's information
    // is older, but within the 250 ms.
    assert!(row.v2.staleness_near_ms.p99 <= 250.0, "{row:?}");
    assert!(row.v2.staleness_near_ms.p99 > clean.v2.staleness_near_ms.p99, "the delay shows: {row:?}");
    assert!(row.bytes_per_player_s <= 1.2 * clean.bytes_per_player_s, "{row:?} against {clean:?}");
}
