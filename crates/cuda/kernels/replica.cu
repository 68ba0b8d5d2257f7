// The replica on the device (crates/cuda/src/replica): each player's tracks, flights and
// credit live in device memory, and the kernels here make the decisions of replica.cuh,
// which the host replica (crates/interest/src/replica.rs) makes the same way. A build is
// k_replica_carry (players left out keep their tracks), k_replica_due (a warp a player:
// the view matched with the tracks, acknowledgements, priorities, the objects due),
// k_replica_rank (a block a player: the objects due sorted by urgency in shared memory),
// k_replica_take (a warp a player: the budget, the records chosen), k_replica_pack
// (kernels/pack.cu, a warp a player: the records packed into delta update bodies in
// mapped host memory), the host's framing and sealing, then k_replica_commit (what the
// datagrams took, flights, tracks marked sent).
//
// What is per object (candidates, the merge with last build's tracks, acknowledgements
// within a datagram, priorities, the records' forms, marking what was sent) runs on the
// warp's 32 lanes; what is in order (the budget, the flights) runs on every lane alike
// or on lane 0, with replica.cuh's functions, so the two halves cannot drift apart.
// Lists compacted across lanes keep their order (a ballot and a population count), and
// every step reads only what the step before wrote after a __syncwarp.
//
// Layout: this build's per-candidate arrays (candidates, tracks, scratch) are at each
// player's AOI list offset; `orph` is at its old tracks' offset; flights and their
// states at its home times R_FLIGHTS and R_STATES.
#include "common.cuh"
#include "replica.cuh"

// `NETWORK_SORT` by the warp's 32 lanes (`lane`).
#define WARP_SORT(T, a, n, LESS, lane) NETWORK_SORT(T, a, n, LESS, lane, 32u, __syncwarp())

// `r_take_sorted` with the warp: 32 objects at a time, each lane chooses its object's
// record and its charge, then every lane runs the same budget over the 32 in order
// (shuffled to all), so all hold the same `fill` and counts, and the lane of an object
// taken writes its record. `wanted` is sorted; returns how many were chosen (in the
// order taken); `info->datagrams`, `deferred` and `starving` as `r_take_sorted`.
__device__ u32 r_take_sorted_warp(const RConfig* cfg, u64 now, u64 floor, const RHome* h, RPos origin,
                                  const RCand* cands, const RTrack* next, const RDue* wanted, u32 nwanted,
                                  RChosen* chosen, RInfo* info, u32 lane) {
    RFilling fill = r_filling_new(cfg, h, info, origin);
    u32 nchosen = 0;
    int open = 1;  // still taking whatever the budget pays (else only the starving)
    for (u32 base = 0; base < nwanted; base += 32) {
        u32 k = base + lane;
        RRecord rec = {};
        u32 bits = 0, starving = 0, eager = 0, track = 0, cand = 0;
        if (k < nwanted) {
            RDue d = wanted[k];
            starving = d.starving;
            eager = d.eager;
            track = d.track;
            cand = d.cand;
            // Once the budget has closed, only the starving are offered: the rest need
            // no record (most of a view where the budget binds).
            if (open || starving) {
                const RCand* c = &cands[d.cand];
                const RTrack* t = &next[d.track];
                RBase acked = r_track_acked(t, floor);
                rec = r_choose(c->id, c->kind, c->pos, now, acked, r_track_prior(t, acked));
                bits = r_charge_bits(&rec, origin);
            }
        }
        u32 items = min(32u, nwanted - base);
        if (!open && __ballot_sync(FULL_WARP, starving) == 0) {
            // Nothing here is offered: each goes deferred (the eager not counted).
            info->deferred += __popc(__ballot_sync(FULL_WARP, k < nwanted && !eager));
            continue;
        }
        for (u32 j = 0; j < items; j++) {
            u32 b = __shfl_sync(FULL_WARP, bits, j);
            u32 st = __shfl_sync(FULL_WARP, starving, j);
            u32 eg = __shfl_sync(FULL_WARP, eager, j);
            open = open && fill.budget >= R_MIN_COST;
            int taken = open || st ? r_offer(&fill, b, (int)st, (int)eg) : 0;
            if (taken) {
                info->starving += taken == 2;
                if (lane == j) {
                    chosen[nchosen].rec = rec;
                    chosen[nchosen].track = track;
                    chosen[nchosen].cand = cand;
                }
                nchosen++;
            } else {
                info->deferred += eg ? 0u : 1u;
            }
        }
    }
    info->datagrams = fill.datagrams;
    return nchosen;
}

