// Interest selection on the device: which objects of each player's AOI list go into its
// updates this tick, by the rule of the host's interest manager (crates/interest), so
// that the host packs exactly the records it would have chosen itself.
//
// One block per player. Its AOI list (slot indices in any order, from k_tree_write or
// k_naive_write; the result does not depend on the order) is read a few times from global memory; the per-candidate values that
// are reused are kept in scratch arrays at the list's own positions:
//
// 1. Candidates: every slot but the player's own object; the id base is the smallest id
//    among them and the own object. A record is compact when its id is within 2^30 of
//    the base and its quantized offset from the player's quantized centre fits an i16.
// 2. If every candidate fits `max_datagrams` datagrams whatever the packing order, they
//    are all selected, by slot, and the player keeps no staleness.
// 3. Otherwise: staleness keys (the tick each candidate was last sent, from the player's
//    table of the previous tick; absent = entered the view now, or `tick - 1` for all
//    when the player kept no table), then the K nearest by (distance², id) and the R
//    stalest of the rest by (key, id), each group sorted by its order, nearest group
//    first. Both orders are total (ids are distinct), so the choice is unique; the host
//    uses the same orders (crates/interest/src/manager.rs).
// 4. The new table holds every candidate's key; k_interest_stamp then sets the key of
//    the records k_interest_pack packed to `tick`.
//
// Determinism: distances are computed as in Rust (no FMA: --fmad=false) and ordered like
// f32::total_cmp; quantization is Rust's `QuantPos::from_f32` (f64, half away from zero,
// saturating conversion, NaN to 0).
#include "common.cuh"
#include "aead.cuh"

#define SEL_THREADS 256
// The most records one selected group may hold (the sort runs in shared memory).
#define SEL_SORT 1024
// Protocol sizes (crates/protocol/src/header.rs and update.rs).
#define MAX_BODY 1166u
// A sealed datagram: the clear header, the body, the tag (crates/protocol/src/header.rs);
// the host's copy holds one every DATAGRAM_STRIDE bytes (`MAX_DATAGRAM`, a multiple of 16).
#define HEADER_LEN 18u
#define TAG_LEN 16u
#define DATAGRAM_STRIDE 1200u
#define PROTOCOL_VERSION 1u
#define STATE_UPDATE_KIND 0x81u
// Datagrams (warps) per block of k_interest_seal.
#define SEAL_WARPS 4
#define UPDATE_HEADER_LEN 32u
#define COMPACT_LEN 10u
#define EXTENDED_LEN 24u
#define ID_WINDOW (1u << 30)
#define NONE 0xffffffffu
// Candidate flags in `cflag`.
#define C_VALID 1u
#define C_EXTENDED 2u

// f32::total_cmp as an unsigned order.
__device__ __forceinline__ u32 total_key(float f) {
    u32 b = __float_as_uint(f);
    return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}

// QuantPos::from_f32 for one component.
__device__ __forceinline__ int quant(float v) {
    double s = (double)v * 64.0;
    return __double2int_rz(__dadd_rn(s, copysign(0.5, s)));
}

__device__ __forceinline__ bool fits_i16(int a, int b) {
    long long d = (long long)a - (long long)b;
    return d >= -32768 && d <= 32767;
}

// Slot of `id` in an open-addressing table of `m` entries (ids stored plus one; 0 is
// empty), or the empty slot where it would go; NONE if the table is empty.
__device__ __forceinline__ u32 table_find(const u64* tid, u32 m, u32 id) {
    if (m == 0) return NONE;
    u64 want = (u64)id + 1;
    u32 h = (u32)((((u64)id * 0x9e3779b97f4a7c15ull) >> 32) % m);
    for (u32 probe = 0; probe < m; probe++) {
        u64 v = tid[h];
        if (v == want || v == 0) return h;
        h = h + 1 == m ? 0 : h + 1;
    }
    return NONE;
}

