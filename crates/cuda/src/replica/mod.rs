//! The replica on the device: each player's [`Replica`](myriad_interest::Replica)
//! (protocol version 3's deltas, priorities and budget) kept in device memory and
//! stepped by one device warp per player (`kernels/replica.cu`), with the host
//! packing and sealing what the device chose.
//!
//! The decisions are C shared by the device and the host (`kernels/replica.cuh`): one
//! test compiles it for the host and holds it to the Rust replica byte for byte on any
//! machine (`host_tests.rs`); the GPU suite holds the device to the host outbound
//! (`crates/server/tests/device_outbound.rs`).

mod device;
mod layout;

pub use device::{Choices, DeviceReplicas, FORGET_BUILDS, RECORDS_PER_DATAGRAM, ReplicaPlayer};
pub use layout::*;

use myriad_interest::{ReplicaReport, ReplicationConfig};
use myriad_protocol::{DeltaRecord, QuantPos, RecordState, ShapeKind};

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
const ABSOLUTE: u8 = 0;
const SAME: u8 = 1;
const DELTA: u8 = 2;
const PREDICTED: u8 = 3;

/// A record the device chose, as the protocol's; `None` for a form or kind no record
/// has (a device fault, never a choice).
pub fn delta_record(r: &RRecord) -> Option<DeltaRecord> {
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
