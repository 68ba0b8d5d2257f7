// The LBVH of Karras 2012, as crates/physics/src/lbvh: Morton codes of box centres over
// the world bounds, an LSD radix sort of (code, index), parallel emission of the internal
// nodes with the index tie-break for duplicate codes, and a bottom-up refit with one
// atomic arrival counter per node.
#include "common.cuh"

// An internal node holds its two children's boxes (min xyz, max xyz each) and children
// (an internal node index, or a leaf index with LEAF_BIT): 64 bytes, one cache line.
struct __align__(64) Node {
    float b[12];
    u32 child[2];
    u32 pad[2];
};

__device__ __forceinline__ u64 expand_bits(u64 v) {
    u64 x = v & 0x1fffffull;
    x = (x | x << 32) & 0x001f00000000ffffull;
    x = (x | x << 16) & 0x001f0000ff0000ffull;
    x = (x | x << 8) & 0x100f00f00f00f00full;
    x = (x | x << 4) & 0x10c30c30c30c30c3ull;
    x = (x | x << 2) & 0x1249249249249249ull;
    return x;
}

__device__ __forceinline__ u64 morton_q(float v, float min, float scale) {
    return (u64)clampf((v - min) * scale, 0.0f, 2097151.0f);
}

// Object boxes (pos ± half, as Aabb::from_center_half) and the Morton codes of their
// centres, with values 0..n for the sort.
extern "C" __global__ void k_boxes_morton(u32 n, const float* pos, const float* half, float* boxes,
                                          u64* keys, u32* vals, float mx, float my, float mz,
                                          float sx, float sy, float sz) {
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
    V3 c = vscale(vadd(lo, hi), 0.5f);
    keys[i] = expand_bits(morton_q(c.x, mx, sx)) << 2 | expand_bits(morton_q(c.y, my, sy)) << 1 |
              expand_bits(morton_q(c.z, mz, sz));
    vals[i] = i;
}

// Radix sort, 8 bits a pass, one launch a pass ("one-sweep", after Adinets and
// Merrill 2022): the digit counts of every pass are order-independent, so one kernel
// counts them all up front; each pass then ranks its tile and finds the tile's output
// offsets by decoupled look-back over the preceding tiles' published counts, instead of
// a histogram launch and a scan of it. Tiles take their index from an atomic counter, so
// a tile only ever waits on tiles that already run (no deadlock).
#define RADIX_THREADS 256
#define RADIX_ITEMS 8
#define RADIX_TILE (RADIX_THREADS * RADIX_ITEMS)
#define RADIX_PASSES 8
#define FLAG_AGGREGATE (1u << 30)
#define FLAG_PREFIX (2u << 30)
#define COUNT_MASK ((1u << 30) - 1u)

// Digit counts of all 8 passes: hist[pass * 256 + digit] (zeroed by the host).
extern "C" __global__ void k_radix_counts(const u64* keys, u32 n, u32* hist) {
    __shared__ u32 h[RADIX_PASSES][256];
    for (u32 p = 0; p < RADIX_PASSES; p++) h[p][threadIdx.x] = 0;
    __syncthreads();
    for (u32 i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x) {
        u64 key = keys[i];
        for (u32 p = 0; p < RADIX_PASSES; p++) atomicAdd(&h[p][(key >> (8 * p)) & 255], 1u);
    }
    __syncthreads();
    for (u32 p = 0; p < RADIX_PASSES; p++) {
        u32 c = h[p][threadIdx.x];
        if (c) atomicAdd(&hist[p * 256 + threadIdx.x], c);
    }
}

// Exclusive scan of one value a thread over a block of 256 threads.
__device__ __forceinline__ u32 scan256(u32 v) {
    __shared__ u32 warp_sums[RADIX_THREADS / 32];
    u32 lane = threadIdx.x & 31, w = threadIdx.x >> 5;
    u32 x = warp_inclusive_sum(v, lane);
    if (lane == 31) warp_sums[w] = x;
    __syncthreads();
    u32 before = 0;
    for (u32 k = 0; k < w; k++) before += warp_sums[k];
    __syncthreads();
    return before + x - v;
}