// The `want`-th smallest (1-based) of `comp` over the eligible candidates, or a value
// that the same candidates, and no others, are at or below; `want` must be at most their
// number. 8-bit radix passes from the highest bit where the eligible values differ, until
// the wanted value's bin holds exactly the values still wanted.
template <typename Comp, typename Elig>
__device__ u64 radix_select(u32 len, u32 want, Comp comp, Elig elig, u32* hist, u64* s_lo, u64* s_hi,
                            u32* s_want) {
    if (threadIdx.x == 0) {
        *s_lo = ~0ull;
        *s_hi = 0;
    }
    __syncthreads();
    for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
        if (!elig(j)) continue;
        u64 c = comp(j);
        atomicMin((unsigned long long*)s_lo, (unsigned long long)c);
        atomicMax((unsigned long long*)s_hi, (unsigned long long)c);
    }
    __syncthreads();
    u64 lo = *s_lo, diff = lo ^ *s_hi;
    __syncthreads();
    if (diff == 0) return lo;
    int top = (63 - __clzll((long long)diff)) / 8 * 8;
    // The bits above `top + 8` are the same in every eligible value.
    u64 mask = top + 8 >= 64 ? 0 : ~((1ull << (top + 8)) - 1);
    u64 prefix = lo & mask;
    for (int shift = top; shift >= 0; shift -= 8) {
        for (u32 d = threadIdx.x; d < 256; d += blockDim.x) hist[d] = 0;
        __syncthreads();
        for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
            if (!elig(j)) continue;
            u64 c = comp(j);
            if ((c & mask) == prefix) atomicAdd(&hist[(c >> shift) & 255], 1u);
        }
        __syncthreads();
        if (threadIdx.x == 0) {
            u32 below = 0, d = 0;
            for (; d < 255; d++) {
                if (below + hist[d] >= want) break;
                below += hist[d];
            }
            u32 rest = want - below;
            u64 p = prefix | ((u64)d << shift);
            // Every value of the bin is wanted: the bin's top ends the search.
            *s_want = rest == hist[d] ? 0 : rest;
            *s_lo = rest == hist[d] ? p | ((1ull << shift) - 1) : p;
        }
        __syncthreads();
        u32 w = *s_want;
        u64 p = *s_lo;
        __syncthreads();
        if (w == 0) return p;
        want = w;
        prefix = p;
        mask |= (u64)255 << shift;
    }
    return prefix;
}

// Sorts `count` (key, slot) pairs ascending by key in shared memory (bitonic; padded to a
// power of two with the largest key).
__device__ void block_sort(u64* key, u32* slot, u32 count) {
    u32 size = 1;
    while (size < count) size <<= 1;
    for (u32 j = count + threadIdx.x; j < size; j += blockDim.x) {
        key[j] = ~0ull;
        slot[j] = NONE;
    }
    __syncthreads();
    for (u32 k = 2; k <= size; k <<= 1) {
        for (u32 s = k >> 1; s > 0; s >>= 1) {
            for (u32 i = threadIdx.x; i < size; i += blockDim.x) {
                u32 p = i ^ s;
                if (p > i) {
                    bool up = (i & k) == 0;
                    if ((key[i] > key[p]) == up) {
                        u64 tk = key[i];
                        key[i] = key[p];
                        key[p] = tk;
                        u32 ts = slot[i];
                        slot[i] = slot[p];
                        slot[p] = ts;
                    }
                }
            }
            __syncthreads();
        }
    }
}

