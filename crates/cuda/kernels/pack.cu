// Step 4 of a replica build on the device (kernels/replica.cu has the rest): a warp a
// player packs its chosen records and own one into delta update bodies, byte for byte
// what pack.cuh's `r_pack` (`pack_deltas`' rules, the host C's packer) writes, and
// stores them straight into mapped host memory.
//
// `r_pack` is a thread's walk over the records, one after the other: with a thread a
// player, 5,000 players kept about one warp busy on each multiprocessor, each thread
// walking hundreds of records. Here the 32 lanes share every pass:
// - the stream parameters: the histograms of backs and of gap lengths in the warp's
//   shared memory, the most frequent back and the cheapest Exp-Golomb order chosen by a
//   reduction with `r_params`' ties (the smallest of equals);
// - the greedy split into datagrams: 32 records' bits at a time, an inclusive sum, and the
//   first record that does not fit (or that no datagram carries) ends the datagram;
// - the bit stream: each lane writes its record alone with pack.cuh's writer (the same
//   function the host C uses, so the bits cannot differ), the sum of the records' lengths
//   before it places them, and the lanes OR their bits into the body in shared memory.
// Nothing is left over for the host to copy but the bodies' bytes.
#include "common.cuh"
#include "replica.cuh"
#include "pack.cuh"

// Warps (players) a block of `k_replica_pack` (PACK_WARPS in src/replica/device.rs).
#define PACK_WARPS 4u
// A body's 64-bit words in shared memory.
#define PACK_WORDS (R_BODY_STRIDE / 8u)
// The stream starts at the body's byte R_STREAM_AT: bit 192.
#define PACK_STREAM_BIT (R_STREAM_AT * 8u)
// Words of one record's bits: at most an Exp-Golomb gap of 129 bits and an absolute far
// record of 101, with the word the writer still holds.
#define PACK_RECORD_WORDS 5u

__device__ __forceinline__ u32 warp_max(u32 v) {
    for (u32 d = 16; d > 0; d >>= 1) v = max(v, __shfl_xor_sync(FULL_WARP, v, d));
    return v;
}

// The smallest `(cost, k)` of the warp, by cost and then by k; returns k.
__device__ __forceinline__ u32 warp_argmin(u64 cost, u32 k) {
    for (u32 d = 16; d > 0; d >>= 1) {
        u64 oc = __shfl_xor_sync(FULL_WARP, cost, d);
        u32 ok = __shfl_xor_sync(FULL_WARP, k, d);
        if (oc < cost || (oc == cost && ok < k)) {
            cost = oc;
            k = ok;
        }
    }
    return k;
}

// The first of `n` records at or after `from` whose id is at least (`above` 0) or above
// (`above` 1) `id`; `n` if none.
__device__ u32 r_first_id(const RChosen* ch, u32 from, u32 n, u64 id, int above, u32 lane) {
    for (u32 base = from; base < n; base += 32) {
        u32 j = base + lane;
        int hit = j < n && (above ? ch[j].rec.id > id : ch[j].rec.id >= id);
        u32 m = __ballot_sync(FULL_WARP, hit);
        if (m) return base + __ffs(m) - 1;
    }
    return n;
}