// One pass. `status` holds 256 words a tile for this pass and `tile_counter` one word,
// both zeroed by the host before the sort.
extern "C" __global__ void k_radix_pass(const u64* keys_in, const u32* vals_in, u64* keys_out,
                                        u32* vals_out, u32 n, u32 pass, const u32* hist,
                                        u32* status, u32* tile_counter) {
    __shared__ u32 tile_s;
    __shared__ u32 running[256];
    __shared__ u32 wcount[RADIX_THREADS / 32][256];
    u32 t = threadIdx.x, lane = t & 31, warp = t >> 5;
    u32 shift = 8 * pass;
    if (t == 0) tile_s = atomicAdd(tile_counter, 1u);
    running[t] = 0;
    __syncthreads();
    u32 tile = tile_s;
    u32 base = tile * RADIX_TILE;
    // This tile's digit counts.
    for (u32 r = 0; r < RADIX_ITEMS; r++) {
        u32 i = base + r * RADIX_THREADS + t;
        if (i < n) atomicAdd(&running[(keys_in[i] >> shift) & 255], 1u);
    }
    __syncthreads();
    u32 mine = running[t];
    volatile u32* st = status;
    // Publish, then look back: thread t owns digit t.
    st[tile * 256 + t] = (tile == 0 ? FLAG_PREFIX : FLAG_AGGREGATE) | mine;
    __threadfence();
    u32 before = 0;
    if (tile > 0) {
        int k = (int)tile - 1;
        for (;;) {
            u32 v = st[k * 256 + t];
            if ((v & ~COUNT_MASK) == 0) continue; // not published yet: wait
            before += v & COUNT_MASK;
            if ((v & ~COUNT_MASK) == FLAG_PREFIX) break;
            k--;
        }
        st[tile * 256 + t] = FLAG_PREFIX | (before + mine);
    }
    u32 digit_base = scan256(hist[pass * 256 + t]);
    running[t] = digit_base + before;
    __syncthreads();
    u32 lt_mask = (1u << lane) - 1u;
    for (u32 r = 0; r < RADIX_ITEMS; r++) {
        u32 i = base + r * RADIX_THREADS + t;
        bool valid = i < n;
        u64 key = valid ? keys_in[i] : 0ull;
        // Invalid items get a digit no valid item has, so they never share a rank.
        u32 digit = valid ? (u32)((key >> shift) & 255) : 256u + lane;
        for (u32 w = 0; w < RADIX_THREADS / 32; w++) wcount[w][t] = 0;
        __syncthreads();
        u32 peers = __match_any_sync(0xffffffffu, digit);
        u32 rank = __popc(peers & lt_mask);
        if (valid && rank == 0) wcount[warp][digit] = __popc(peers);
        __syncthreads();
        u32 sum = 0;
        for (u32 w = 0; w < RADIX_THREADS / 32; w++) {
            u32 c = wcount[w][t];
            wcount[w][t] = sum;
            sum += c;
        }
        __syncthreads();
        if (valid) {
            u32 at = running[digit] + wcount[warp][digit] + rank;
            keys_out[at] = key;
            vals_out[at] = vals_in[i];
        }
        __syncthreads();
        running[t] += sum;
        __syncthreads();
    }
}

// delta(i, j): common prefix length of the keys of leaves i and j, the leaf indices
// appended to break ties; -1 outside the leaves.
__device__ __forceinline__ int delta(const u64* keys, long long n, long long i, long long j) {
    if (j < 0 || j >= n) return -1;
    u64 a = keys[i], b = keys[j];
    if (a == b) return 64 + __clz((u32)i ^ (u32)j);
    return __clzll(a ^ b);
}

