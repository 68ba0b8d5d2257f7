//! The replica on the device: each player's [`Replica`](myriad_interest::Replica)
//! (protocol version 3's deltas, priorities and budget) kept in device memory and
//! stepped by one device warp per player (`kernels/replica.cu`), which also packs the
//! records it chose into delta update bodies (`kernels/pack.cuh`); the host frames and
//! seals them.
//!
//! The decisions and the packing are C shared by the device and the host
//! (`kernels/replica.cuh`, `kernels/pack.cuh`): tests compile them for the host and hold
//! them to the Rust replica and `pack_deltas` byte for byte on any machine
//! (`host_tests.rs`); the GPU suite holds the device to the host outbound
//! (`crates/server/tests/device_outbound.rs`).

mod device;
mod homes;
mod layout;

pub use device::{BODY_STRIDE, Choices, DeviceReplicas, FORGET_BUILDS, ReplicaPlayer};
pub use layout::*;

use myriad_interest::{ReplicaReport, ReplicationConfig};

#[cfg(test)]
mod host_tests;

/// The configuration as the kernels read it.
pub fn device_config(c: &ReplicationConfig, max_datagrams: usize) -> RConfig {
    RConfig {
        resend_ticks: c.resend_ticks,
        budget: c.budget_bytes_per_tick,
        near_units: c.near,
        near_bound: c.near_bound_ticks,
        far_bound: c.far_bound_ticks,
        far_units: c.far,
        refresh: c.refresh_ticks,
        max_wait: c.max_wait_ticks,
        max_datagrams: max_datagrams.clamp(1, u32::MAX as usize) as u32,
    }
}

/// Record forms (`R_ABSOLUTE` … in the kernels).
#[cfg(test)]
const ABSOLUTE: u8 = 0;
#[cfg(test)]
const SAME: u8 = 1;
#[cfg(test)]
const DELTA: u8 = 2;
#[cfg(test)]
const PREDICTED: u8 = 3;

/// A record the C replica chose, as the protocol's; `None` for a form or kind no record
/// has.
#[cfg(test)]
fn delta_record(r: &RRecord) -> Option<myriad_protocol::DeltaRecord> {
    use myriad_protocol::{DeltaRecord, QuantPos, RecordState, ShapeKind};
    let d = r.v.map(|a| a as i16);
    let state = match r.form {
        ABSOLUTE => {
            RecordState::Absolute { kind: ShapeKind::from_code(r.kind)?, pos: QuantPos::new(r.v[0], r.v[1], r.v[2]) }
        }
        SAME => RecordState::Same { back: r.back },
        DELTA => RecordState::Delta { back: r.back, d },
        PREDICTED => RecordState::Predicted { back: r.back, prior: r.prior, d },
        _ => return None,
    };
    Some(DeltaRecord { id: r.id, state })
}

/// What the device's choosing counted for one player, as the host replica reports it
/// (packing adds what it packed).
pub fn chose_report(info: &RInfo) -> ReplicaReport {
    ReplicaReport {
        in_view: info.in_view as usize,
        out_of_order: info.out_of_order as usize,
        deferred: info.deferred as usize,
        starving: info.starving as usize,
        ..ReplicaReport::default()
    }
}