extern "C" __global__ void k_interest_select(
    u32 first, u32 nq, const u32* offsets, u32 parts, const u32* objects, u32 n, const float* pos, const u32* ids,
    const u32* own, const float* centres, const u32* prev_index, const u32* prev_toff,
    const u64* prev_tid, const u64* prev_tkey, const u8* prev_rot, u32* next_toff, u64* next_tid,
    u64* next_tkey, u8* next_rot, u32* cdist, u32* cid, u8* cflag, u64* ckey, u64 tick,
    u32 max_datagrams, u32 near_slots, u32 rotation_slots, u32 cap, u32* meta, u32* sel) {
    __shared__ u32 hist[256];
    __shared__ u64 s_lo, s_hi;
    __shared__ u32 s_want, s_min_id, s_valid, s_ext, s_count;
    __shared__ u64 sort_key[SEL_SORT];
    __shared__ u32 sort_slot[SEL_SORT];

    // Players first..nq (one chunk of the tick's players), one block each.
    u32 i = first + blockIdx.x;
    if (i >= nq) return;
    // Player i's list is `parts` consecutive lists (k_aoi_cells' cells, or one).
    u32 start = offsets[parts * i], len = offsets[parts * (i + 1)] - start;
    const u32* list = objects + start;
    u32* dist = cdist + start;
    u32* cand_id = cid + start;
    u8* flag = cflag + start;
    u64* key = ckey + start;
    if (threadIdx.x == 0) {
        next_toff[i] = start;
        if (i == nq - 1) next_toff[nq] = start + len;
        s_min_id = NONE;
        s_valid = 0;
        s_ext = 0;
        s_count = 0;
    }
    u32 o = own[i];
    bool own_ok = o < n;
    u32 own_id = own_ok ? ids[o] : 0;
    float cx = centres[3 * i], cy = centres[3 * i + 1], cz = centres[3 * i + 2];
    int qx = quant(cx), qy = quant(cy), qz = quant(cz);
    __syncthreads();

    // 1. Candidates and the id base.
    for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
        u32 s = list[j];
        u32 f = 0, id = 0;
        if (s < n) {
            id = ids[s];
            if (!(own_ok && id == own_id)) {
                f = C_VALID;
                float dx = pos[3 * s] - cx, dy = pos[3 * s + 1] - cy, dz = pos[3 * s + 2] - cz;
                dist[j] = total_key(dx * dx + dy * dy + dz * dz);
                atomicMin(&s_min_id, id);
            }
        }
        cand_id[j] = id;
        flag[j] = (u8)f;
    }
    __syncthreads();
    u32 base = own_ok ? min(own_id, s_min_id) : s_min_id;
    for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
        if (!(flag[j] & C_VALID)) continue;
        u32 s = list[j];
        bool compact = cand_id[j] - base < ID_WINDOW && fits_i16(quant(pos[3 * s]), qx) &&
                       fits_i16(quant(pos[3 * s + 1]), qy) && fits_i16(quant(pos[3 * s + 2]), qz);
        if (!compact) {
            flag[j] = (u8)(C_VALID | C_EXTENDED);
            atomicAdd(&s_ext, 1u);
        }
        atomicAdd(&s_valid, 1u);
    }
    __syncthreads();
    u32 valid = s_valid;
    u32 own_size = 0;
    if (own_ok) {
        bool compact = own_id - base < ID_WINDOW && fits_i16(quant(pos[3 * o]), qx) &&
                       fits_i16(quant(pos[3 * o + 1]), qy) && fits_i16(quant(pos[3 * o + 2]), qz);
        own_size = compact ? COMPACT_LEN : EXTENDED_LEN;
    }

    // 2. Does everything fit? (`fits_whatever_order` in crates/interest: exact for compact
    // records, and with extended ones a bound that holds for any packing order.)
    u32 mdg = max_datagrams < 1 ? 1 : max_datagrams;
    u32 area = MAX_BODY - UPDATE_HEADER_LEN - own_size;
    u32 ext = s_ext;
    bool fits = ext == 0 ? (valid + area / COMPACT_LEN - 1) / (area / COMPACT_LEN) <= mdg
                         : (u64)(valid - ext) * COMPACT_LEN + (u64)ext * EXTENDED_LEN <=
                               (u64)mdg * (area - (EXTENDED_LEN - 1));
    if (fits) {
        // Everything, by slot: the host packs a fitting view in its list's order, and the
        // host's lists are sorted by slot (this one, unsorted, is in the walk's order).
        if (threadIdx.x == 0) s_count = 0;
        __syncthreads();
        for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
            if (!(flag[j] & C_VALID)) continue;
            u32 at = atomicAdd(&s_count, 1u);
            if (at < SEL_SORT) {
                sort_key[at] = list[j];
                sort_slot[at] = list[j];
            }
        }
        __syncthreads();
        u32 count = min(min(valid, cap), (u32)SEL_SORT);
        block_sort(sort_key, sort_slot, count);
        for (u32 j = threadIdx.x; j < count; j += blockDim.x) sel[(u64)i * cap + j] = sort_slot[j];
        if (threadIdx.x == 0) {
            meta[4 * i] = count;
            meta[4 * i + 1] = valid;
            meta[4 * i + 2] = 0;
            meta[4 * i + 3] = 0;
            next_rot[i] = 0;
        }
        return;
    }

    // 3. Over budget: staleness keys.
    u32 p = prev_index[i];
    bool had = p != NONE && prev_rot[p];
    u64 fresh = had ? tick : (tick > 0 ? tick - 1 : 0);
    u32 pstart = had ? 2 * prev_toff[p] : 0;
    u32 pm = had ? 2 * prev_toff[p + 1] - pstart : 0;
    for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
        if (!(flag[j] & C_VALID)) continue;
        u64 k = fresh;
        u32 at = table_find(prev_tid + pstart, pm, cand_id[j]);
        if (at != NONE && prev_tid[pstart + at] != 0) k = prev_tkey[pstart + at];
        key[j] = k;
    }
    __syncthreads();

    // The K nearest by (distance², id), then the R stalest of the rest by (key, id). A key
    // is at most `tick`; ages beyond 2^32 - 1 ticks would compare as equal (never reached:
    // the refresh bound is a few ticks).
    auto near_comp = [&](u32 j) { return ((u64)dist[j] << 32) | cand_id[j]; };
    auto valid_j = [&](u32 j) { return (flag[j] & C_VALID) != 0; };
    u32 k = min(near_slots, valid);
    u64 near_max = 0;
    bool near_any = k > 0;
    if (k >= valid) {
        near_max = ~0ull;
    } else if (near_any) {
        near_max = radix_select(len, k, near_comp, valid_j, hist, &s_lo, &s_hi, &s_want);
    }
    auto in_near = [&](u32 j) { return near_any && near_comp(j) <= near_max; };
    auto stale_comp = [&](u32 j) {
        u64 age = tick >= key[j] ? tick - key[j] : 0;
        u32 a = age > 0xffffffffull ? 0xffffffffu : (u32)age;
        return ((u64)(0xffffffffu - a) << 32) | cand_id[j];
    };
    auto stale_elig = [&](u32 j) { return valid_j(j) && !in_near(j); };
    u32 r = min(rotation_slots, valid - k);
    u64 stale_max = 0;
    bool stale_any = r > 0;
    if (r >= valid - k) {
        stale_max = ~0ull;
    } else if (stale_any) {
        stale_max = radix_select(len, r, stale_comp, stale_elig, hist, &s_lo, &s_hi, &s_want);
    }

    // Each group sorted into the selection: nearest first, then stalest.
    for (int group = 0; group < 2; group++) {
        u32 count = group == 0 ? k : r;
        if (count == 0) continue;
        if (threadIdx.x == 0) s_count = 0;
        __syncthreads();
        for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
            bool take = group == 0 ? (valid_j(j) && in_near(j))
                                   : (stale_any && stale_elig(j) && stale_comp(j) <= stale_max);
            if (!take) continue;
            u32 at = atomicAdd(&s_count, 1u);
            if (at < SEL_SORT) {
                sort_key[at] = group == 0 ? near_comp(j) : stale_comp(j);
                sort_slot[at] = list[j];
            }
        }
        __syncthreads();
        block_sort(sort_key, sort_slot, count);
        u32 first = group == 0 ? 0 : k;
        for (u32 j = threadIdx.x; j < count; j += blockDim.x) sel[(u64)i * cap + first + j] = sort_slot[j];
        __syncthreads();
    }

    // 4. The new table: every candidate with its key (k_interest_stamp marks what was sent).
    u32 tstart = 2 * start, m = 2 * len;
    for (u32 j = threadIdx.x; j < len; j += blockDim.x) {
        if (!(flag[j] & C_VALID)) continue;
        u64 want = (u64)cand_id[j] + 1;
        u32 h = (u32)((((u64)cand_id[j] * 0x9e3779b97f4a7c15ull) >> 32) % m);
        for (u32 probe = 0; probe < m; probe++) {
            u64 prev = atomicCAS(&next_tid[tstart + h], 0ull, want);
            if (prev == 0 || prev == want) {
                next_tkey[tstart + h] = key[j];
                break;
            }
            h = h + 1 == m ? 0 : h + 1;
        }
    }
    if (threadIdx.x == 0) {
        meta[4 * i] = k + r;
        meta[4 * i + 1] = valid;
        meta[4 * i + 2] = 1;
        meta[4 * i + 3] = k;
        next_rot[i] = 1;
    }
}

