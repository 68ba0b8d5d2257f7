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

// Sorts each query's range of `objects` ascending, one block a query: `NETWORK_SORT` in
// shared memory for ranges of up to SORT_SHARED slots, in global memory (the same
// network, the whole block) for longer ones (a crowd of thousands in one box). The AOI
// queries of the server (thousands of boxes of thousands of objects, `grid.cu`) are
// sorted here: one thread sorting each range in global memory left the device waiting
// on memory for tens of milliseconds.
#define SORT_SHARED 4096
__device__ __forceinline__ bool slot_less(const u32* a, const u32* b) { return *a < *b; }
extern "C" __global__ void k_sort_ranges(u32 nq, const u32* offsets, u32* objects) {
    __shared__ u32 s[SORT_SHARED];
    u32 q = blockIdx.x;
    if (q >= nq) return;
    u32 begin = offsets[q], len = offsets[q + 1] - begin;
    if (len <= 1) return;
    u32* a = objects + begin;
    u32 t = threadIdx.x, step = blockDim.x;
    if (len > SORT_SHARED) {
        NETWORK_SORT(u32, a, len, slot_less, t, step, __syncthreads());
        return;
    }
    for (u32 i = t; i < len; i += step) s[i] = a[i];
    __syncthreads();
    NETWORK_SORT(u32, s, len, slot_less, t, step, __syncthreads());
    for (u32 i = t; i < len; i += step) a[i] = s[i];
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
