//! How the device outbound splits a build's players into chunks ([`ChunkPlan`]).
//!
//! Every chunk's kernels are queued at once, so the device chooses for the chunks back to
//! back, never waiting for the host; the host seals and sends chunk `c` as soon as the
//! device is done with it, while the device chooses for chunk `c + 1`. With `d` the
//! device's time a player and `h` the host's, the build ends when the host is done with
//! the last chunk: at `d·N + h·s_last` when the device is the slower (`h < d`: the host
//! keeps up and then seals the last chunk alone), at `d·s_first + h·N` when the host is.
//! Both are least, and the host never waits in between, when each chunk is `ρ = h / d`
//! times the one before it (a chunk's host work then takes as long as the device's work
//! on the next): chunks that shrink, with the last one small, where the device is the
//! slower, and grow, with the first one small, where the host is. Equal chunks leave the
//! host a whole quarter of its work after the device is done (four chunks).
//!
//! [`ChunkPlan::observe`] measures `ρ` from each build (the host's sealing and sending
//! against the device's time for the choice), so the chunks follow the load: scenario 3
//! at AOI 100 measures 0.44–0.66 on an H200 (chunks of 5,862, 2,549, 1,107 and 482
//! players: 14.88 ms a tick against 15.45 in equal chunks, one run each,
//! `docs/benchmarks.md`).
//! A measured plan never lets chunks grow (`ρ` is taken at most 1): where the host is
//! the slower, the first chunk's device time it would save is small, and large chunks
//! cost the host more: scenario 4 at AOI 14 (`ρ` about 5) in chunks growing from 592 to
//! 37,615 players took the host 12.3–14.7 ms a build against 11.4–11.9 in equal chunks,
//! and the tick 29.90 ms against 25.45 (most likely a large chunk's sealed datagrams are
//! out of the caches by the time they are sent). Chunks below [`MIN_CHUNK`] players are
//! not made (each costs some fixed work on both sides): the plan takes fewer chunks
//! instead. The chunks change nothing that is sent, only when.

/// Fewest players in a chunk of a tapered plan (where there are enough players): each
/// chunk costs four launches, an event, a wait and a hand-over to the pool. A chosen
/// floor, not a measured optimum (no chunk's fixed cost was measured apart).
const MIN_CHUNK: usize = 256;

/// The measured ratio is kept within these bounds: chunks never grow (module docs).
const RATIO_BOUNDS: (f64, f64) = (0.25, 1.0);

/// Weight of the newest build in the measured ratio (an exponential mean).
const RATIO_WEIGHT: f64 = 0.3;

/// How the sizes of a build's chunks relate.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Taper {
    /// Chunks of equal size (within one player).
    Equal,
    /// Each chunk this many times the one before it.
    Fixed(f64),
    /// Each chunk `ρ` times the one before it, `ρ` measured from the builds and at
    /// most 1 (module docs); equal chunks until the first measurement.
    Measured,
}

/// How a build's players are split into chunks: see the module docs.
#[derive(Debug, Clone, PartialEq)]
pub struct ChunkPlan {
    count: usize,
    taper: Taper,
    /// The measured `ρ` (for [`Taper::Measured`]).
    measured: Option<f64>,
    /// Fewest players in a chunk of a tapered plan ([`MIN_CHUNK`] unless told).
    min_chunk: usize,
}

impl ChunkPlan {
    /// Chunks of players a build runs in when `MYRIAD_REPLICA_CHUNKS` does not say.
    pub const DEFAULT_COUNT: usize = 4;

    /// `count` chunks (at least 1) of equal size.
    pub fn equal(count: usize) -> ChunkPlan {
        ChunkPlan { count: count.max(1), taper: Taper::Equal, measured: None, min_chunk: MIN_CHUNK }
    }

    /// `count` chunks (at least 1), each `ratio` times the one before it (a ratio that is
    /// not a positive number: equal chunks).
    pub fn tapered(count: usize, ratio: f64) -> ChunkPlan {
        let taper = if ratio.is_finite() && ratio > 0.0 { Taper::Fixed(ratio) } else { Taper::Equal };
        ChunkPlan { count: count.max(1), taper, measured: None, min_chunk: MIN_CHUNK }
    }

    /// `count` chunks (at least 1), tapered by the measured ratio.
    pub fn measured(count: usize) -> ChunkPlan {
        ChunkPlan { count: count.max(1), taper: Taper::Measured, measured: None, min_chunk: MIN_CHUNK }
    }

    /// The same plan, its tapered chunks at least `players` players each (at least 1)
    /// where there are enough players: for tests of many chunks on few players.
    pub fn with_min_chunk(mut self, players: usize) -> ChunkPlan {
        self.min_chunk = players.max(1);
        self
    }