// A player's own object this build: whether there is one, its id, kind and position.
typedef struct {
    int has;
    u64 id;
    u32 kind;
    RPos pos;
} ROwn;

// An object as a build reads it (`RObj`, src/replica/layout.rs), gathered from the
// world's arrays once a build by `k_replica_objects`: a view's slots are scattered over
// the world, so a candidate read from the arrays touched a 32-byte sector for its
// position, one for its id and one for its shape; from here it touches one, and its
// position comes quantized.
typedef struct __align__(16) {
    RPos q;
    float p[3];
    u32 id, kind;
} RObj;
static_assert(sizeof(RObj) == 32, "RObj is one sector");

extern "C" __global__ void k_replica_objects(u32 n, const float* pos, const u32* ids, const u8* shapes,
                                             RObj* objs) {
    u32 s = blockIdx.x * blockDim.x + threadIdx.x;
    if (s >= n) return;
    RObj o;
    for (u32 a = 0; a < 3; a++) o.p[a] = pos[3 * (u64)s + a];
    o.q.x = r_quant(o.p[0]);
    o.q.y = r_quant(o.p[1]);
    o.q.z = r_quant(o.p[2]);
    o.id = ids[s];
    o.kind = shapes[s];
    objs[s] = o;
}

// `r_candidate` of a gathered object, the quantization done.
__device__ __forceinline__ RCand r_candidate_obj(u32 slot, const RObj* o, const float* centre) {
    RCand c;
    c.id = o->id;
    c.slot = slot;
    c.kind = o->kind;
    c.pos = o->q;
    c.distance = r_distance(o->p, centre);
    return c;
}

__device__ ROwn r_own_of(const RPlayer* p, u32 n, const RObj* objs) {
    ROwn own = {0, 0, 0, {0, 0, 0}};
    if (p->own_slot < n) {
        const RObj* o = &objs[p->own_slot];
        own.has = 1;
        own.id = o->id;
        own.kind = o->kind;
        own.pos = o->q;
    }
    return own;
}

// Warps a block of `k_replica_due` (PLAYERS_PER_BLOCK in src/replica/device.rs).
#define DUE_WARPS 4u
// Bits of a warp's filter of the ids its acknowledged flights carry.
#define DUE_BLOOM_BITS 4096u

__device__ __forceinline__ u32 r_bloom_bit(u64 id) { return (u32)((id * 0x9E3779B97F4A7C15ull) >> 52); }
__device__ __forceinline__ int r_bloom_has(const u32* bloom, u64 id) {
    u32 b = r_bloom_bit(id);
    return (bloom[b >> 5] >> (b & 31u)) & 1u;
}

