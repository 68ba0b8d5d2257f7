//! What the messages of rebalancing carry besides records: a heartbeat's [`Load`] and
//! the cuts of starts, checkpoints and cut moves (layouts in `docs/zones.md`).

use super::{LOAD_LEN, WireError, f32_at, u32_at, u64_at};
use crate::rebalance::Cuts;

/// What a zone's heartbeat says of its work and its cuts, for the supervisor's
/// rebalancing ([`crate::rebalance::announce`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Load {
    /// Its step (the zone's own work and the physics, not the wait for neighbours), a
    /// moving average over about a second, in microseconds.
    pub step_us: u32,
    /// Objects it owns.
    pub owned: u32,
    /// [`crate::rebalance::live::cuts_digest`] of the cuts it stepped its last tick with.
    pub cuts: u64,
    /// The `apply_at` of the cut move it accepted and has not applied yet (0: none).
    pub pending: u64,
}

impl Load {
    /// The heartbeat body ([`LOAD_LEN`] bytes, little-endian, in field order).
    pub(super) fn to_bytes(self) -> Vec<u8> {
        let mut b = Vec::with_capacity(LOAD_LEN);
        b.extend_from_slice(&self.step_us.to_le_bytes());
        b.extend_from_slice(&self.owned.to_le_bytes());
        b.extend_from_slice(&self.cuts.to_le_bytes());
        b.extend_from_slice(&self.pending.to_le_bytes());
        b
    }

    /// The load in a heartbeat body of [`LOAD_LEN`] bytes (checked by the caller).
    pub(super) fn from_bytes(b: &[u8]) -> Load {
        Load { step_us: u32_at(b, 0), owned: u32_at(b, 4), cuts: u64_at(b, 8), pending: u64_at(b, 16) }
    }
}

/// The header's counts of cuts (x, z) and the cuts' bytes: each axis at least two cuts,
/// finite and ascending (what [`crate::ZoneLayout`] accepts as cuts at all).
pub(super) fn cut_block((xs, zs): &Cuts) -> Result<([u16; 2], Vec<u8>), WireError> {
    let mut counts = [0u16; 2];
    for (n, cuts) in counts.iter_mut().zip([xs, zs]) {
        *n = u16::try_from(cuts.len()).map_err(|_| WireError::Field("cuts"))?;
        check_cuts(cuts)?;
    }
    let b = xs.iter().chain(zs).flat_map(|c| c.to_le_bytes()).collect();
    Ok((counts, b))
}

fn check_cuts(cuts: &[f32]) -> Result<(), WireError> {
    let ok = cuts.len() >= 2 && cuts.iter().all(|c| c.is_finite()) && cuts.windows(2).all(|w| w[0] < w[1]);
    if ok { Ok(()) } else { Err(WireError::Field("cuts")) }
}

/// Reads the cuts a header counts (`counts`: x, z) from the start of `body`.
pub(super) fn read_cuts(body: &[u8], counts: [u16; 2]) -> Result<Cuts, WireError> {
    let (nx, nz) = (counts[0] as usize, counts[1] as usize);
    let all: Vec<f32> = (0..nx + nz).map(|i| f32_at(body, 4 * i)).collect();
    let (xs, zs) = (all[..nx].to_vec(), all[nx..].to_vec());
    check_cuts(&xs)?;
    check_cuts(&zs)?;
    Ok((xs, zs))
}
