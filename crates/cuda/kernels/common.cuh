// Shared definitions of the Myriad kernels: the parameter block, small vector helpers,
// counter-based random numbers and the terrain sampler.
//
// Determinism: everything here mirrors the Rust code operation for operation. The
// program is compiled with --fmad=false -prec-div=true -prec-sqrt=true, so `a * b + c` is
// two rounded operations as in Rust, and division and square root are IEEE.
#pragma once

typedef unsigned int u32;
typedef unsigned long long u64;
typedef unsigned char u8;

#define LEAF_BIT 0x80000000u
#define NO_SELF 0xffffffffu
// The LBVH depth is at most 97 (delta grows strictly down the tree, <= 64 + 32 bits) and
// each level leaves at most one sibling on the stack.
#define STACK_SIZE 128
#define FULL_WARP 0xffffffffu

// Lanes below this one set in `mask`: where this lane's item goes in a list a warp
// compacts in order.
__device__ __forceinline__ u32 lanes_before(u32 mask, u32 lane) { return __popc(mask & ((1u << lane) - 1u)); }

// The sum of `v` over this lane and the lanes below it (every lane of the warp calls it).
__device__ __forceinline__ u32 warp_inclusive_sum(u32 v, u32 lane) {
    for (u32 d = 1; d < 32; d <<= 1) {
        u32 o = __shfl_up_sync(FULL_WARP, v, d);
        if (lane >= d) v += o;
    }
    return v;
}

// Per-tick constants, world bounds and terrain sampling constants. Mirrors
// `DeviceParams` in crates/cuda/src/params.rs field for field (all 4 bytes wide).
struct Params {
    float gravity_dt2, air_keep, ground_keep, move_accel, jump_velocity, one_plus_e,
        ground_tolerance, support_min_y;
    u32 npc_period;
    float bmin[3], bmax[3];
    u32 t_width, t_depth;
    float origin_x, origin_z, inv_cell_x, inv_cell_z, height_scale, base_y;
};

struct V3 {
    float x, y, z;
};
__device__ __forceinline__ V3 v3(float x, float y, float z) {
    V3 r;
    r.x = x;
    r.y = y;
    r.z = z;
    return r;
}
__device__ __forceinline__ V3 vsub(V3 a, V3 b) { return v3(a.x - b.x, a.y - b.y, a.z - b.z); }
__device__ __forceinline__ V3 vadd(V3 a, V3 b) { return v3(a.x + b.x, a.y + b.y, a.z + b.z); }
__device__ __forceinline__ V3 vscale(V3 a, float s) { return v3(a.x * s, a.y * s, a.z * s); }
__device__ __forceinline__ V3 vneg(V3 a) { return v3(-a.x, -a.y, -a.z); }
// (a.x * b.x + a.y * b.y) + a.z * b.z, the order of `narrow::dot`.
__device__ __forceinline__ float vdot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
__device__ __forceinline__ V3 load3(const float* p, u32 i) {
    return v3(p[3 * i], p[3 * i + 1], p[3 * i + 2]);
}
__device__ __forceinline__ void store3(float* p, u32 i, V3 v) {
    p[3 * i] = v.x;
    p[3 * i + 1] = v.y;
    p[3 * i + 2] = v.z;
}

// The `p`-th comparison of a bitonic network's step (`k`, `j`): items `*lo < *hi`. The
// first step of each merge compares mirrored pairs, so every comparison moves the smaller
// item to the lower index, and items past a count `n` never take part: sorting `n` items
// needs no padding (checked against a sort for every n up to 70 before its first GPU run).
__device__ __forceinline__ void bitonic_pair(u32 p, u32 k, u32 j, u32* lo, u32* hi) {
    *lo = ((p & ~(j - 1)) << 1) | (p & (j - 1));
    *hi = j == (k >> 1) ? *lo ^ (k - 1) : *lo | j;
}

// Sorts `a[0 .. n)` ascending by `LESS`, in place, by `bitonic_pair`'s network: the
// thread numbered `first` of `stride` makes every `stride`-th comparison of a step, and
// `SYNC` ends each step. Every thread calls it with the same `n`; it ends synchronised.
#define NETWORK_SORT(T, a, n, LESS, first, stride, SYNC)                                                \
    do {                                                                                                \
        u32 n_ = (n), size_ = 1;                                                                        \
        while (size_ < n_) size_ <<= 1;                                                                 \
        for (u32 k_ = 2; k_ <= size_; k_ <<= 1) {                                                       \
            for (u32 j_ = k_ >> 1; j_ > 0; j_ >>= 1) {                                                  \
                for (u32 p_ = (first); p_ < size_ / 2; p_ += (stride)) {                                \
                    u32 lo_, hi_;                                                                       \
                    bitonic_pair(p_, k_, j_, &lo_, &hi_);                                               \
                    if (hi_ < n_ && LESS(&(a)[hi_], &(a)[lo_])) {                                       \
                        T t_ = (a)[lo_];                                                                \
                        (a)[lo_] = (a)[hi_];                                                            \
                        (a)[hi_] = t_;                                                                  \
                    }                                                                                   \
                }                                                                                       \
                SYNC;                                                                                   \
            }                                                                                           \
        }                                                                                               \
    } while (0)

// Boxes are six floats: min xyz, max xyz (the layout of `myriad_core::Aabb`).
__device__ __forceinline__ bool box_overlaps(const float* a, const float* b) {
    return (a[0] <= b[3]) & (b[0] <= a[3]) & (a[1] <= b[4]) & (b[1] <= a[4]) & (a[2] <= b[5]) &
           (b[2] <= a[5]);
}

// SplitMix64's finaliser and hash3, as in crates/core/src/rng.rs.
__device__ __forceinline__ u64 mix64(u64 z) {
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}
__device__ __forceinline__ u64 hash3(u64 seed, u64 a, u64 b) {
    return mix64(mix64(mix64(seed ^ 0x9e3779b97f4a7c15ull) ^ a) ^ b);
}

// Rust's f32::clamp: two comparisons, in this order.
__device__ __forceinline__ float clampf(float v, float lo, float hi) {
    if (v < lo) v = lo;
    if (v > hi) v = hi;
    return v;
}

// Terrain::height_at, operation for operation (hand-written bilinear filtering: the
// texture unit's 8-bit weights would not match the CPU).
__device__ __forceinline__ float height_at(const Params& p, const unsigned short* samples, float x,
                                           float z) {
    float max_i = (float)(p.t_width - 1);
    float max_j = (float)(p.t_depth - 1);
    float fx = clampf((x - p.origin_x) * p.inv_cell_x, 0.0f, max_i);
    float fz = clampf((z - p.origin_z) * p.inv_cell_z, 0.0f, max_j);
    u32 i = min((u32)fx, p.t_width - 2);
    u32 j = min((u32)fz, p.t_depth - 2);
    float tx = fx - (float)i;
    float tz = fz - (float)j;
    u64 w = p.t_width;
    u64 k = (u64)j * w + i;
    float h00 = (float)samples[k];
    float h10 = (float)samples[k + 1];
    float h01 = (float)samples[k + w];
    float h11 = (float)samples[k + w + 1];
    float a = h00 + (h10 - h00) * tx;
    float b = h01 + (h11 - h01) * tx;
    float h = a + (b - a) * tz;
    return p.base_y + h * p.height_scale;
}