// After the packing: the key of each of the first `packed[i]` selected records becomes
// `tick` in player i's new table (players over budget only).
extern "C" __global__ void k_interest_stamp(u32 first, u32 nq, const u32* meta, const u32* sel, u32 cap,
                                            const u32* packed, const u32* ids, const u32* toff,
                                            const u64* tid, u64* tkey, u64 tick) {
    u32 i = first + blockIdx.x;
    if (i >= nq || meta[4 * i + 2] == 0) return;
    u32 count = min(packed[i], meta[4 * i]);
    u32 tstart = 2 * toff[i], m = 2 * toff[i + 1] - tstart;
    for (u32 j = threadIdx.x; j < count; j += blockDim.x) {
        u32 at = table_find(tid + tstart, m, ids[sel[(u64)i * cap + j]]);
        if (at != NONE && tid[tstart + at] != 0) tkey[tstart + at] = tick;
    }
}

// ---------------------------------------------------------------------------------------
// Packing: the selected records into state update bodies, byte for byte what
// `pack_updates_pinned` (crates/protocol/src/update.rs) makes of them on the host: the
// player's own object first in every datagram, then the selection in order, each
// datagram filled greedily and written against its id base (the smallest id it carries,
// which can turn records extended; `fit` there). k_interest_seal then frames and seals them.