// Karras's construction of internal node i (boxes are filled by the refit).
extern "C" __global__ void k_emit(const u64* keys, u32 n, Node* nodes, u32* node_parent,
                                  u32* leaf_parent) {
    u32 gi = blockIdx.x * blockDim.x + threadIdx.x;
    if (n < 2 || gi >= n - 1) return;
    long long N = n, i = gi;
    long long d = (delta(keys, N, i, i + 1) - delta(keys, N, i, i - 1)) >= 0 ? 1 : -1;
    int dmin = delta(keys, N, i, i - d);
    long long lmax = 2;
    while (delta(keys, N, i, i + lmax * d) > dmin) lmax *= 2;
    long long l = 0;
    for (long long t = lmax / 2; t >= 1; t /= 2)
        if (delta(keys, N, i, i + (l + t) * d) > dmin) l += t;
    long long j = i + l * d;
    int dnode = delta(keys, N, i, j);
    long long s = 0, div = 2;
    for (;;) {
        long long t = (l + div - 1) / div;
        if (delta(keys, N, i, i + (s + t) * d) > dnode) s += t;
        if (t == 1) break;
        div *= 2;
    }
    long long gamma = i + s * d + (d < 0 ? d : 0);
    long long first = i < j ? i : j, last = i < j ? j : i;
    u32 left = first == gamma ? ((u32)gamma | LEAF_BIT) : (u32)gamma;
    u32 right = last == gamma + 1 ? ((u32)(gamma + 1) | LEAF_BIT) : (u32)(gamma + 1);
    nodes[gi].child[0] = left;
    nodes[gi].child[1] = right;
    // Parents are stored with the side the child hangs on (parent << 1 | side), so the
    // refit needs no read of the parent's children to know which box it writes.
    u32 up = gi << 1;
    if (left & LEAF_BIT) leaf_parent[left & ~LEAF_BIT] = up; else node_parent[left] = up;
    if (right & LEAF_BIT) leaf_parent[right & ~LEAF_BIT] = up | 1u; else node_parent[right] = up | 1u;
}

// Bottom-up refit: each leaf walks up; the first child to arrive at a node stops, the
// second (which sees the counter at 1) unions its box with its sibling's, both being
// final. The walk is a chain of dependent memory operations from leaf to root, so each
// level does as few as it can: write one side, fence, count, read the other side.
extern "C" __global__ void k_refit(u32 n, const u32* order, const float* boxes, Node* nodes,
                                   const u32* node_parent, const u32* leaf_parent, u32* arrivals) {
    u32 leaf = blockIdx.x * blockDim.x + threadIdx.x;
    if (n < 2 || leaf >= n) return;
    const float* src = boxes + 6 * (u64)order[leaf];
    float b[6];
    for (int k = 0; k < 6; k++) b[k] = src[k];
    u32 up = leaf_parent[leaf];
    for (;;) {
        u32 node = up >> 1, side = up & 1u;
        volatile float* nb = nodes[node].b;
        for (int k = 0; k < 6; k++) nb[side * 6 + k] = b[k];
        __threadfence();
        if (atomicAdd(&arrivals[node], 1u) == 0) return;
        __threadfence();
        u32 other = (side ^ 1u) * 6;
        for (int k = 0; k < 3; k++) {
            b[k] = fminf(b[k], nb[other + k]);
            b[3 + k] = fmaxf(b[3 + k], nb[other + 3 + k]);
        }
        if (node == 0) return;
        up = node_parent[node];
    }
}

// Calls emit(target) for every target whose box overlaps `q`, except `self`, and whose
// box `keep` accepts; `keep` must accept a node's box whenever it accepts a box inside it
// (it prunes whole subtrees).
template <typename K, typename F>
__device__ __forceinline__ void tree_visit_if(const Node* nodes, const u32* order, u32 nleaves,
                                              const float* tboxes, const float* q, u32 self,
                                              K keep, F emit) {
    if (nleaves == 0) return;
    if (nleaves == 1) {
        u32 t = order[0];
        const float* tb = tboxes + 6 * (u64)t;
        if (t != self && box_overlaps(tb, q) && keep(tb, true)) emit(t);
        return;
    }
    u32 stack[STACK_SIZE];
    u32 top = 1;
    stack[0] = 0;
    while (top > 0) {
        const Node& nd = nodes[stack[--top]];
        for (int side = 0; side < 2; side++) {
            const float* cb = nd.b + 6 * side;
            if (box_overlaps(cb, q)) {
                u32 c = nd.child[side];
                bool leaf = (c & LEAF_BIT) != 0;
                if (!keep(cb, leaf)) continue;
                if (leaf) {
                    u32 t = order[c & ~LEAF_BIT];
                    if (t != self) emit(t);
                } else if (top < STACK_SIZE) {
                    stack[top++] = c;
                }
            }
        }
    }
}

// Calls emit(target) for every target whose box overlaps `q`, except `self`.
template <typename F>
__device__ __forceinline__ void tree_visit(const Node* nodes, const u32* order, u32 nleaves,
                                           const float* tboxes, const float* q, u32 self, F emit) {
    tree_visit_if(nodes, order, nleaves, tboxes, q, self, [](const float*, bool) { return true; }, emit);
}
