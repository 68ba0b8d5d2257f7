// The replica on the device (crates/cuda/src/replica): each player's tracks, flights and
// credit live in device memory, and one thread per player runs the decisions of
// replica.cuh, which the host replica (crates/interest/src/replica.rs) makes the same
// way. A build is k_replica_carry (players left out keep their tracks), k_replica_select
// (the records chosen, stored into mapped host memory), the host's packing and sealing,
// then k_replica_commit (what the datagrams took, flights, tracks marked sent).
//
// Layout: this build's per-candidate arrays (candidates, tracks, scratch) are at each
// player's AOI list offset; `orph` is at its old tracks' offset; flights and their
// states at its home times R_FLIGHTS and R_STATES.
#include "common.cuh"
#include "replica.cuh"

extern "C" __global__ void k_replica_select(u32 nq, const RConfig* cfg, u64 tick, const u32* offsets,
                                            const u32* objects, u32 n, const float* pos, const u32* ids,
                                            const u8* shapes, const RPlayer* players, RHome* homes,
                                            const RTrack* old_tracks, RTrack* next_tracks, RCand* cands,
                                            u32* cand_of, RKey* un, RKey* orph, RMoved* moved, RDue* wanted,
                                            RChosen* chosen, RFlight* flights, RState* states, RInfo* info,
                                            RRecord* out, u32 out_cap) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= nq) return;
    const RPlayer* p = &players[i];
    RHome* h = &homes[p->home];
    if (p->reset) {
        RHome zero = {};
        *h = zero;
    }
    u32 o = offsets[i], len = offsets[i + 1] - o;
    int has_own = p->own_slot < n;
    u64 own_id = 0;
    u32 own_kind = 0;
    RPos own_pos = {0, 0, 0};
    if (has_own) {
        u32 s = p->own_slot;
        own_id = ids[s];
        own_kind = shapes[s];
        own_pos.x = r_quant(pos[3 * s]);
        own_pos.y = r_quant(pos[3 * s + 1]);
        own_pos.z = r_quant(pos[3 * s + 2]);
    }
    u32 nc = 0;
    for (u32 j = 0; j < len; j++) {
        u32 s = objects[o + j];
        if (s >= n) continue;
        u64 id = ids[s];
        if (has_own && id == own_id) continue;
        cands[o + nc++] = r_candidate(s, id, shapes[s], pos + 3 * (u64)s, p->centre);
    }
    RPos origin = {r_quant(p->centre[0]), r_quant(p->centre[1]), r_quant(p->centre[2])};
    u32 old_off = h->track_off, nold = h->track_len;
    RInfo mine;
    r_select(cfg, tick, h, p, has_own, own_id, own_kind, own_pos, origin, cands + o, nc, old_tracks + old_off, nold,
             flights + (u64)p->home * R_FLIGHTS, states + (u64)p->home * R_STATES, next_tracks + o, cand_of + o,
             un + o, orph + old_off, moved + o, wanted + o, chosen + o, &mine);
    h->track_off = o;
    h->track_len = mine.in_view;
    if (mine.count > out_cap) {
        mine.overflow = 1;
        mine.count = out_cap;
    }
    RRecord* dst = out + (u64)i * out_cap;
    for (u32 k = 0; k < mine.count; k++) dst[k] = chosen[o + k].rec;
    info[i] = mine;
}

extern "C" __global__ void k_replica_commit(u32 nq, const RConfig* cfg, u64 tick, const u32* offsets,
                                            const RPlayer* players, RHome* homes, const RCommit* commits,
                                            const u32* ends, const RChosen* chosen, const RCand* cands,
                                            RTrack* next_tracks, RFlight* flights, RState* states) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= nq) return;
    u32 home = players[i].home, o = offsets[i];
    r_commit(cfg, tick, &homes[home], &commits[i], ends + (u64)i * cfg->max_datagrams, chosen + o, cands + o,
             next_tracks + o, flights + (u64)home * R_FLIGHTS, states + (u64)home * R_STATES);
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
