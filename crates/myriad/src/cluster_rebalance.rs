//! `myriad cluster --rebalance` and `--rebalance-force`: the supervisor's rebalancing
//! from the flags (docs/zones.md, "Cut moves in a live cluster").

use anyhow::{Result, bail};
use myriad_zone::ZoneLayout;
use myriad_zone::rebalance::announce::{LiveOptions, LivePolicy};
use myriad_zone::rebalance::{ForcedMove, StepTimeOptions};

use crate::zones::ClusterArgs;

/// A forced cut move from `AT:X1,X2/Z1` (inner cuts; the layout's edges are kept; an
/// empty list keeps the axis's cuts).
fn parse_forced(text: &str, layout: &ZoneLayout) -> Result<ForcedMove> {
    let bad = || anyhow::anyhow!("--rebalance-force {text:?}: expected AT:X1,X2/Z1 (inner cuts)");
    let (at, cuts) = text.split_once(':').ok_or_else(bad)?;
    let (xs, zs) = cuts.split_once('/').ok_or_else(bad)?;
    let at: u64 = at.trim().parse().map_err(|_| bad())?;
    let inner = |list: &str, now: &[f32]| -> Result<Vec<f32>> {
        if list.trim().is_empty() {
            return Ok(now.to_vec());
        }
        let mid = list.split(',').map(|c| c.trim().parse::<f32>().map_err(|_| bad())).collect::<Result<Vec<_>>>()?;
        if mid.len() + 2 != now.len() {
            bail!("--rebalance-force {text:?}: {} inner cuts for an axis that has {}", mid.len(), now.len() - 2);
        }
        Ok(std::iter::once(now[0]).chain(mid).chain(std::iter::once(now[now.len() - 1])).collect())
    };
    let (now_x, now_z) = layout.cuts();
    Ok(ForcedMove { at, xs: inner(xs, now_x)?, zs: inner(zs, now_z)? })
}

/// The supervisor's rebalancing from the flags (`None`: the cuts stay).
pub(crate) fn live_options(args: &ClusterArgs, layout: &ZoneLayout) -> Result<Option<LiveOptions>> {
    let policy = if !args.rebalance_force.is_empty() {
        LivePolicy::Forced(args.rebalance_force.iter().map(|f| parse_forced(f, layout)).collect::<Result<_>>()?)
    } else if args.rebalance {
        let hz = args.common.tick_hz;
        let budget_ms = if hz > 0.0 { 1e3 / hz } else { StepTimeOptions::default().budget_ms };
        LivePolicy::StepTime(StepTimeOptions { budget_ms, ..StepTimeOptions::default() })
    } else {
        return Ok(None);
    };
    Ok(Some(LiveOptions::new(args.rebalance_lead_ticks, policy)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::{Aabb, Vec3};

    #[test]
    fn forced_moves_name_inner_cuts() {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(1024.0, 50.0, 1024.0));
        let l = ZoneLayout::for_count(&b, 4, 1.5, 2.0).unwrap();
        let f = parse_forced("60:530/490", &l).unwrap();
        assert_eq!((f.at, f.xs, f.zs), (60, vec![0.0, 530.0, 1024.0], vec![0.0, 490.0, 1024.0]));
        let f = parse_forced("90:/", &l).unwrap();
        assert_eq!((f.xs, f.zs), (vec![0.0, 512.0, 1024.0], vec![0.0, 512.0, 1024.0]), "empty lists keep the cuts");
        for bad in ["60", "60:530", "x:530/", "60:530,600/", "60:a/"] {
            assert!(parse_forced(bad, &l).is_err(), "{bad}");
        }
    }
}