    /// The plan `MYRIAD_REPLICA_CHUNKS` (a count, default [`ChunkPlan::DEFAULT_COUNT`]) and
    /// `MYRIAD_REPLICA_TAPER` (`measured`, the default; `equal`; or a ratio) say.
    pub fn from_env() -> ChunkPlan {
        let count = std::env::var("MYRIAD_REPLICA_CHUNKS").ok();
        let taper = std::env::var("MYRIAD_REPLICA_TAPER").ok();
        ChunkPlan::from_values(count.as_deref(), taper.as_deref())
    }

    /// [`ChunkPlan::from_env`] of these values; one that does not parse is reported and
    /// its default taken.
    fn from_values(count: Option<&str>, taper: Option<&str>) -> ChunkPlan {
        let count = match count.map(|v| (v, v.trim().parse::<usize>())) {
            None => ChunkPlan::DEFAULT_COUNT,
            Some((_, Ok(n))) if n >= 1 => n,
            Some((v, _)) => {
                tracing::warn!(
                    value = v,
                    default = ChunkPlan::DEFAULT_COUNT,
                    "MYRIAD_REPLICA_CHUNKS is not a count of at least 1"
                );
                ChunkPlan::DEFAULT_COUNT
            }
        };
        match taper.map(str::trim) {
            None | Some("measured") => ChunkPlan::measured(count),
            Some("equal") => ChunkPlan::equal(count),
            Some(v) => match v.parse::<f64>() {
                Ok(r) if r.is_finite() && r > 0.0 => ChunkPlan::tapered(count, r),
                _ => {
                    tracing::warn!(value = v, "MYRIAD_REPLICA_TAPER is not `measured`, `equal` or a positive ratio");
                    ChunkPlan::measured(count)
                }
            },
        }
    }

    /// The ratio of each chunk to the one before it that the next build uses.
    pub fn ratio(&self) -> f64 {
        match self.taper {
            Taper::Equal => 1.0,
            Taper::Fixed(r) => r,
            Taper::Measured => self.measured.unwrap_or(1.0),
        }
    }

    /// Notes a build's host time for sealing and sending (`host_ms`) against the device's
    /// for choosing (`device_ms`), for a measured taper.
    pub fn observe(&mut self, host_ms: f64, device_ms: f64) {
        if self.taper != Taper::Measured || !(host_ms > 0.0 && device_ms > 0.0) {
            return;
        }
        let rho = (host_ms / device_ms).clamp(RATIO_BOUNDS.0, RATIO_BOUNDS.1);
        self.measured = Some(match self.measured {
            None => rho,
            Some(m) => m + RATIO_WEIGHT * (rho - m),
        });
    }

    /// The sizes of the chunks of a build of `players` players, in order, into `out`:
    /// each at least one player, together every player (none when there are none).
    pub fn sizes(&self, players: usize, out: &mut Vec<usize>) {
        out.clear();
        if players == 0 {
            return;
        }
        let ratio = self.ratio();
        let tapered = ratio != 1.0;
        let mut k = self.count.min(players);
        loop {
            split(players, k, ratio, out);
            let least = out.iter().copied().min().unwrap_or(players);
            // Equal chunks are as large as they can be; a tapered plan makes fewer rather
            // than small ones (unless the players are too few for any).
            if k == 1 || (least > 0 && (!tapered || least >= self.min_chunk.min(players / self.count))) {
                return;
            }
            k -= 1;
        }
    }
}

