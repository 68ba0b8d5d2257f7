use super::*;
use myriad_protocol::QuantPos;

fn rec(id: u64, x: f32) -> StateRecord {
    StateRecord { id, kind: ShapeKind::Box, pos: QuantPos::from_f32([x, 0.0, 0.0]) }
}

/// 3 ticks: the 100 ms cap at 30 Hz.
const CAP: f64 = 3.0;

fn x(r: Option<Rendered>) -> (f32, RenderMode) {
    let r = r.expect("object known");
    (r.position[0], r.mode)
}

#[test]
fn newer_ticks_win_and_late_ones_are_ignored() {
    let mut m = WorldMirror::new(Duration::from_secs(1));
    let t = Instant::now();
    assert_eq!(m.apply(10, [rec(1, 1.0), rec(2, 2.0)], t), 2);
    assert_eq!(m.apply(9, [rec(1, 5.0)], t), 0, "a late datagram does not overwrite");
    assert_eq!(m.get(1).unwrap().position[0], 1.0);
    assert_eq!(m.apply(11, [rec(1, 3.0)], t), 1);
    assert_eq!(m.get(1).unwrap().position[0], 3.0);
    assert_eq!(m.apply(11, [rec(1, 4.0)], t), 0, "a duplicate changes nothing");
    let ticks: Vec<u64> = m.get(1).unwrap().states().map(|s| s.tick).collect();
    assert_eq!(ticks, [9, 10, 11], "the late state filled the history");
}

#[test]
fn stale_marking() {
    let mut m = WorldMirror::new(Duration::from_millis(100));
    let t = Instant::now();
    m.apply(1, [rec(1, 0.0)], t);
    m.apply(5, [rec(2, 0.0)], t + Duration::from_millis(150));
    assert_eq!(m.mark_stale(t + Duration::from_millis(200)), 1);
    assert!(m.get(1).unwrap().stale);
    assert!(!m.get(2).unwrap().stale);
    assert_eq!(m.fresh(), 1);
    m.forget_older_than(Duration::from_millis(100), t + Duration::from_millis(200));
    assert_eq!(m.len(), 1);
}

#[test]
fn interpolates_between_the_states_around_the_render_tick() {
    let mut m = WorldMirror::new(Duration::from_secs(1));
    let t = Instant::now();
    for (tick, pos) in [(10, 0.0), (11, 1.0), (13, 5.0)] {
        m.apply(tick, [rec(1, pos)], t);
    }
    assert_eq!(x(m.sample(1, 10.5)), (0.5, RenderMode::Between));
    assert_eq!(x(m.sample(1, 11.0)), (1.0, RenderMode::Between));
    // Across the missing tick 12: halfway from 1 to 5.
    assert_eq!(x(m.sample(1, 12.0)), (3.0, RenderMode::Between));
    assert_eq!(x(m.sample(1, 13.0)), (5.0, RenderMode::Between));
    assert_eq!(x(m.sample(1, 9.0)), (0.0, RenderMode::Oldest), "before the history: its oldest state");
    assert_eq!(m.sample(2, 11.0), None);
}

#[test]
fn a_reordered_state_takes_its_place_and_the_history_stays_bounded() {
    let mut m = WorldMirror::new(Duration::from_secs(1));
    let t = Instant::now();
    m.apply(10, [rec(1, 0.0)], t);
    m.apply(12, [rec(1, 6.0)], t);
    assert_eq!(x(m.sample(1, 11.0)).0, 3.0, "without tick 11: the straight line");
    assert_eq!(m.apply(11, [rec(1, 5.0)], t), 0, "an older state is not the newest");
    assert_eq!(x(m.sample(1, 11.0)).0, 5.0, "with it: its position");
    assert_eq!(x(m.sample(1, 11.5)).0, 5.5);
    for tick in 13..=20 {
        m.apply(tick, [rec(1, tick as f32)], t);
    }
    let ticks: Vec<u64> = m.get(1).unwrap().states().map(|s| s.tick).collect();
    assert_eq!(ticks, [17, 18, 19, 20], "the newest {HISTORY} states");
    // A state older than everything kept is dropped; one inside the history fills a gap.
    m.apply(16, [rec(1, 100.0)], t);
    m.apply(22, [rec(1, 22.0)], t);
    m.apply(21, [rec(1, 21.5)], t);
    let states: Vec<(u64, f32)> = m.get(1).unwrap().states().map(|s| (s.tick, s.position[0])).collect();
    assert_eq!(states, [(19, 19.0), (20, 20.0), (21, 21.5), (22, 22.0)]);
}