// Step 1 and 2 of a build, a warp a player: the candidates, the merge with last build's
// tracks, the acknowledgements and the priorities; the objects due go to `wanted`, and
// `counts[2 i]` and `counts[2 i + 1]` say how many candidates and how many due
// (R_NO_SLOT due: the list was out of order, reported in `info[i]`).
// `taken` marks, at last build's track offsets, each old track a candidate took with
// `build` (a number no earlier build used), so the old tracks nobody took are found
// without searching the candidates. A track whose id no acknowledged flight carries (a
// filter of their ids says so) takes its priority in the pass over the list, while it
// and its candidate are in registers; the rest (tracks new this build, and those the
// acknowledgements may touch) after the acknowledgements, as the host replica does
// for all. The objects due are in no particular order (`k_replica_rank` orders them by
// what they are).
extern "C" __global__ void k_replica_due(u32 nq, const RConfig* cfg, u64 tick, u64 build, const u32* offsets,
                                         const u32* objects, u32 n, const RObj* objs, const RPlayer* players,
                                         RHome* homes,
                                         const RTrack* old_tracks, RTrack* next_tracks, u64* taken, RCand* cands,
                                         RKey* un, RKey* orph, RMoved* moved, RDue* wanted, RFlight* flights,
                                         RState* states, u32* counts, RInfo* info) {
    u32 lane = threadIdx.x & 31u;
    u32 i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    if (i >= nq) return;
    const RPlayer* p = &players[i];
    RHome* h = &homes[p->home];
    if (p->reset && lane == 0) {
        RHome zero = {};
        *h = zero;
    }
    __syncwarp();
    u64 floor = tick > R_MAX_BACK - 1 ? tick - (R_MAX_BACK - 1) : 0;
    u32 o = offsets[i], len = offsets[i + 1] - o;
    ROwn own = r_own_of(p, n, objs);
    // Last build's tracks (`k_replica_take` points the home at this build's).
    const RTrack* old = old_tracks + h->track_off;
    u32 nold = h->track_len;
    RKey* orph_p = orph + h->track_off;
    u64* taken_p = taken + h->track_off;
    RFlight* fl_p = flights + (u64)p->home * R_FLIGHTS;
    RState* st_p = states + (u64)p->home * R_STATES;
    RCand* cs = cands + o;
    RTrack* nx = next_tracks + o;
    RKey* un_p = un + o;
    RMoved* mv = moved + o;
    RDue* wd = wanted + o;
    __syncwarp();
    if (lane == 0) r_own_now(h, own.has, own.id, own.pos);

    // The filter of the ids the acknowledged flights carry.
    __shared__ u32 blooms[DUE_WARPS][DUE_BLOOM_BITS / 32];
    u32* bloom = blooms[(threadIdx.x >> 5) % DUE_WARPS];
    for (u32 w = lane; w < DUE_BLOOM_BITS / 32; w += 32) bloom[w] = 0;
    __syncwarp();
    u32 nfl = h->nflights;
    // How fresh the link is after this build's acknowledgements (`Replica::apply_acks`
    // moves it before any priority), for the eager records.
    u64 heard = h->heard;
    for (u32 f = 0; f < nfl; f++) {
        RFlight fl = fl_p[f];
        int acked;
        r_flight_kept(p, &fl, floor, &acked);
        if (!acked) continue;
        if (fl.tick + 1 > heard) heard = fl.tick + 1;
        for (u32 s = lane; s < fl.len; s += 32) {
            u32 b = r_bloom_bit(st_p[fl.start + s].id);
            atomicOr(&bloom[b >> 5], 1u << (b & 31u));
        }
    }
    __syncwarp();
    if (lane == 0) h->heard = heard;
    int fresh_link = r_fresh_link(cfg, heard, tick);

    // One pass over the list: the candidates (the list less the own object, in its
    // order), each checked against the one before it and merged at once with last
    // build's tracks: a candidate keeps the track of its slot and id; the rest start
    // afresh (`un`), and old tracks nobody took (`orph`) may be theirs by id (an object
    // whose slot changed). A view changes little from tick to tick, so each lane looks
    // for its next item where its last one was found, shifted alike.
    // The device's lists are sorted with no slot twice, so every candidate takes a track
    // (the host replica's out-of-order drops never happen); a list that is not is a
    // fault the host is told of, not a choice.
    u32 nc = 0, nun = 0, nw = 0, nlater = 0, last_slot = 0;
    int has_last = 0, disorder = 0, drift = 0;
    for (u32 base = 0; base < len; base += 32) {
        u32 j = base + lane;
        int valid = 0;
        RCand c;
        if (j < len) {
            u32 s = objects[o + j];
            if (s < n) {
                RObj ob = objs[s];
                if (!(own.has && ob.id == own.id)) {
                    valid = 1;
                    c = r_candidate_obj(s, &ob, p->centre);
                }
            }
        }
        u32 mask = __ballot_sync(FULL_WARP, valid);
        u32 my_slot = valid ? c.slot : 0;
        u32 below = mask & ((1u << lane) - 1u);
        u32 before = __shfl_sync(FULL_WARP, my_slot, below ? 31 - __clz(below) : lane);
        int fresh = 0, due = 0, later = 0;
        RDue d;
        u32 k = nc + __popc(below);
        if (valid) {
            if (below || has_last) disorder |= c.slot <= (below ? before : last_slot);
            u32 at = r_find_slot(old, nold, c.slot, (u32)max((int)k + drift, 0));
            if (at != R_NO_SLOT && old[at].id == c.id) {
                RTrack t = old[at];
                taken_p[at] = build;
                drift = (int)at - (int)k;
                if (r_bloom_has(bloom, c.id))
                    later = 1;
                else
                    due = r_priority(cfg, tick, floor, fresh_link, &t, &c, k, k, &d);
                nx[k] = t;
            } else {
                nx[k] = r_track_new(c.id, c.slot);
                fresh = 1;
            }
            // Only what a later step reads keeps its candidate: the due (the take and
            // the commit), the fresh and the later (their priorities below). At AOI 100
            // most of a view is neither, and this is 32 bytes a candidate not written.
            if (fresh || due || later) cs[k] = c;
        }
        u32 fmask = __ballot_sync(FULL_WARP, fresh);
        if (fresh) un_p[nun + lanes_before(fmask, lane)].index = k;
        nun += __popc(fmask);
        u32 dmask = __ballot_sync(FULL_WARP, due);
        if (due) wd[nw + lanes_before(dmask, lane)] = d;
        nw += __popc(dmask);
        // The later ones' indices from the end of `wanted` down (the due fill it up).
        u32 lmask = __ballot_sync(FULL_WARP, later);
        if (later) wd[len - 1 - (nlater + lanes_before(lmask, lane))].track = k;
        nlater += __popc(lmask);
        if (mask) {
            last_slot = __shfl_sync(FULL_WARP, my_slot, 31 - __clz(mask));
            has_last = 1;
        }
        nc += __popc(mask);
    }
    if (__any_sync(FULL_WARP, disorder)) {
        if (lane == 0) {
            RInfo bad = {};
            bad.unsorted = 1;
            info[i] = bad;
            counts[2 * i] = nc;
            counts[2 * i + 1] = R_NO_SLOT;
        }
        return;
    }
    __syncwarp();
    u32 norph = 0;
    if (nun > 0) {
        for (u32 base = 0; base < nold; base += 32) {
            u32 k = base + lane;
            int orphan = k < nold && taken_p[k] != build;
            u32 mask = __ballot_sync(FULL_WARP, orphan);
            if (orphan) orph_p[norph + lanes_before(mask, lane)].index = k;
            norph += __popc(mask);
        }
    }
    __syncwarp();
    u32 nmoved = 0;
    if (lane == 0) nmoved = r_match_moved(old, nx, un_p, nun, orph_p, norph, mv);
    nmoved = __shfl_sync(FULL_WARP, nmoved, 0);
    __syncwarp();
    if (nmoved > 0) {
        // States in flight name objects by slot: the moved ones' follow them.
        for (u32 f = 0; f < nfl; f++) {
            RFlight fl = fl_p[f];
            for (u32 s = lane; s < fl.len; s += 32) {
                RState* st = &st_p[fl.start + s];
                for (u32 m = 0; m < nmoved; m++) {
                    if (mv[m].from == st->slot && mv[m].id == st->id) {
                        st->slot = mv[m].to;
                        break;
                    }
                }
            }
        }
        __syncwarp();
    }

    // Acknowledgements: flights in order, one flight's states (distinct objects) at once.
    u32 kept = 0;
    for (u32 f = 0; f < nfl; f++) {
        RFlight fl = fl_p[f];
        int acked;
        int keep = r_flight_kept(p, &fl, floor, &acked);
        if (acked) {
            for (u32 s = lane; s < fl.len; s += 32) r_ack_state(h, nx, nc, &st_p[fl.start + s], fl.tick);
        }
        __syncwarp();
        if (keep) {
            if (lane == 0) fl_p[kept] = fl;
            kept++;
        }
        __syncwarp();
    }
    if (lane == 0) h->nflights = kept;

    // Priorities of the tracks new this build, then of those the acknowledgements may
    // have touched; the objects due after the list pass's. Those read from the end of
    // `wanted` lowest index first, each chunk read before any is written: the due
    // written so far never reach an index not yet read.
    for (u32 base = 0; base < nun; base += 32) {
        u32 j = base + lane;
        u32 k = j < nun ? un_p[j].index : 0;
        RDue d;
        int due = j < nun && r_priority(cfg, tick, floor, fresh_link, &nx[k], &cs[k], k, k, &d);
        u32 mask = __ballot_sync(FULL_WARP, due);
        if (due) wd[nw + lanes_before(mask, lane)] = d;
        nw += __popc(mask);
    }
    for (u32 base = 0; base < nlater; base += 32) {
        u32 j = base + lane;
        u32 k = j < nlater ? wd[len - nlater + j].track : 0;
        __syncwarp();
        RDue d;
        int due = j < nlater && r_priority(cfg, tick, floor, fresh_link, &nx[k], &cs[k], k, k, &d);
        u32 mask = __ballot_sync(FULL_WARP, due);
        if (due) wd[nw + lanes_before(mask, lane)] = d;
        nw += __popc(mask);
    }
    if (lane == 0) {
        counts[2 * i] = nc;
        counts[2 * i + 1] = nw;
    }
}

