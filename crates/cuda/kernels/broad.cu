// Broad phase and AOI queries. Every query (a dynamic object's box, or an AOI box) gets
// the sorted list of targets (dynamic slots or static primitives) whose boxes overlap it,
// in two passes: count, then (after an exclusive scan of the counts gives each query its
// exact range) write and sort the range. No list can overflow and no pair is dropped:
// the host grows the output to the exact total before the write pass.
//
// Canonical order: each query's range is sorted ascending, so static pairs come out by
// (object, primitive) and each object's dynamic neighbours by slot, whatever order the
// tree walk found them in.
#include "common.cuh"

// Moves a[root] down the max-heap a[0..end).
__device__ __forceinline__ void sift_down(u32* a, u32 root, u32 end) {
    u32 v = a[root];
    for (;;) {
        u32 child = 2 * root + 1;
        if (child >= end) break;
        if (child + 1 < end && a[child + 1] > a[child]) child++;
        if (a[child] <= v) break;
        a[root] = a[child];
        root = child;
    }
    a[root] = v;
}

// Sorts one query's targets ascending. The values are distinct slots, so the result is
// the same whatever the algorithm (the CPU's order).
__device__ __forceinline__ void sort_range(u32* a, u32 len) {
    if (len <= 32) {
        // Insertion sort: the contacts of one object are a handful, and this is the
        // fastest for those.
        for (u32 i = 1; i < len; i++) {
            u32 v = a[i];
            u32 j = i;
            while (j > 0 && a[j - 1] > v) {
                a[j] = a[j - 1];
                j--;
            }
            a[j] = v;
        }
        return;
    }
    // Heapsort, O(n log n) in place: an object in a dense crowd overlaps hundreds, where
    // insertion sort's O(n^2) stalls its thread (the AOI lists, thousands of objects,
    // took a whole second a tick that way for 10,000 players; `k_sort_ranges` sorts those).
    for (u32 i = len / 2; i-- > 0;) sift_down(a, i, len);
    for (u32 end = len - 1; end > 0; end--) {
        u32 t = a[0];
        a[0] = a[end];
        a[end] = t;
        sift_down(a, 0, end);
    }
}

// Tree queries. `exclude_self` leaves query q out of its own list (dynamic self-query).
// `qorder` (may be null) maps threads to queries: the step passes the dynamic tree's leaf
// order, so neighbouring threads query neighbouring boxes and walk the same nodes
// (coherent branches and cache lines). `cap` is the output's capacity: writes past it are
// dropped, and the host, which reads the exact total, grows the output and redoes the
// step when that happened.
__device__ __forceinline__ u32 query_index(const u32* qorder, u32 t) {
    return qorder ? qorder[t] : t;
}

// The count pass also keeps the first `slots` targets of each query in `scratch`
// (`slots` a query, may be 0): the write pass copies those instead of walking the tree
// again, and walks it only for the queries with more.
extern "C" __global__ void k_tree_count(u32 nq, const float* qboxes, const u32* qorder,
                                        u32 exclude_self, const Node* nodes, const u32* order,
                                        u32 nleaves, const float* tboxes, u32* counts,
                                        u32* scratch, u32 slots) {
    u32 t = blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= nq) return;
    u32 q = query_index(qorder, t);
    const float* qb = qboxes + 6 * (u64)q;
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = qb[k];
    u32* keep = scratch + (u64)q * slots;
    u32 c = 0;
    tree_visit(nodes, order, nleaves, tboxes, b, exclude_self ? q : NO_SELF, [&](u32 target) {
        if (c < slots) keep[c] = target;
        c++;
    });
    counts[q] = c;
}

extern "C" __global__ void k_tree_write(u32 nq, const float* qboxes, const u32* qorder,
                                        u32 exclude_self, const Node* nodes, const u32* order,
                                        u32 nleaves, const float* tboxes, const u32* offsets,
                                        u32* out, u32 cap, const u32* scratch, u32 slots) {
    u32 t = blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= nq) return;
    u32 q = query_index(qorder, t);
    u32 begin = offsets[q], end = offsets[q + 1];
    if (end > cap) return;
    u32* dst = out + begin;
    u32 len = end - begin;
    if (len <= slots) {
        const u32* keep = scratch + (u64)q * slots;
        for (u32 k = 0; k < len; k++) dst[k] = keep[k];
        sort_range(dst, len);
        return;
    }
    const float* qb = qboxes + 6 * (u64)q;
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = qb[k];
    u32 c = 0;
    tree_visit(nodes, order, nleaves, tboxes, b, exclude_self ? q : NO_SELF, [&](u32 target) {
        if (c < len) dst[c] = target;
        c++;
    });
    sort_range(dst, min(c, len));
}