#[test]
fn an_object_at_rest_stays_at_rest_until_the_tick_before_its_next_state() {
    let mut m = WorldMirror::new(Duration::from_secs(1));
    let t = Instant::now();
    // Still at 2 (two states at one place), then sent again only when it moved at 20.
    for (tick, pos) in [(10, 0.0), (11, 2.0), (12, 2.0), (20, 5.0)] {
        m.apply(tick, [rec(1, pos)], t);
    }
    assert_eq!(x(m.sample(1, 10.5)).0, 1.0, "moving: between the two");
    assert_eq!(x(m.sample(1, 15.0)), (2.0, RenderMode::Between), "at rest across the gap");
    assert_eq!(x(m.sample(1, 19.0)).0, 2.0, "until the tick before its next state");
    assert_eq!(x(m.sample(1, 19.5)).0, 3.5, "then the last tick's move");
    assert_eq!(x(m.sample(1, 20.0)).0, 5.0);
    // Not at rest (the states before differ): across the gap on a straight line.
    m.apply(10, [rec(2, 0.0)], t);
    m.apply(11, [rec(2, 1.0)], t);
    m.apply(15, [rec(2, 5.0)], t);
    assert_eq!(x(m.sample(2, 13.0)).0, 3.0);
    // Stopped (two equal states): not carried on past them.
    m.apply(21, [rec(1, 5.0)], t);
    assert_eq!(x(m.sample(1, 23.0)), (5.0, RenderMode::Extrapolated));
}

#[test]
fn extrapolates_for_at_most_the_cap_then_holds() {
    let mut m = WorldMirror::new(Duration::from_secs(1));
    let t = Instant::now();
    m.apply(10, [rec(1, 0.0)], t);
    m.apply(12, [rec(1, 2.0)], t);
    // 1 unit a tick; the cap is 100 ms = 3 ticks at 30 Hz.
    assert_eq!(x(m.sample(1, 13.0)), (3.0, RenderMode::Extrapolated));
    assert_eq!(x(m.sample(1, 12.0 + CAP)), (5.0, RenderMode::Extrapolated));
    assert_eq!(x(m.sample(1, 40.0)), (5.0, RenderMode::Held), "held where the cap stopped it");
    // A single state is held as it is.
    m.apply(12, [rec(2, 7.0)], t);
    assert_eq!(x(m.sample(2, 14.0)), (7.0, RenderMode::Held));
    // Half the rate (dilation 500 ‰): 100 ms are 1.5 ticks.
    m.set_timing(30, 500, t);
    assert_eq!(x(m.sample(1, 20.0)), (3.5, RenderMode::Held));
    // No extrapolation at all.
    let m = m.with_interpolation(Interpolation { max_extrapolation: Duration::ZERO, ..Interpolation::default() });
    assert_eq!(x(m.sample(1, 13.0)), (2.0, RenderMode::Held));
}

#[test]
fn the_render_tick_trails_the_server_by_the_delay_and_renders_between_states() {
    let t0 = Instant::now();
    let mut m = WorldMirror::new(Duration::from_secs(1));
    assert_eq!(m.render_tick(t0), None);
    assert_eq!(m.rendered(t0).count(), 0);
    // Tick k arrives at k/30 s, the object moving 1 unit a tick.
    let at = |tick: u64| t0 + Duration::from_secs_f64(tick as f64 / 30.0);
    for tick in 0..=30 {
        m.apply(tick, [rec(1, tick as f32)], at(tick));
    }
    let render = m.render_tick(at(30)).unwrap();
    assert!((render - 28.0).abs() < 1e-9, "{render}");
    let (id, _, r) = m.rendered(at(30)).next().unwrap();
    assert_eq!((id, r.position[0], r.mode), (1, 28.0, RenderMode::Between));
    // Updates stop: the render time runs on, extrapolation runs to the cap and holds.
    let later = m.render_tick(at(32)).unwrap();
    assert!((later - (28.0 + 2.0 * 0.98)).abs() < 1e-6, "{later}");
    let (_, _, r) = m.rendered(at(40)).next().unwrap();
    assert_eq!((r.position[0], r.mode), (33.0, RenderMode::Held));
    // A new session: the clock starts over.
    m.clear();
    assert_eq!(m.render_tick(at(40)), None);
}
