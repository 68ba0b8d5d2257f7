//! Exclusive prefix sums of `u32` arrays on the device (`kernels/scan.cu`): they turn
//! per-query counts into each query's range in a pair list.

use myriad_physics::PhysicsError;

use crate::device::{DevBuf, Gpu};
use crate::launch::{DevPtr, KScanAdd, KScanBlocks, KScanSums};

/// Threads (and items) per block of the block-parallel scan.
const SCAN_BLOCK: usize = 1024;
/// Up to this length one block scans the whole array in one launch (4 items a thread),
/// saving two launches. Not more: each thread reads its items one after the other, and at
/// 32 items a thread (the 32k-entry radix histogram of 260k keys) this one launch took
/// 52 us on an H200 where the three launches of the block-parallel scan took 12.6 us.
const SCAN_ONE_BLOCK: usize = 4 * 1024;

/// Exclusive scans of u32 arrays on the device.
pub(super) struct Scan {
    /// Each block's total, for the block-parallel scan.
    pub sums: DevBuf<u32>,
}

impl Scan {
    /// Replaces `data[0..len]` by its exclusive prefix sum.
    pub fn exclusive(&mut self, gpu: &Gpu, data: DevPtr<u32>, len: usize) -> Result<(), PhysicsError> {
        if len == 0 {
            return Ok(());
        }
        if len <= SCAN_ONE_BLOCK {
            return gpu.launch_grid(1, SCAN_BLOCK as u32, KScanSums { sums: data, len: len as u32 });
        }
        let blocks = len.div_ceil(SCAN_BLOCK);
        self.sums.ensure(gpu, blocks * 4, 1.5)?;
        let sums = self.sums.ptr();
        gpu.launch_grid(blocks as u32, SCAN_BLOCK as u32, KScanBlocks { data, len: len as u32, block_sums: sums })?;
        gpu.launch_grid(1, SCAN_BLOCK as u32, KScanSums { sums, len: blocks as u32 })?;
        gpu.launch_grid(blocks as u32, SCAN_BLOCK as u32, KScanAdd { data, len: len as u32, sums })
    }
}
