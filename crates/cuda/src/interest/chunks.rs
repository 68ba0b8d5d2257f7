//! What a queued tick's chunks give back: each chunk's players' sealed datagrams, in
//! mapped page-locked host memory, readable from any thread once its event is done.

use std::ops::Range;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use cudarc::driver::safe::CudaContext;
use myriad_physics::PhysicsError;
use myriad_protocol::{MAX_BODY, MIN_DATAGRAM};

use super::DATAGRAM_STRIDE;
use crate::device::{Event, Pinned};

/// One player's updates, as packed and sealed on the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Payload<'a> {
    /// Objects in view, own excluded.
    pub in_view: u32,
    /// Whether the view was over budget (the records are then the nearest, then the
    /// stalest).
    pub over_budget: bool,
    /// Whether the player's own object is pinned at the start of every datagram.
    pub pinned: bool,
    /// Records of other objects packed.
    pub packed: u32,
    /// Each datagram's body length (each at most `MAX_BODY`).
    lens: &'a [u32],
    /// The player's datagrams, one every [`DATAGRAM_STRIDE`] bytes.
    bytes: &'a [u8],
}

impl<'a> Payload<'a> {
    /// The sealed datagrams, in order, ready to send.
    pub fn datagrams(&self) -> impl Iterator<Item = &'a [u8]> + use<'a> {
        let bytes = self.bytes;
        self.lens.iter().enumerate().map(move |(d, &len)| {
            let at = d * DATAGRAM_STRIDE;
            &bytes[at..at + MIN_DATAGRAM + len as usize]
        })
    }
}

/// The updates of one chunk of players ([`InterestChunks::wait`]), in pinned host
/// memory; player `i` is the chunk's `i`-th.
#[derive(Debug, Clone, Copy)]
pub struct Payloads<'a> {
    /// Per player: in view, flags (over budget, pinned << 1), packed, datagrams.
    info: &'a [u32],
    /// Per player, `max_datagrams` body lengths.
    lens: &'a [u32],
    /// Per player, `max_datagrams` datagrams of [`DATAGRAM_STRIDE`] bytes.
    bytes: &'a [u8],
    max_datagrams: usize,
}

impl<'a> Payloads<'a> {
    /// Number of players.
    pub fn len(&self) -> usize {
        self.info.len() / 4
    }

    /// Whether there is no player.
    pub fn is_empty(&self) -> bool {
        self.info.is_empty()
    }

    /// Player `i`'s updates; `None` past the end or if the device's counts cannot be
    /// right (a body longer than `MAX_BODY`).
    pub fn get(&self, i: usize) -> Option<Payload<'a>> {
        let m = self.info.get(4 * i..4 * i + 4)?;
        let mdg = self.max_datagrams;
        let datagrams = (m[3] as usize).min(mdg);
        let lens = self.lens.get(i * mdg..i * mdg + datagrams)?;
        let bytes = self.bytes.get(i * mdg * DATAGRAM_STRIDE..(i + 1) * mdg * DATAGRAM_STRIDE)?;
        if lens.iter().any(|&l| l as usize > MAX_BODY) {
            return None;
        }
        Some(Payload { in_view: m[0], over_budget: m[1] & 1 != 0, pinned: m[1] & 2 != 0, packed: m[2], lens, bytes })
    }
}

/// A chunk's state: queued, being waited for, done or failed.
pub(super) const CHUNK_QUEUED: u8 = 0;
const CHUNK_WAITED: u8 = 1;
const CHUNK_DONE: u8 = 2;
const CHUNK_FAILED: u8 = 3;

/// The chunks of a queued tick ([`DeviceInterest::chunks`](super::DeviceInterest::chunks)):
/// any thread may wait for any chunk and read its payloads.
#[derive(Clone, Copy)]
pub struct InterestChunks<'a> {
    pub(super) chunks: &'a [Range<usize>],
    pub(super) done: &'a [Event],
    /// Per chunk: queued, being waited for, done or failed (`CHUNK_*`).
    pub(super) state: &'a [AtomicU8],
    pub(super) info: &'a Pinned,
    pub(super) lens: &'a Pinned,
    pub(super) out: &'a Pinned,
    pub(super) max_datagrams: usize,
    pub(super) ctx: &'a Arc<CudaContext>,
}

impl std::fmt::Debug for InterestChunks<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InterestChunks").field("chunks", &self.chunks).finish_non_exhaustive()
    }
}

impl<'a> InterestChunks<'a> {
    /// Number of chunks.
    pub fn len(&self) -> usize {
        self.chunks.len()
    }

    /// Whether there is no chunk (no player).
    pub fn is_empty(&self) -> bool {
        self.chunks.is_empty()
    }

    /// Chunk `k`'s players (a range of the query's), known before it is done.
    pub fn players(&self, k: usize) -> Option<Range<usize>> {
        self.chunks.get(k).cloned()
    }

    /// Waits for chunk `k`; returns its players and their payloads. Of several threads
    /// waiting for one chunk, one waits in the driver and the others for it.
    pub fn wait(&self, k: usize) -> Result<(Range<usize>, Payloads<'a>), PhysicsError> {
        let (Some(players), Some(done), Some(state)) = (self.chunks.get(k), self.done.get(k), self.state.get(k)) else {
            return Err(PhysicsError::Device { stage: "interest", message: format!("no chunk {k} queued") });
        };
        loop {
            match state.compare_exchange(CHUNK_QUEUED, CHUNK_WAITED, Ordering::Acquire, Ordering::Acquire) {
                Ok(_) => {
                    let waited = self
                        .ctx
                        .bind_to_thread()
                        .map_err(|e| PhysicsError::Device { stage: "bind", message: format!("{e:?}") })
                        .and_then(|()| done.wait());
                    state.store(if waited.is_ok() { CHUNK_DONE } else { CHUNK_FAILED }, Ordering::Release);
                    waited?;
                    break;
                }
                Err(CHUNK_DONE) => break,
                Err(CHUNK_FAILED) => {
                    return Err(PhysicsError::Device { stage: "interest", message: format!("chunk {k} failed") });
                }
                Err(_) => std::hint::spin_loop(),
            }
        }
        let (a, m) = (players.start, players.len());
        let mdg = self.max_datagrams;
        let payloads = Payloads {
            info: self.info.range::<u32>(4 * a, 4 * m),
            lens: self.lens.range::<u32>(a * mdg, m * mdg),
            bytes: self.out.range::<u8>(a * mdg * DATAGRAM_STRIDE, m * mdg * DATAGRAM_STRIDE),
            max_datagrams: mdg,
        };
        Ok((players.clone(), payloads))
    }
}
