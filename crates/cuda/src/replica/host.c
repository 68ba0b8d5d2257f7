// The replica kernels' shared logic (kernels/replica.cuh) compiled for the host, so that
// a test on any machine holds it to the Rust replica (crates/interest/src/replica.rs)
// byte for byte; the device runs the same functions (kernels/replica.cu). Built by
// build.rs with -ffp-contract=off: no fused multiply-add, as Rust and --fmad=false.
#include <math.h>
#include <stdint.h>
#include <string.h>

typedef uint32_t u32;
typedef uint64_t u64;
typedef uint8_t u8;

#include "../../kernels/replica.cuh"
#include "../../kernels/pack.cuh"

void myriad_replica_select(const RConfig* cfg, u64 now, RHome* h, const RPlayer* p, int has_own, u64 own_id,
                           u32 own_kind, const RPos* own_pos, const RPos* origin, const RCand* cands, u32 ncands,
                           const RTrack* old, u32 nold, RFlight* flights, RState* states, RTrack* next,
                           u32* cand_of, RKey* un, RKey* orph, RMoved* moved, RDue* wanted, RChosen* chosen,
                           RInfo* info) {
    r_select(cfg, now, h, p, has_own, own_id, own_kind, *own_pos, *origin, cands, ncands, old, nold, flights, states,
             next, cand_of, un, orph, moved, wanted, chosen, info);
}

void myriad_replica_commit(const RConfig* cfg, u64 now, RHome* h, const RCommit* done, const u32* ends,
                           const RChosen* chosen, const RCand* cands, RTrack* next, RFlight* flights,
                           RState* states) {
    r_commit(cfg, now, h, done, ends, chosen, cands, next, flights, states);
}

void myriad_replica_candidate(u32 slot, u64 id, u32 kind, const float* p, const float* centre, RCand* out) {
    *out = r_candidate(slot, id, kind, p, centre);
}

// `r_find_slot` from `hint`, for the test that holds it to a search of the whole array.
u32 myriad_replica_find_slot(const RTrack* tracks, u32 n, u32 slot, u32 hint) {
    return r_find_slot(tracks, n, slot, hint);
}

// The size of each shared struct, for the layout test.
void myriad_replica_sizes(u32* out) {
    out[0] = sizeof(RTrack);
    out[1] = sizeof(RConfig);
    out[2] = sizeof(RRecord);
    out[3] = sizeof(RCand);
    out[4] = sizeof(RFlight);
    out[5] = sizeof(RState);
    out[6] = sizeof(RMoved);
    out[7] = sizeof(RDue);
    out[8] = sizeof(RChosen);
    out[9] = sizeof(RHome);
    out[10] = sizeof(RPlayer);
    out[11] = sizeof(RInfo);
    out[12] = sizeof(RCommit);
    out[13] = sizeof(RKey);
    out[14] = sizeof(RPacked);
}

// `r_pack`: `pinned` may be null; `bodies` holds `max_datagrams` strides of
// `R_BODY_STRIDE` bytes, `lens` and `ends` `max_datagrams` entries.
void myriad_replica_pack(u64 tick, u32 dilation, const RPos* origin, const RRecord* pinned, const RChosen* chosen,
                         u32 n, u32 max_datagrams, u8* bodies, u32* lens, u32* ends, RPacked* out) {
    *out = r_pack(tick, dilation, *origin, pinned, chosen, n, max_datagrams, bodies, lens, ends);
}

u32 myriad_replica_body_stride(void) { return R_BODY_STRIDE; }
