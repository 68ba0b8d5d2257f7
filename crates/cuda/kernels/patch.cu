// The incremental upload of a zone's world (crates/cuda/src/backend/patch.rs): instead of
// copying every object to the device each tick, the device moves the objects it already
// holds to their new slots (gather) and the host sends only the states it wrote (scatter).
//
// The nine per-object arrays are pos, prev, half (3 floats an object), radius (float),
// shape, kind (one byte), id (u32), action, flags (one byte). Both kernels copy bits and
// do no arithmetic on the values, so the result is exactly what a full upload gives. The
// last kernel reads some positions back, copying bits too.
#include "common.cuh"

// One thread per new slot `i < n`: the run covering `i` (runs of 3 words: to, from, len,
// ascending by `to`, non-overlapping; found by binary search) names the old slot that
// held the object, copied from the current arrays into the `out_` arrays. A slot no run
// covers holds a new object: it is left for k_patch_scatter. The host checked every run
// against both lengths, so `from + (i - to)` is an old slot.
extern "C" __global__ void k_patch_gather(u32 n, const u32* runs, u32 nruns, const float* pos,
                                          const float* prev, const float* half,
                                          const float* radius, const u8* shape, const u8* kind,
                                          const u32* id, const u8* action, const u8* flags,
                                          float* out_pos, float* out_prev, float* out_half,
                                          float* out_radius, u8* out_shape, u8* out_kind,
                                          u32* out_id, u8* out_action, u8* out_flags) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    // The first run starting after `i`, in [lo, hi).
    u32 lo = 0, hi = nruns;
    while (lo < hi) {
        u32 mid = lo + (hi - lo) / 2;
        if (runs[3 * mid] <= i) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    if (lo == 0) return;
    u32 r = lo - 1;
    u32 to = runs[3 * r], from = runs[3 * r + 1], len = runs[3 * r + 2];
    if (i - to >= len) return;
    u32 j = from + (i - to);
    store3(out_pos, i, load3(pos, j));
    store3(out_prev, i, load3(prev, j));
    store3(out_half, i, load3(half, j));
    out_radius[i] = radius[j];
    out_shape[i] = shape[j];
    out_kind[i] = kind[j];
    out_id[i] = id[j];
    out_action[i] = action[j];
    out_flags[i] = flags[j];
}

// One thread per written state `k < w`, from the staged words (layout of
// `patch::pack_written`): slots [0, w), pos [w, 4w), prev [4w, 7w), half [7w, 10w),
// radius bits [10w, 11w), id [11w, 12w), then one word of bytes a state
// (shape | kind << 8 | action << 16 | flags << 24) in [12w, 13w). A slot at or past `n`
// (never sent: the host checks) is skipped rather than written out of bounds.
extern "C" __global__ void k_patch_scatter(u32 w, const u32* staged, u32 n, float* pos, float* prev,
                                           float* half, float* radius, u8* shape, u8* kind,
                                           u32* id, u8* action, u8* flags) {
    u32 k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= w) return;
    u32 s = staged[k];
    if (s >= n) return;
    const u32* v = staged + w;
    for (u32 c = 0; c < 3; c++) {
        pos[3 * s + c] = __uint_as_float(v[3 * k + c]);
        prev[3 * s + c] = __uint_as_float(v[3 * w + 3 * k + c]);
        half[3 * s + c] = __uint_as_float(v[6 * w + 3 * k + c]);
    }
    radius[s] = __uint_as_float(v[9 * w + k]);
    id[s] = v[10 * w + k];
    u32 bytes = v[11 * w + k];
    shape[s] = (u8)(bytes & 0xffu);
    kind[s] = (u8)((bytes >> 8) & 0xffu);
    action[s] = (u8)((bytes >> 16) & 0xffu);
    flags[s] = (u8)(bytes >> 24);
}

// One thread per asked slot `i < m`: the position of object `slots[i]` into `out` (three
// floats a slot). The host's read of a few positions (a GPU server's players, every tick)
// while the step left every position on the device (crates/cuda/src/backend/held.rs); the
// host checked each slot against the number of objects.
extern "C" __global__ void k_gather_positions(u32 m, const u32* slots, const float* pos, float* out) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= m) return;
    store3(out, i, load3(pos, slots[i]));
}