// `r_params` by the warp over the `n` records with `pinned` at `split`; `hist` is the
// warp's 129 words of shared memory (backs 0..63, then gap lengths 0..64).
__device__ RParams r_params_warp(const RChosen* ch, u32 n, const RRecord* pinned, u32 split, u32* hist, u32 lane) {
    for (u32 b = lane; b < 129; b += 32) hist[b] = 0;
    __syncwarp();
    u32 total = n + (pinned ? 1u : 0u);
    for (u32 j = lane; j < total; j += 32) {
        const RRecord* r = r_packed_at(ch, pinned, split, j);
        u64 previous = j > 0 ? r_packed_at(ch, pinned, split, j - 1)->id : 0;
        u64 g = r_gap(j > 0, previous, r->id);
        atomicAdd(&hist[64 + 64 - r_clz64(g)], 1u);
        if (r->form != R_ABSOLUTE) atomicAdd(&hist[r->back & 63], 1u);
    }
    __syncwarp();
    RParams p;
    // The most frequent back of 1..63, the smallest of equals (none counted: 0): the
    // largest (count, 63 - back).
    u32 best = 0;
    for (u32 b = lane; b < 64; b += 32) {
        if (b >= 1 && hist[b] > 0) best = max(best, hist[b] << 6 | (63u - b));
    }
    best = warp_max(best);
    p.usual = best == 0 ? 0u : 63u - (best & 63u);
    // The longest gap length counted (0 if none but 0).
    u32 longest = 0;
    for (u32 len = lane; len < 65; len += 32) {
        if (hist[64 + len] > 0) longest = max(longest, len);
    }
    longest = warp_max(longest);
    // The cheapest order k of 0..min(longest, 63), the smallest of equals.
    u32 top = longest < 63 ? longest : 63;
    u64 least = ~0ull;
    u32 least_k = 0;
    for (u32 k = lane; k <= top; k += 32) {
        u64 cost = 0;
        for (u32 len = 0; len <= longest; len++) {
            u32 count = hist[64 + len];
            if (count == 0) continue;
            u64 g = len == 0 ? 0 : 1ull << (len - 1);
            cost += (u64)count * r_eg_bits(g, k);
        }
        if (cost < least) {
            least = cost;
            least_k = k;
        }
    }
    p.k = warp_argmin(least, least_k);
    __syncwarp();
    return p;
}

// The end of the datagram that starts at `from`: `r_pack`'s greedy split (records while
// they fit in `room` bits; one no datagram carries ends it too).
__device__ u32 r_split_warp(const RChosen* ch, u32 from, u32 n, RParams p, RPos origin, u32 room, u32 lane) {
    u32 used = 0;
    for (u32 base = from; base < n; base += 32) {
        u32 j = base + lane;
        u32 bits = 0;
        if (j < n) bits = r_stream_bits(&ch[j].rec, j > from, j > from ? ch[j - 1].rec.id : 0, p, origin);
        u32 incl = warp_inclusive_sum(bits, lane);
        u32 stop = __ballot_sync(FULL_WARP, j < n && (bits == 0 || used + incl > room));
        if (stop) return base + __ffs(stop) - 1;
        used += __shfl_sync(FULL_WARP, incl, 31);
    }
    return n;
}

// One record's bits, as `r_put_record` writes them from bit 0, into `words` (zeroed);
// returns how many.
__device__ u32 r_record_words(const RRecord* r, int has_previous, u64 previous, RParams p, RPos origin,
                              u64* words) {
    RBits w = {(u8*)words, 0, 0, 0};
    r_put_record(&w, r, has_previous, previous, p, origin);
    words[w.flushed / 8] = w.word;  // the held bits (the word has no others)
    return w.flushed * 8 + w.held;
}

// ORs `bits` bits of `words` into `body` from bit `at`.
__device__ void r_or_bits(u64* body, u32 at, const u64* words, u32 bits) {
    u32 w = at >> 6, shift = at & 63u;
    for (u32 q = 0; q * 64 < bits; q++) {
        u64 v = words[q];
        if (w + q < PACK_WORDS) atomicOr(&body[w + q], v << shift);
        if (shift && w + q + 1 < PACK_WORDS && (v >> (64 - shift)) != 0) atomicOr(&body[w + q + 1], v >> (64 - shift));
    }
}

// Writes the datagram of records `[from, end)` and the pinned one (placed before the
// first record whose id is above its own) into `body` (zeroed, in shared memory) from
// the stream's parameters on; returns the stream's bits and adds the records relative to
// a baseline (the pinned one not counted) to `relative`.
__device__ u32 r_write_warp(const RChosen* ch, u32 from, u32 end, const RRecord* pinned, RParams p, RPos origin,
                            u64* body, u32* relative, u32 lane) {
    if (lane == 0) body[PACK_STREAM_BIT / 64] = (u64)(p.usual & 63u) | (u64)(p.k & 63u) << 6;
    __syncwarp();
    u32 place = pinned ? r_first_id(ch, from, end, pinned->id, 1, lane) - from : 0;
    u32 records = end - from, total = records + (pinned ? 1u : 0u);
    u32 bit = 12;
    for (u32 base = 0; base < total; base += 32) {
        u32 m = base + lane;
        u64 words[PACK_RECORD_WORDS] = {0, 0, 0, 0, 0};
        u32 bits = 0;
        int counted = 0;
        if (m < total) {
            const RRecord* r = r_packed_at(ch + from, pinned, place, m);
            u64 previous = m > 0 ? r_packed_at(ch + from, pinned, place, m - 1)->id : 0;
            bits = r_record_words(r, m > 0, previous, p, origin, words);
            counted = r != pinned && r->form != R_ABSOLUTE;
        }
        u32 incl = warp_inclusive_sum(bits, lane);
        if (m < total) r_or_bits(body, PACK_STREAM_BIT + bit + incl - bits, words, bits);
        *relative += __popc(__ballot_sync(FULL_WARP, counted));
        bit += __shfl_sync(FULL_WARP, incl, 31);
    }
    __syncwarp();
    return bit;
}