// Sorts each query's range of `objects` ascending, one block a query, in shared memory
// up to SORT_SHARED slots, longer ones (a crowd of thousands in one box) by
// `NETWORK_SORT` in global memory, the whole block. The AOI queries of the server
// (thousands of boxes of thousands of objects, `grid.cu`) are sorted here: one thread
// sorting each range in global memory left the device waiting on memory for tens of
// milliseconds. In shared memory, ranges of up to SORT_NETWORK_MAX slots take the sorting
// network, longer ones a radix sort: the network pads a range to a power of two (a range
// of 2,500, scenario 3 at AOI 100, is 78 steps of 4 comparisons a thread), and the radix
// sort's passes cost about the same whatever the range (its counts are summed whole), so
// it pays only for the longest (a lent H100, 2026-12-07: 1.02 ms a tick with the network
// alone at scenario 3, AOI 100, 0.76 with the radix sort alone, whose 0.40 at AOI 14
// the network takes a fraction of).
//
// The radix sort: SORT_BITS a pass from the lowest bit to the highest one any slot of the
// range has (5 passes for 260,000 objects). A thread holds its items of each round
// (item `r * SORT_THREADS + t`); a warp ranks its 32 items of a round among equal digits
// (`__match_any_sync`), the counts of each (digit, round, warp) are summed in that order,
// and each item goes to its count's sum plus its rank: every pass is stable, so the
// range ends sorted by the whole slot.
#define SORT_SHARED 4096
#define SORT_NETWORK_MAX 2048
// The launch's block (src/backend/aoi.rs); another block size takes the network.
#define SORT_THREADS 512u
#define SORT_WARPS (SORT_THREADS / 32u)
#define SORT_ROUNDS (SORT_SHARED / SORT_THREADS)
#define SORT_BITS 4u
#define SORT_DIGITS (1u << SORT_BITS)
#define SORT_COUNTS (SORT_DIGITS * SORT_ROUNDS * SORT_WARPS)
#if SORT_COUNTS != 4 * SORT_THREADS
#error "the counts' sum takes four counts a thread"
#endif
__device__ __forceinline__ bool slot_less(const u32* a, const u32* b) { return *a < *b; }
extern "C" __global__ void k_sort_ranges(u32 nq, const u32* offsets, u32* objects) {
    __shared__ u32 s[SORT_SHARED];
    __shared__ u32 counts[SORT_COUNTS];
    __shared__ u32 sums[SORT_WARPS];
    u32 q = blockIdx.x;
    if (q >= nq) return;
    u32 begin = offsets[q], len = offsets[q + 1] - begin;
    if (len <= 1) return;
    u32* a = objects + begin;
    u32 t = threadIdx.x, step = blockDim.x;
    if (len > SORT_SHARED || step != SORT_THREADS) {
        NETWORK_SORT(u32, a, len, slot_less, t, step, __syncthreads());
        return;
    }
    u32 lane = t & 31u, warp = t >> 5;
    // The bits any slot of the range has: the passes needed.
    u32 any = 0;
    for (u32 i = t; i < len; i += SORT_THREADS) {
        u32 v = a[i];
        s[i] = v;
        any |= v;
    }
    if (len <= SORT_NETWORK_MAX) {
        __syncthreads();
        NETWORK_SORT(u32, s, len, slot_less, t, step, __syncthreads());
        for (u32 i = t; i < len; i += SORT_THREADS) a[i] = s[i];
        return;
    }
    any = __reduce_or_sync(FULL_WARP, any);
    if (lane == 0) sums[warp] = any;
    __syncthreads();
    any = 0;
    for (u32 w = 0; w < SORT_WARPS; w++) any |= sums[w];
    u32 bits = 32 - __clz(any);
    u32 rounds = (len + SORT_THREADS - 1) / SORT_THREADS;
    for (u32 shift = 0; shift < bits; shift += SORT_BITS) {
        u32 key[SORT_ROUNDS], rank[SORT_ROUNDS], at[SORT_ROUNDS];
        for (u32 c = t; c < SORT_COUNTS; c += SORT_THREADS) counts[c] = 0;
        __syncthreads();
#pragma unroll
        for (u32 r = 0; r < SORT_ROUNDS; r++) {
            u32 i = r * SORT_THREADS + t;
            bool valid = r < rounds && i < len;
            key[r] = valid ? s[i] : 0;
            // Items past the range get a digit of their own, so they never share a rank.
            u32 d = valid ? (key[r] >> shift) & (SORT_DIGITS - 1) : SORT_DIGITS + lane;
            at[r] = (d * SORT_ROUNDS + r) * SORT_WARPS + warp;
            rank[r] = 0;
            if (r < rounds) {  // the same for the whole block
                u32 peers = __match_any_sync(FULL_WARP, d);
                rank[r] = __popc(peers & ((1u << lane) - 1u));
                if (valid && rank[r] == 0) counts[at[r]] = __popc(peers);
            }
        }
        __syncthreads();
        // Each count becomes the sum of those before it in (digit, round, warp) order.
        u32 c[4], local = 0;
        for (u32 k = 0; k < 4; k++) {
            c[k] = counts[4 * t + k];
            local += c[k];
        }
        u32 incl = warp_inclusive_sum(local, lane);
        if (lane == 31) sums[warp] = incl;
        __syncthreads();
        if (warp == 0) {
            u32 v = lane < SORT_WARPS ? sums[lane] : 0;
            u32 x = warp_inclusive_sum(v, lane);
            if (lane < SORT_WARPS) sums[lane] = x - v;
        }
        __syncthreads();
        u32 before = sums[warp] + incl - local;
        for (u32 k = 0; k < 4; k++) {
            counts[4 * t + k] = before;
            before += c[k];
        }
        __syncthreads();
#pragma unroll
        for (u32 r = 0; r < SORT_ROUNDS; r++) {
            if (r < rounds && r * SORT_THREADS + t < len) s[counts[at[r]] + rank[r]] = key[r];
        }
        __syncthreads();
    }
    for (u32 i = t; i < len; i += SORT_THREADS) a[i] = s[i];
}