// Warps (players) per block of k_interest_pack.
#define PACK_WARPS 4
// Most datagrams a player (`MAX_PACK_DATAGRAMS` in backend/interest.rs): the selection
// holds at most SEL_SORT records, 113 a datagram.
#define MAX_PACK_DATAGRAMS 9

// A record's length against `base`: compact when its id is within 2^30 above the base
// and its offset from the origin fits an i16 in each axis (`near`).
__device__ __forceinline__ u32 rec_len(u32 id, bool near, u32 base) {
    return near && id >= base && id - base < ID_WINDOW ? COMPACT_LEN : EXTENDED_LEN;
}

__device__ __forceinline__ void put16(u8* p, u32 v) {
    p[0] = (u8)v;
    p[1] = (u8)(v >> 8);
}

__device__ __forceinline__ void put32(u8* p, u32 v) {
    put16(p, v);
    put16(p + 2, v >> 16);
}

__device__ __forceinline__ void put64(u8* p, u64 v) {
    put32(p, (u32)v);
    put32(p + 4, (u32)(v >> 32));
}

// Writes object `s` as a record against `base` and origin `q`; returns its length. The
// shape code is the `ShapeKind` discriminant, which is also the wire's code.
__device__ u32 write_rec(u8* out, u32 s, const float* pos, const u32* ids, const u8* shapes, u32 base,
                         int qx, int qy, int qz) {
    int px = quant(pos[3 * s]), py = quant(pos[3 * s + 1]), pz = quant(pos[3 * s + 2]);
    u32 id = ids[s], kind = shapes[s];
    bool near = fits_i16(px, qx) && fits_i16(py, qy) && fits_i16(pz, qz);
    if (rec_len(id, near, base) == COMPACT_LEN) {
        put32(out, ((id - base) << 2) | kind);
        put16(out + 4, (u32)(px - qx));
        put16(out + 6, (u32)(py - qy));
        put16(out + 8, (u32)(pz - qz));
        return COMPACT_LEN;
    }
    put32(out, 3u | (kind << 2));
    put64(out + 4, (u64)id);
    put32(out + 12, (u32)px);
    put32(out + 16, (u32)py);
    put32(out + 20, (u32)pz);
    return EXTENDED_LEN;
}