// Step 4 of a build, a warp a player: its chosen records and own one packed into delta
// update bodies (`r_pack`'s, above), each assembled in shared memory and stored into
// mapped host memory (`out`, 16 bytes a lane), with its length (`out_lens`) and what
// packing did (`packed`), which the host frames and seals; `ends` (where each datagram's
// records end) stays on the device for `k_replica_commit`.
extern "C" __global__ void k_replica_pack(u32 nq, const RConfig* cfg, u64 tick, u32 dilation, const u32* offsets,
                                          const RPlayer* players, const u32* counts, const RInfo* infos,
                                          const RChosen* chosen, u32* ends, RPacked* packed, u8* out,
                                          u32* out_lens) {
    __shared__ __align__(16) u64 bodies[PACK_WARPS][PACK_WORDS];
    __shared__ u32 hists[PACK_WARPS][129];
    u32 lane = threadIdx.x & 31u, warp = (threadIdx.x >> 5) % PACK_WARPS;
    u32 i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    if (i >= nq || counts[2 * i + 1] == R_NO_SLOT) return;
    u64* body = bodies[warp];
    const RInfo* in = &infos[i];
    const RPlayer* pl = &players[i];
    const RRecord* pinned = in->has_own_record ? &in->own_record : 0;
    const RChosen* ch = chosen + offsets[i];
    u32 n = in->count, mdg = cfg->max_datagrams;
    u32 most = in->datagrams < mdg ? in->datagrams : mdg;
    u64 at = (u64)i * mdg;
    RPos origin = {r_quant(pl->centre[0]), r_quant(pl->centre[1]), r_quant(pl->centre[2])};

    RPacked done = {0, 0, 0, 0};
    u32 split = pinned ? r_first_id(ch, 0, n, pinned->id, 0, lane) : 0;
    RParams p = r_params_warp(ch, n, pinned, split, hists[warp], lane);
    if (pinned && pinned->form != R_ABSOLUTE) done.relative = 1;
    u32 pinned_bits = pinned ? r_stream_bits(pinned, 0, 0, p, origin) : 0;
    if (!pinned || pinned_bits != 0) {
        u32 room = (R_MAX_BODY - R_DELTA_HEADER_LEN) * 8u - R_STREAM_PARAMS_BITS - pinned_bits;
        u32 from = 0, datagrams = 0;
        while ((from < n || (pinned && datagrams == 0)) && datagrams < most) {
            u32 end = r_split_warp(ch, from, n, p, origin, room, lane);
            for (u32 w = lane; w < PACK_WORDS; w += 32) body[w] = 0;
            __syncwarp();
            u32 bits = r_write_warp(ch, from, end, pinned, p, origin, body, &done.relative, lane);
            u32 count = end - from + (pinned ? 1u : 0u);
            if (lane == 0) r_put_header((u8*)body, tick, dilation, origin, count);
            __syncwarp();
            u32 len = R_STREAM_AT + (bits + 7) / 8;
            const uint4* src = (const uint4*)body;
            uint4* dst = (uint4*)(out + (at + datagrams) * R_BODY_STRIDE);
            for (u32 k = lane; k < (len + 15) / 16; k += 32) dst[k] = src[k];
            if (lane == 0) {
                out_lens[at + datagrams] = len;
                ends[at + datagrams] = end;
            }
            // Every lane has copied the body before it is zeroed for the next.
            __syncwarp();
            datagrams++;
            if (end == from) break;  // only the pinned record went in: never loop on it
            from = end;
        }
        done.packed = from;
        done.datagrams = datagrams;
    }
    if (lane == 0) packed[i] = done;
}