/// `players` split into `k` chunks each `ratio` times the one before, rounded so that
/// the ends are the nearest players to the exact ones (a chunk may come out empty).
fn split(players: usize, k: usize, ratio: f64, out: &mut Vec<usize>) {
    out.clear();
    let weight = |c: usize| ratio.powi(c as i32);
    let total: f64 = (0..k).map(weight).sum();
    let (mut sum, mut end) = (0.0, 0usize);
    for c in 0..k {
        sum += weight(c);
        let next = if c + 1 == k { players } else { ((players as f64) * sum / total).round() as usize };
        let next = next.clamp(end, players);
        out.push(next - end);
        end = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sizes(plan: &ChunkPlan, players: usize) -> Vec<usize> {
        let mut out = Vec::new();
        plan.sizes(players, &mut out);
        out
    }

    #[test]
    fn equal_chunks_differ_by_at_most_one_player_and_cover_everyone() {
        assert_eq!(sizes(&ChunkPlan::equal(4), 10_000), vec![2_500; 4]);
        assert_eq!(sizes(&ChunkPlan::equal(3), 300), vec![100; 3]);
        assert_eq!(sizes(&ChunkPlan::equal(1), 7), vec![7]);
        for (k, n) in [(4, 10), (6, 10), (6, 5), (3, 1), (4, 9_999)] {
            let s = sizes(&ChunkPlan::equal(k), n);
            assert_eq!(s.iter().sum::<usize>(), n, "{k} chunks of {n}: {s:?}");
            assert_eq!(s.len(), k.min(n), "{k} chunks of {n}: {s:?}");
            let (lo, hi) = (s.iter().min().unwrap(), s.iter().max().unwrap());
            assert!(*lo >= 1 && hi - lo <= 1, "{k} chunks of {n}: {s:?}");
        }
        assert!(sizes(&ChunkPlan::equal(4), 0).is_empty());
    }

    #[test]
    fn a_taper_below_one_shrinks_each_chunk_and_above_one_grows_it() {
        let s = sizes(&ChunkPlan::tapered(4, 0.5), 15_000);
        assert_eq!(s, vec![8_000, 4_000, 2_000, 1_000]);
        let s = sizes(&ChunkPlan::tapered(4, 2.0), 15_000);
        assert_eq!(s, vec![1_000, 2_000, 4_000, 8_000]);
        // Scenario 3's players at the ratio measured there: the last chunk is small.
        let s = sizes(&ChunkPlan::tapered(6, 0.6), 10_000);
        assert_eq!(s.iter().sum::<usize>(), 10_000);
        assert!(s.windows(2).all(|w| w[1] < w[0]), "{s:?}");
        assert!(s[5] < 400 && s[5] >= MIN_CHUNK, "{s:?}");
    }

    #[test]
    fn a_tapered_plan_makes_fewer_chunks_rather_than_small_ones() {
        // 0.25⁵ of the first chunk would be 1 player in 1,000: two chunks fewer.
        let s = sizes(&ChunkPlan::tapered(6, 0.25), 10_000);
        assert!(s.len() < 6 && s.iter().all(|&c| c >= MIN_CHUNK), "{s:?}");
        assert_eq!(s.iter().sum::<usize>(), 10_000);
        // Too few players for chunks of MIN_CHUNK: chunks of at least an equal share.
        let s = sizes(&ChunkPlan::tapered(3, 0.5), 12);
        assert_eq!(s, vec![8, 4]);
        // Unless told: the device test's five chunks on 300 players.
        let s = sizes(&ChunkPlan::tapered(5, 0.5).with_min_chunk(1), 300);
        assert_eq!(s, vec![155, 77, 39, 19, 10]);
        // Fewer players than chunks: one each at most.
        let s = sizes(&ChunkPlan::tapered(5, 2.0), 3);
        assert_eq!(s.iter().sum::<usize>(), 3);
        assert!(s.iter().all(|&c| c >= 1), "{s:?}");
    }

    #[test]
    fn a_measured_plan_starts_equal_then_follows_the_ratio_of_host_to_device() {
        let mut plan = ChunkPlan::measured(4);
        assert_eq!(sizes(&plan, 4_000), vec![1_000; 4]);
        plan.observe(4.5, 7.5);
        assert!((plan.ratio() - 0.6).abs() < 1e-9);
        // An exponential mean: one build moves it by RATIO_WEIGHT of the difference.
        plan.observe(7.5, 7.5);
        assert!((plan.ratio() - (0.6 + RATIO_WEIGHT * 0.4)).abs() < 1e-9);
        // Where the host is the slower, the chunks stay equal, never growing.
        let mut host_bound = ChunkPlan::measured(4);
        host_bound.observe(12.0, 2.4);
        assert_eq!(sizes(&host_bound, 50_000), vec![12_500; 4]);
        // Bounded, and nothing measured from nothing.
        for _ in 0..50 {
            plan.observe(100.0, 1.0);
        }
        assert!((plan.ratio() - RATIO_BOUNDS.1).abs() < 1e-6);
        let before = plan.ratio();
        plan.observe(0.0, 3.0);
        plan.observe(3.0, 0.0);
        plan.observe(f64::NAN, 3.0);
        assert_eq!(plan.ratio(), before);
        // An equal or fixed plan measures nothing.
        let mut fixed = ChunkPlan::tapered(4, 0.5);
        fixed.observe(9.0, 1.0);
        assert_eq!(fixed.ratio(), 0.5);
        let mut equal = ChunkPlan::equal(4);
        equal.observe(9.0, 1.0);
        assert_eq!(equal.ratio(), 1.0);
    }

    #[test]
    fn the_environment_names_a_count_and_a_taper_and_anything_else_is_the_default() {
        assert_eq!(ChunkPlan::from_values(None, None), ChunkPlan::measured(ChunkPlan::DEFAULT_COUNT));
        assert_eq!(ChunkPlan::from_values(Some(" 6 "), Some("equal")), ChunkPlan::equal(6));
        assert_eq!(ChunkPlan::from_values(Some("1"), Some("0.5")), ChunkPlan::tapered(1, 0.5));
        assert_eq!(ChunkPlan::from_values(Some("3"), Some("measured")), ChunkPlan::measured(3));
        for bad in ["0", "-2", "four", ""] {
            assert_eq!(
                ChunkPlan::from_values(Some(bad), None),
                ChunkPlan::measured(ChunkPlan::DEFAULT_COUNT),
                "{bad:?}"
            );
        }
        for bad in ["0", "-1", "NaN", "inf", "steep"] {
            assert_eq!(ChunkPlan::from_values(Some("4"), Some(bad)), ChunkPlan::measured(4), "{bad:?}");
        }
    }
}
