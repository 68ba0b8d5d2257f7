// Exclusive prefix sums of u32 arrays: a block-level pass (1024 elements a block), a
// one-block pass over the block sums, and a pass adding each block's prefix back.
// Integer sums are exact, so the order of additions does not matter.
#include "common.cuh"

#define SCAN_BLOCK 1024

// Exclusive scan of `v` over a block of exactly 1024 threads; `*total` gets the sum.
__device__ __forceinline__ u32 block_exclusive_scan(u32 v, u32* total) {
    __shared__ u32 warp_sums[32];
    u32 lane = threadIdx.x & 31, w = threadIdx.x >> 5;
    u32 x = warp_inclusive_sum(v, lane);
    if (lane == 31) warp_sums[w] = x;
    __syncthreads();
    if (w == 0) {
        warp_sums[lane] = warp_inclusive_sum(warp_sums[lane], lane);
    }
    __syncthreads();
    u32 incl = x + (w > 0 ? warp_sums[w - 1] : 0u);
    *total = warp_sums[31];
    __syncthreads();
    return incl - v;
}

extern "C" __global__ void k_scan_blocks(u32* data, u32 len, u32* block_sums) {
    u32 i = blockIdx.x * SCAN_BLOCK + threadIdx.x;
    u32 v = i < len ? data[i] : 0u;
    u32 total;
    u32 ex = block_exclusive_scan(v, &total);
    if (i < len) data[i] = ex;
    if (threadIdx.x == 0) block_sums[blockIdx.x] = total;
}

// One block of 1024 threads scans `len` values, each thread a contiguous chunk: used
// for the block sums, and directly for short arrays (one launch instead of three).
extern "C" __global__ void k_scan_sums(u32* sums, u32 len) {
    u32 chunk = (len + SCAN_BLOCK - 1) / SCAN_BLOCK;
    u32 begin = min(threadIdx.x * chunk, len), end = min(begin + chunk, len);
    u32 s = 0;
    for (u32 i = begin; i < end; i++) s += sums[i];
    u32 total;
    u32 run = block_exclusive_scan(s, &total);
    for (u32 i = begin; i < end; i++) {
        u32 v = sums[i];
        sums[i] = run;
        run += v;
    }
}

extern "C" __global__ void k_scan_add(u32* data, u32 len, const u32* sums) {
    u32 i = blockIdx.x * SCAN_BLOCK + threadIdx.x;
    if (i < len) data[i] += sums[blockIdx.x];
}