// All pairs (cuda-naive): query q tests every target in index order, so its list comes
// out sorted.
extern "C" __global__ void k_naive_count(u32 nq, const float* qboxes, u32 exclude_self, u32 nt,
                                         const float* tboxes, u32* counts) {
    u32 q = blockIdx.x * blockDim.x + threadIdx.x;
    if (q >= nq) return;
    const float* qb = qboxes + 6 * (u64)q;
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = qb[k];
    u32 self = exclude_self ? q : NO_SELF;
    u32 c = 0;
    for (u32 t = 0; t < nt; t++)
        if (t != self && box_overlaps(tboxes + 6 * (u64)t, b)) c++;
    counts[q] = c;
}

extern "C" __global__ void k_naive_write(u32 nq, const float* qboxes, u32 exclude_self, u32 nt,
                                         const float* tboxes, const u32* offsets, u32* out,
                                         u32 cap) {
    u32 q = blockIdx.x * blockDim.x + threadIdx.x;
    if (q >= nq) return;
    const float* qb = qboxes + 6 * (u64)q;
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = qb[k];
    u32 self = exclude_self ? q : NO_SELF;
    u32 begin = offsets[q], end = offsets[q + 1];
    if (end > cap) return;
    u32 len = end - begin, c = 0;
    for (u32 t = 0; t < nt && c < len; t++)
        if (t != self && box_overlaps(tboxes + 6 * (u64)t, b)) out[begin + c++] = t;
}

// Boxes of static primitives (no Morton codes needed by cuda-naive).
extern "C" __global__ void k_boxes(u32 n, const float* pos, const float* half, float* boxes) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    V3 p = load3(pos, i), h = load3(half, i);
    V3 lo = vsub(p, h), hi = vadd(p, h);
    float* b = boxes + 6 * (u64)i;
    b[0] = lo.x;
    b[1] = lo.y;
    b[2] = lo.z;
    b[3] = hi.x;
    b[4] = hi.y;
    b[5] = hi.z;
}