// The most objects due that `k_replica_rank` sorts in shared memory (a player's view
// rarely holds more; beyond, the block sorts them in global memory).
#define RANK_CAP 4096u

// A block a player: the objects due sorted by `r_due_less` into `ranked`. The sort keys
// (each rank's upper word and the item's index) are sorted in shared memory, where a
// warp sorting 32-byte items in global memory waited on every step; equal upper words,
// rare, are told apart by the items themselves (`r_due_less` is a total order), so the
// order the items come in does not matter.
extern "C" __global__ void k_replica_rank(u32 nq, const u32* offsets, const u32* counts, RDue* wanted,
                                          RDue* ranked) {
    __shared__ u64 key[RANK_CAP];
    __shared__ unsigned short at[RANK_CAP];
    u32 i = blockIdx.x;
    if (i >= nq) return;
    u32 nw = counts[2 * i + 1];
    if (nw == R_NO_SLOT) return;
    u32 o = offsets[i], t = threadIdx.x, step = blockDim.x;
    RDue* wd = wanted + o;
    RDue* rk = ranked + o;
    if (nw > RANK_CAP) {
        NETWORK_SORT(RDue, wd, nw, r_due_less, t, step, __syncthreads());
        for (u32 k = t; k < nw; k += step) rk[k] = wd[k];
        return;
    }
    u32 size = 1;
    while (size < nw) size <<= 1;
    for (u32 k = t; k < nw; k += step) {
        key[k] = wd[k].hi;
        at[k] = (unsigned short)k;
    }
    __syncthreads();
    for (u32 k = 2; k <= size; k <<= 1) {
        for (u32 j = k >> 1; j > 0; j >>= 1) {
            for (u32 q = t; q < size / 2; q += step) {
                u32 lo, hi;
                bitonic_pair(q, k, j, &lo, &hi);
                if (hi < nw) {
                    u64 a = key[hi], b = key[lo];
                    if (a < b || (a == b && r_due_less(&wd[at[hi]], &wd[at[lo]]))) {
                        key[hi] = b;
                        key[lo] = a;
                        unsigned short x = at[lo];
                        at[lo] = at[hi];
                        at[hi] = x;
                    }
                }
            }
            __syncthreads();
        }
    }
    for (u32 k = t; k < nw; k += step) rk[k] = wd[at[k]];
}

