//! The probe on a small world in process: what its figures mean, not how fast.

use myriad_core::ScenarioSpec;
use myriad_interest::ReplicationConfig;
use myriad_physics::BackendKind;
use myriad_server::ServerConfig;

use super::*;

/// The largest error of a state drawn exactly: quantization to 1/64 unit rounds each
/// axis by at most 1/128.
const QUANTIZATION: f32 = 0.0136;

fn run(aoi_size: f32, send_budget_kbps: f64, delay_ticks: f64) -> QualityProbe {
    run_probe(aoi_size, send_budget_kbps, delay_ticks, None).0
}

fn run_probe(
    aoi_size: f32,
    send_budget_kbps: f64,
    delay_ticks: f64,
    shadow: Option<(ReplicationConfig, usize, Link)>,
) -> (QualityProbe, usize, f64) {
    let world = ScenarioSpec::custom(11).counts(1_200, 40, 300).map_size(256.0, 129).build().unwrap();
    let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
    let config = ServerConfig { aoi_size, send_budget_kbps, ..ServerConfig::default() };
    let mut bench = TickBench::new(config, world, backend).unwrap();
    let interpolation = Interpolation { delay_ticks, ..Interpolation::default() };
    let config = QualityConfig { players: 16, every: 2, seed: 3, aoi_size, tick_rate_hz: 30, interpolation, shadow };
    let mut probe = QualityProbe::new(&bench, config);
    // Long enough for every object a client lacks to come (new ones starve within 30
    // ticks whatever the budget).
    for _ in 0..36 {
        bench.tick_with(|bot, tick, records| probe.on_update(bot, tick, records)).unwrap();
        probe.after_tick(bench.world());
    }
    probe.start_measuring();
    let mut bytes = 0;
    for _ in 0..24 {
        bytes += bench.tick_with(|bot, tick, records| probe.on_update(bot, tick, records)).unwrap().work.bytes;
        probe.after_tick(bench.world());
    }
    let players = probe.players();
    // Bytes per player and second, over all players, at 30 ticks a second.
    let live = bytes as f64 / bench.players() as f64 / (24.0 / 30.0);
    (probe, players, live)
}

const TICK_MS: f64 = 1000.0 / 30.0;

#[test]
fn with_a_generous_budget_near_objects_stay_within_their_bound() {
    let probe = run(40.0, 4_000.0, 2.0);
    assert_eq!(probe.players(), 16);
    let (s, info) = (probe.summary(), probe.information_summary());
    assert!(info.staleness_all_ms.samples > 100, "{info:?}");
    assert!(info.staleness_near_ms.samples > 0 && info.staleness_near_ms.samples <= info.staleness_all_ms.samples);
    assert_eq!(s.missing_all, 0, "every object of the AOI came: {s:?}");
    // A changing object within 30 units is sent at least every third tick, so the
    // client's information about it is never more than two ticks old.
    assert!(info.staleness_near_ms.max <= 2.0 * TICK_MS + 0.5, "{info:?}");
    // Drawn between states at most three ticks apart: within a unit.
    assert!(s.error_near.samples > 100 && s.error_near.p99 < 1.0, "{s:?}");
    assert!(s.error_near.p50 <= f64::from(QUANTIZATION), "most near objects are drawn exactly: {s:?}");
}

#[test]
fn a_small_budget_makes_far_objects_wait_and_drawn_off() {
    // A 200-unit AOI holds most of the map; 64 kbit/s holds a score of records a tick.
    let probe = run(200.0, 64.0, 2.0);
    let (s, info) = (probe.summary(), probe.information_summary());
    assert!(info.staleness_all_ms.p99 > info.staleness_near_ms.p99, "far objects wait longer: {info:?}");
    assert!(s.error_all.p99 > f64::from(QUANTIZATION), "waiting objects are drawn off: {s:?}");
    // Both ages are whole numbers of ticks (on the server's clock, no network delay), to
    // the histograms' precision (3 significant digits: a bucket of 0.36 ms at 733 ms).
    for v in [s.staleness_all_ms.p50, s.staleness_all_ms.p99, info.staleness_all_ms.p99, info.staleness_all_ms.max] {
        let off = (v - (v / TICK_MS).round() * TICK_MS).abs();
        assert!(off < 0.01 * TICK_MS + v / 1024.0, "{v} ms is not whole ticks: {s:?} {info:?}");
    }
}

#[test]
fn an_unchanged_object_ages_while_the_information_stays_current() {
    // Most of the world's objects settle and stop: protocol 3 confirms them only now and
    // then, so the newest state a client holds grows old while it is still the current
    // one. The information age tells the two apart; the newest state's age does not.
    let probe = run(60.0, 4_000.0, 2.0);
    let (s, info) = (probe.summary(), probe.information_summary());
    assert!(s.staleness_all_ms.p99 >= 4.0 * TICK_MS, "unchanged objects are not resent every tick: {s:?}");
    assert!(info.staleness_all_ms.p99 < s.staleness_all_ms.p99, "{s:?} {info:?}");
    assert_eq!(info.staleness_all_ms.samples, s.staleness_all_ms.samples, "the same objects, the same samples");
}

#[test]
fn a_shadow_with_a_smaller_budget_sends_less_than_the_live_server() {
    let small = ReplicationConfig { budget_bytes_per_tick: 16_000.0 / 8.0 / 30.0, ..ReplicationConfig::default() };
    let (probe, _, live_bytes) = run_probe(60.0, 256.0, 2.0, Some((small, 2, Link::default())));
    let row = probe.shadow_row().expect("the shadows ran");
    assert_eq!(row.unresolved, 0, "every record resolved against a state the client held");
    assert!(row.relative_share > 0.3, "deltas were used: {row:?}");
    let (v2, live) = (&row.v2, &row.live);
    // The same objects looked at: each either held (a sample) or missing.
    let looked = |q: &crate::bench::QualityRowFigures| q.staleness_all_ms.samples + q.missing_all;
    assert!(v2.staleness_near_ms.samples > 100 && looked(v2) == looked(live), "{row:?}");
    assert!(row.bytes_per_player_s < live_bytes, "{} against {live_bytes}", row.bytes_per_player_s);
    // The larger budget keeps the live clients more current, and none of their objects
    // missing.
    assert!(live.staleness_all_ms.p99 < v2.staleness_all_ms.p99, "{row:?}");
    assert_eq!(live.missing_all, 0, "{row:?}");
    assert!(v2.missing_all > 0, "a sixteenth of the budget leaves objects waiting: {row:?}");
}

#[test]
fn protocol_3_through_loss_and_delay_only_waits() {
    let budget = ReplicationConfig { budget_bytes_per_tick: 32_000.0 / 30.0, ..ReplicationConfig::default() };
    let lossy = Link { loss: 0.05, delay_ms: 100.0, jitter_ms: 20.0 };
    let (clean, _, _) = run_probe(60.0, 64.0, 2.0, Some((budget, 2, Link::default())));
    let (probe, _, _) = run_probe(60.0, 64.0, 2.0, Some((budget, 2, lossy)));
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