// One warp per player of first..nq: packs `min(meta[4 i], cap)` selected slots into at
// most `max_datagrams` bodies at `bodies + (i * max_datagrams + d) * MAX_BODY`, with
// their lengths in `lens` (0 past the last); `info[4 i..]` = (objects in view, over
// budget | own object pinned << 1, records packed, datagrams), `packed[i]` the records
// packed (for the stamp).
extern "C" __global__ void k_interest_pack(
    u32 first, u32 nq, const u32* meta, const u32* sel, u32 cap, u32 n, const float* pos, const u32* ids,
    const u8* shapes, const u32* own, const float* centres, u64 tick, u32 dilation,
    u32 max_datagrams, u8* bodies, u32* lens, u32* info, u32* packed) {
    // Record r of a player: its own object first when pinned, then the selection.
    __shared__ u32 s_id[PACK_WARPS][SEL_SORT + 1];
    __shared__ u8 s_near[PACK_WARPS][SEL_SORT + 1];
    __shared__ u32 s_first[PACK_WARPS][MAX_PACK_DATAGRAMS], s_take[PACK_WARPS][MAX_PACK_DATAGRAMS],
        s_base[PACK_WARPS][MAX_PACK_DATAGRAMS];
    __shared__ u32 s_done[PACK_WARPS], s_dgrams[PACK_WARPS];
    u32 w = threadIdx.x / 32, lane = threadIdx.x % 32;
    u32 i = first + blockIdx.x * PACK_WARPS + w;
    if (i >= nq) return;
    u32 mdg = min(max(max_datagrams, 1u), (u32)MAX_PACK_DATAGRAMS);
    u32 count = min(min(meta[4 * i], cap), (u32)SEL_SORT);
    u32 o = own[i];
    u32 pin = o < n ? 1 : 0;
    float cx = centres[3 * i], cy = centres[3 * i + 1], cz = centres[3 * i + 2];
    int qx = quant(cx), qy = quant(cy), qz = quant(cz);
    const u32* chosen = sel + (u64)i * cap;
    u32* id = s_id[w];
    u8* near = s_near[w];
    for (u32 r = lane; r < pin + count; r += 32) {
        u32 s = r < pin ? o : chosen[r - pin];
        id[r] = ids[s];
        near[r] = fits_i16(quant(pos[3 * s]), qx) && fits_i16(quant(pos[3 * s + 1]), qy) &&
                  fits_i16(quant(pos[3 * s + 2]), qz);
    }
    __syncwarp();

    // Where each datagram starts, what it takes and its base: `pack_updates_pinned` and
    // `fit`, serially (cheap: shared memory, a few hundred records).
    if (lane == 0) {
        const u32 room = MAX_BODY - UPDATE_HEADER_LEN;
        u32 done = 0, d = 0;
        while ((done < count || (pin && d == 0)) && d < mdg) {
            u32 base = id[pin ? 0 : done];
            u32 used = pin ? rec_len(id[0], near[0], base) : 0;
            u32 take = 0;
            for (u32 k = 0; done + k < count; k++) {
                u32 r = pin + done + k;
                if (id[r] < base) {
                    // A smaller id lowers the base: measure again against it.
                    u32 lower = pin ? rec_len(id[0], near[0], id[r]) : 0;
                    for (u32 m = pin + done; m <= r; m++) lower += rec_len(id[m], near[m], id[r]);
                    if (lower > room) break;
                    base = id[r];
                    used = lower;
                } else {
                    u32 len = rec_len(id[r], near[r], base);
                    if (used + len > room) break;
                    used += len;
                }
                take = k + 1;
            }
            s_first[w][d] = done;
            s_take[w][d] = take;
            s_base[w][d] = base;
            done += take;
            d++;
            // Only the own object went in: nothing left (any record fits beside it).
            if (take == 0) break;
        }
        s_done[w] = done;
        s_dgrams[w] = d;
    }
    __syncwarp();

    // The bytes, a warp at a time: each lane one record, offsets by a warp scan.
    u32 dgrams = s_dgrams[w];
    for (u32 d = 0; d < mdg; d++) {
        u32 len = 0;
        if (d < dgrams) {
            u8* body = bodies + ((u64)i * mdg + d) * MAX_BODY;
            u32 base = s_base[w][d], first = pin + s_first[w][d], take = s_take[w][d];
            u32 at = UPDATE_HEADER_LEN;
            if (pin) {
                if (lane == 0) write_rec(body + at, o, pos, ids, shapes, base, qx, qy, qz);
                at += rec_len(id[0], near[0], base);
            }
            for (u32 c = 0; c < take; c += 32) {
                u32 k = c + lane;
                u32 l = k < take ? rec_len(id[first + k], near[first + k], base) : 0;
                u32 incl = l;
                for (u32 off = 1; off < 32; off <<= 1) {
                    u32 v = __shfl_up_sync(0xffffffffu, incl, off);
                    if (lane >= off) incl += v;
                }
                if (k < take) write_rec(body + at + incl - l, chosen[first + k - pin], pos, ids, shapes, base, qx, qy, qz);
                at += __shfl_sync(0xffffffffu, incl, 31);
            }
            if (lane == 0) {
                put64(body, tick);
                put16(body + 8, dilation);
                put32(body + 10, (u32)qx);
                put32(body + 14, (u32)qy);
                put32(body + 18, (u32)qz);
                put64(body + 22, (u64)base);
                put16(body + 30, pin + take);
            }
            len = at;
        }
        if (lane == 0) lens[(u64)i * mdg + d] = len;
    }
    if (lane == 0) {
        info[4 * i] = meta[4 * i + 1];
        info[4 * i + 1] = (meta[4 * i + 2] != 0 ? 1u : 0u) | (pin << 1);
        info[4 * i + 2] = s_done[w];
        info[4 * i + 3] = dgrams;
        packed[i] = s_done[w];
    }
}