// Step 3 of a build, a warp a player: the own record, then the objects due (`ranked`, in
// the order of urgency) into the budget (`r_take_due`'s steps: every lane keeps the same
// budget), the chosen records sorted by the warp; the counts to the host (`info`, mapped)
// and to `k_replica_pack` (`infos`).
extern "C" __global__ void k_replica_take(u32 nq, const RConfig* cfg, u64 tick, const u32* offsets, u32 n,
                                          const RObj* objs, const RPlayer* players, RHome* homes,
                                          const RTrack* next_tracks, const RCand* cands, const u32* counts,
                                          const RDue* ranked, RChosen* chosen, RInfo* info, RInfo* infos) {
    u32 lane = threadIdx.x & 31u;
    u32 i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    if (i >= nq) return;
    u32 nc = counts[2 * i], nw = counts[2 * i + 1];
    if (nw == R_NO_SLOT) return;
    const RPlayer* p = &players[i];
    RHome* h = &homes[p->home];
    u64 floor = tick > R_MAX_BACK - 1 ? tick - (R_MAX_BACK - 1) : 0;
    u32 o = offsets[i];
    ROwn own = r_own_of(p, n, objs);
    RChosen* ch = chosen + o;

    RInfo mine = {};
    mine.in_view = nc;
    mine.has_own_record = (u32)(own.has && h->has_own);
    if (mine.has_own_record) {
        RBase acked = r_track_acked(&h->own, floor);
        mine.own_record = r_choose(own.id, own.kind, own.pos, tick, acked, r_track_prior(&h->own, acked));
    }
    RPos origin = {r_quant(p->centre[0]), r_quant(p->centre[1]), r_quant(p->centre[2])};
    u32 nch = r_take_sorted_warp(cfg, tick, floor, h, origin, cands + o, next_tracks + o, ranked + o, nw, ch, &mine,
                                 lane);
    __syncwarp();
    WARP_SORT(RChosen, ch, nch, r_chosen_less, lane);
    // A repeated id (only from a broken source) goes once: the rare case on lane 0.
    int repeated = 0;
    for (u32 k = 1 + lane; k < nch; k += 32) repeated |= ch[k].rec.id == ch[k - 1].rec.id;
    if (__any_sync(FULL_WARP, repeated)) {
        if (lane == 0) r_chosen_unique(ch, nch, &mine);
    } else {
        mine.count = nch;
    }
    if (lane == 0) {
        h->track_off = o;
        h->track_len = nc;
        info[i] = mine;
        infos[i] = mine;
    }
}

