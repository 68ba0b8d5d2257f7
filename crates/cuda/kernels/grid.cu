// Area-of-interest queries over a grid of columns. The server's AOI boxes are few (one a
// player) and large (thousands of objects each): walked in the tree a thread a box, ten
// thousand boxes kept a fraction of the device busy for milliseconds. Here the objects
// are counting-sorted into columns of the (x, z) plane by their box's low corner, and a
// warp answers a box: for each row of columns the box can reach, the row's objects are
// one contiguous range, which the 32 lanes test with `box_overlaps` (the tree's exact
// test) and compact in order. The lists hold exactly the tree's objects; their order
// (columns, and within a column the scatter's) is not the canonical one, so
// `k_sort_ranges` sorts each list after, as it did the tree walk's.
//
// Why every overlapping object is found: an object overlaps a box only if its low x lies
// in [box.min.x - W, box.max.x], where W bounds every object's width (the largest, kept
// by `k_grid_keys`), and the same for z; the column of a coordinate is monotonic in it
// (clamped at the grid's edges), so those objects lie in the columns between those of
// the two ends. One more column below each range absorbs the rounding of the
// subtraction.
#include "common.cuh"

// The column of coordinate `v`, clamped to [0, g - 1] (NaN to 0: such a box overlaps
// nothing, so where it is kept does not matter).
__device__ __forceinline__ u32 grid_col(float v, float origin, float inv, u32 g) {
    float f = floorf((v - origin) * inv);
    if (!(f >= 0.0f)) return 0;
    if (f >= (float)(g - 1)) return g - 1;
    return (u32)f;
}

// Each object's column (`keys`), the columns' populations (`cells`, zeroed, `g * g + 1`
// entries) and the widest object's width in x or z (`wmax`, zeroed: float bits, which
// order as unsigned integers for non-negative floats).
extern "C" __global__ void k_grid_keys(u32 n, const float* boxes, float ox, float oz, float inv, u32 g, u32* keys,
                                       u32* cells, u32* wmax) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    u32 width = 0;
    if (i < n) {
        const float* b = boxes + 6 * (u64)i;
        u32 key = grid_col(b[2], oz, inv, g) * g + grid_col(b[0], ox, inv, g);
        keys[i] = key;
        atomicAdd(&cells[key], 1u);
        float w = fmaxf(b[3] - b[0], b[5] - b[2]);
        if (w > 0.0f) width = __float_as_uint(w);
    }
    // One atomic a warp, not one an object on a single word.
    width = __reduce_max_sync(FULL_WARP, width);
    if ((threadIdx.x & 31u) == 0 && width > 0) atomicMax(wmax, width);
}

// Scatters the objects into their columns: `cells` holds each column's first index (the
// exclusive scan of the populations) and ends holding the next column's, so column c's
// objects are at [c == 0 ? 0 : cells[c - 1], cells[c]). Their boxes are copied beside
// their slots, so a warp reads a column's boxes in one stride.
extern "C" __global__ void k_grid_scatter(u32 n, const u32* keys, u32* cells, const float* boxes, float* gboxes,
                                          u32* gslots) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    u32 at = atomicAdd(&cells[keys[i]], 1u);
    const float* b = boxes + 6 * (u64)i;
    float* d = gboxes + 6 * (u64)at;
    for (int k = 0; k < 6; k++) d[k] = b[k];
    gslots[at] = i;
}

// The columns a query box can reach, `[x0, x1] x [z0, z1]`.
struct GridSpan {
    u32 x0, x1, z0, z1;
};

__device__ __forceinline__ GridSpan grid_span(const float* q, float w, float ox, float oz, float inv, u32 g) {
    GridSpan s;
    s.x0 = grid_col(q[0] - w, ox, inv, g);
    s.z0 = grid_col(q[2] - w, oz, inv, g);
    s.x0 -= s.x0 > 0;
    s.z0 -= s.z0 > 0;
    s.x1 = grid_col(q[3], ox, inv, g);
    s.z1 = grid_col(q[5], oz, inv, g);
    return s;
}

// Walks box `q`'s rows with its warp, 32 grid entries at a time: each lane calls
// `emit(j, hit, at)` for its entry `j`, `hit` whether that object overlaps the box and
// `at` its place among the hits so far (in order); returns the count of hits.
template <typename F>
__device__ __forceinline__ u32 grid_visit(const float* q, const u32* cells, const float* gboxes, float w, float ox,
                                          float oz, float inv, u32 g, u32 lane, F emit) {
    GridSpan s = grid_span(q, w, ox, oz, inv, g);
    u32 c = 0;
    for (u32 z = s.z0; z <= s.z1 && s.x0 <= s.x1; z++) {
        u32 first = z * g + s.x0;
        u32 begin = first == 0 ? 0 : cells[first - 1];
        u32 end = cells[z * g + s.x1];
        for (u32 k = begin; k < end; k += 32) {
            u32 j = k + lane;
            bool hit = j < end && box_overlaps(gboxes + 6 * (u64)j, q);
            u32 mask = __ballot_sync(FULL_WARP, hit);
            emit(j, hit, c + lanes_before(mask, lane));
            c += __popc(mask);
        }
    }
    return c;
}

// A warp a query (`qorder` maps warps to queries, as for the tree), in one of two passes.
// Counting (`out` null): `counts[q]` = the objects box q overlaps. Writing: `counts`
// holds the scanned offsets, and the objects' slots go to `out[counts[q] ..]` in the
// grid's order, for the queries whose range ends within `cap`.
extern "C" __global__ void k_grid_pass(u32 nq, const float* qboxes, const u32* qorder, float ox, float oz, float inv,
                                       u32 g, const u32* cells, const float* gboxes, const u32* gslots,
                                       const u32* wmax, u32* counts, u32* out, u32 cap) {
    u32 lane = threadIdx.x & 31u;
    u32 t = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    if (t >= nq) return;
    u32 q = query_index(qorder, t);
    u32 begin = 0, len = 0;
    if (out) {
        begin = counts[q];
        u32 end = counts[q + 1];
        if (end > cap) return;
        len = end - begin;
    }
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = qboxes[6 * (u64)q + k];
    float w = __uint_as_float(*wmax);
    u32 c = grid_visit(b, cells, gboxes, w, ox, oz, inv, g, lane, [&](u32 j, bool hit, u32 at) {
        if (out && hit && at < len) out[begin + at] = gslots[j];
    });
    if (!out && lane == 0) counts[q] = c;
}