// Sealing and the download: datagram `d` of player i (first..nq), for `d` below its
// datagram count, is framed (the clear header: version, StateUpdate, session id, sequence
// number `first sequence + d`), sealed with the player's session key by ChaCha20-Poly1305
// (aead.cuh) and stored at `out + (i * max_datagrams + d) * DATAGRAM_STRIDE`. `out` is
// page-locked host memory mapped into the device's address space, so these stores are
// the transfer, and only the bytes in use cross the bus. `leases[12 i..]`: the session
// key (8 words), the session id and the first sequence number (2 words each, low first);
// a first number of u64 max: no lease, nothing is sealed. A warp a datagram.
extern "C" __global__ void k_interest_seal(u32 first, u32 nq, u32 max_datagrams, const u8* bodies,
                                           const u32* lens, const u32* info, const u32* leases,
                                           u8* out) {
    __shared__ uint4 s_buf[SEAL_WARPS][DATAGRAM_STRIDE / 16];
    u32 w = threadIdx.x / 32, lane = threadIdx.x % 32;
    u64 g = (u64)blockIdx.x * SEAL_WARPS + w;
    u32 i = first + (u32)(g / max_datagrams), d = (u32)(g % max_datagrams);
    // Uniform over the warp: whole warps leave.
    if (i >= nq || d >= min(info[4 * i + 3], max_datagrams)) return;
    const u32* lease = leases + 12ull * i;
    u64 sequence = (u64)lease[10] | ((u64)lease[11] << 32);
    if (sequence == ~0ull) return;
    sequence += d;
    u32 len = min(lens[(u64)i * max_datagrams + d], MAX_BODY);
    u8* buf = (u8*)s_buf[w];
    const u8* body = bodies + ((u64)i * max_datagrams + d) * MAX_BODY;
    for (u32 k = lane; k < len; k += 32) buf[HEADER_LEN + k] = body[k];
    if (lane == 0) {
        buf[0] = PROTOCOL_VERSION;
        buf[1] = STATE_UPDATE_KIND;
        for (u32 k = 0; k < 8; k++) {
            buf[2 + k] = (u8)(lease[8 + k / 4] >> (8 * (k % 4)));
            buf[10 + k] = (u8)(sequence >> (8 * k));
        }
    }
    __syncwarp();
    u32 key[8];
    for (u32 k = 0; k < 8; k++) key[k] = lease[k];
    // The nonce: the direction byte (1, server to client), three zero bytes, the sequence
    // number (crates/protocol/src/aead.rs).
    u32 nonce[3] = {1u, (u32)sequence, (u32)(sequence >> 32)};
    seal_warp(buf, HEADER_LEN, len, key, nonce);
    u32 words = (HEADER_LEN + len + TAG_LEN + 15) / 16;
    uint4* dst = (uint4*)(out + ((u64)i * max_datagrams + d) * DATAGRAM_STRIDE);
    for (u32 k = lane; k < words; k += 32) dst[k] = s_buf[w][k];
}