extern "C" __global__ void k_replica_commit(u32 nq, const RConfig* cfg, u64 tick, const u32* offsets,
                                            const RPlayer* players, RHome* homes, const RCommit* commits,
                                            const u32* ends, const RChosen* chosen, const RCand* cands,
                                            RTrack* next_tracks, RFlight* flights, RState* states) {
    u32 lane = threadIdx.x & 31u;
    u32 i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    if (i >= nq) return;
    u32 home = players[i].home, o = offsets[i];
    RHome* h = &homes[home];
    const RCommit* done = &commits[i];
    if (lane == 0) r_commit_credit(cfg, h, done);
    if (!done->ok) return;
    RFlight* fl_p = flights + (u64)home * R_FLIGHTS;
    RState* st_p = states + (u64)home * R_STATES;
    const u32* e = ends + (u64)i * cfg->max_datagrams;
    u32 own = h->has_own_now ? 1u : 0u;
    u32 start = 0;
    for (u32 d = 0; d < done->datagrams; d++) {
        u32 end = e[d];
        u32 at = 0;
        if (lane == 0) at = r_commit_flight(h, fl_p, st_p, done->first + d, tick, end - start);
        at = __shfl_sync(FULL_WARP, at, 0);
        __syncwarp();
        for (u32 k = start + lane; k < end; k += 32)
            r_commit_record(tick, &chosen[o + k], cands + o, next_tracks + o, &st_p[at + own + (k - start)]);
        __syncwarp();
        start = end;
    }
}

// Players left out of this build keep their tracks: `carry` holds (home, new offset)
// pairs, each home's tracks copied there from the last build's buffer.
extern "C" __global__ void k_replica_carry(u32 count, const u32* carry, const RTrack* old_tracks,
                                           RTrack* next_tracks, RHome* homes) {
    u32 k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= count) return;
    RHome* h = &homes[carry[2 * k]];
    u32 to = carry[2 * k + 1];
    for (u32 t = 0; t < h->track_len; t++) next_tracks[to + t] = old_tracks[h->track_off + t];
    h->track_off = to;
}
