// The replica's decisions (crates/interest/src/replica.rs, protocol version 3), one
// player at a time, in C that compiles for the device (kernels/replica.cu, NVRTC) and
// for the host (src/replica/host.c, the test that holds it to the Rust replica). The
// records chosen here are packed by pack.cuh's `r_pack` (`pack_deltas`' rules), the host
// seals them, and what the datagrams took comes back (`r_commit`).
//
// Every function mirrors its Rust counterpart operation for operation: floats in the
// same order with no fused multiply–add (--fmad=false, -ffp-contract=off), IEEE division
// and square root, integer rounding as Rust's `div_euclid`. Sorts that Rust leaves
// unstable sort here (and there) by a total order, so both pick the same.
#pragma once

#ifdef __CUDACC__
#define RFN __device__ static inline
#else
#define RFN static inline
#endif

#define R_NONE 0xffffffffffffffffull
#define R_NO_SLOT 0xffffffffu
#define R_MAX_BACK 63ull
#define R_ACK_BITS 64ull
// Flights a player keeps at most, and the states in them (`MAX_FLIGHTS`,
// `MAX_FLIGHT_STATES` in replica.rs): beyond, the oldest flight is dropped.
#define R_FLIGHTS 64u
#define R_STATES 4096u
// Protocol constants (crates/protocol/src/delta.rs, header.rs).
#define R_MAX_BODY 1166u
#define R_DELTA_HEADER_LEN 24u
#define R_MAX_RECORD_LEN 29u
#define R_STREAM_PARAMS_BITS 12u
#define R_ID_CHARGE_BITS 16u
// `DATAGRAM_OVERHEAD`: packet header 18, tag 16, delta update header 24.
#define R_DATAGRAM_OVERHEAD 58u
#define R_WAIT_SLACK 1.0e-3f

// Record forms (`RecordState`).
#define R_ABSOLUTE 0u
#define R_SAME 1u
#define R_DELTA 2u
#define R_PREDICTED 3u

typedef struct {
    int x, y, z;
} RPos;

// `Track`, 64 bytes.
typedef struct {
    u64 id;
    u64 acked_tick;
    u64 sent_tick;
    RPos acked;
    RPos sent;
    float priority;
    u32 slot;
    u8 prior_back;
    u8 sent_moved;
    short prior_offset[3];
} RTrack;

// `ReplicationConfig` and `max_datagrams`.
typedef struct {
    u64 resend_ticks;
    float budget, near_units, near_bound, far_bound, far_units, refresh, max_wait;
    u32 max_datagrams;
} RConfig;

// A `DeltaRecord`: `v` is the delta (Delta, Predicted) or the position (Absolute).
typedef struct {
    u64 id;
    u8 form, kind, back, prior;
    int v[3];
} RRecord;

// A candidate (`Candidate`).
typedef struct {
    u64 id;
    u32 slot, kind;
    RPos pos;
    float distance;
} RCand;

// One flight's header; its states are `states[start .. start + len]`.
typedef struct {
    u64 sequence, tick;
    u32 start, len;
} RFlight;

// One state a flight carried: `(slot, id, position)`.
typedef struct {
    u64 id;
    u32 slot;
    RPos pos;
} RState;

// `(old slot, id, new slot)` of an object matched by id.
typedef struct {
    u64 id;
    u32 from, to;
} RMoved;

// `Due`: the rank as two words (`hi`, then the id), the track and candidate indices.
typedef struct {
    u64 hi, id;
    u32 track, cand;
    u32 starving, eager;
} RDue;

// What a player's build chose: the record and where it came from.
typedef struct {
    RRecord rec;
    u32 track, cand;
} RChosen;

// What persists of a player from build to build besides its tracks.
typedef struct {
    RTrack own;
    float credit;
    u32 has_own, nflights;
    // Where its tracks are, in the buffer the last build wrote.
    u32 track_off, track_len;
    // This build's own object, for its flights.
    u32 has_own_now;
    u64 own_now_id;
    RPos own_now;
    u32 pad;
    // One past the tick of the newest flight the player acknowledged (0: none yet).
    u64 heard;
} RHome;

// One player's inputs of a build.
typedef struct {
    u64 ack_newest, ack_bits;
    float centre[3];
    u32 home, reset, own_slot, has_acks, pad;
} RPlayer;

// One player's outputs of a build (besides the chosen records).
typedef struct {
    RRecord own_record;
    // `unsorted`: the player's AOI list was not in ascending slot order (a device
    // fault the host is told of; nothing else was built).
    u32 has_own_record, datagrams, count, in_view, out_of_order, deferred, starving, unsorted;
} RInfo;

// What packing (pack.cuh) and the host's sealing did, for `r_commit`: whether the
// datagrams were sealed, the first one's sequence number, the bytes they took, how many
// records they packed, and how many there are (`ends` holds where each one's records
// end).
typedef struct {
    u64 first;
    float spent;
    u32 ok, packed, datagrams;
} RCommit;

// ---- protocol (crates/protocol/src/delta.rs, bits.rs, baselines.rs) ----

RFN u32 r_clz64(u64 v) {
#ifdef __CUDACC__
    return (u32)__clzll((long long)v);
#else
    return v == 0 ? 64u : (u32)__builtin_clzll(v);
#endif
}

// `signed_bits`: bits of the smallest two's complement field that holds `v`.
RFN u32 r_signed_bits(long long v) {
    u64 magnitude = (u64)(v < 0 ? ~v : v);
    return 65u - r_clz64(magnitude);
}

RFN u32 r_delta_width(u32 c) { return c == 0 ? 3u : c == 1 ? 5u : c == 2 ? 7u : 10u; }
RFN u32 r_near_width(u32 c) { return c == 0 ? 10u : c == 1 ? 12u : c == 2 ? 13u : 16u; }

// `class_of`: the first class whose width holds every axis, or -1.
RFN int r_class_of(int near_widths, long long a, long long b, long long c) {
    u32 need = r_signed_bits(a);
    u32 nb = r_signed_bits(b), nc = r_signed_bits(c);
    if (nb > need) need = nb;
    if (nc > need) need = nc;
    for (u32 k = 0; k < 4; k++) {
        u32 w = near_widths ? r_near_width(k) : r_delta_width(k);
        if (w >= need) return (int)k;
    }
    return -1;
}

// `delta_to`: `pos - from` if the widest delta class holds it.
RFN int r_delta_to(RPos pos, const long long from[3], int d[3]) {
    long long a = (long long)pos.x - from[0], b = (long long)pos.y - from[1], c = (long long)pos.z - from[2];
    if (r_class_of(0, a, b, c) < 0) return 0;
    d[0] = (int)(short)a;
    d[1] = (int)(short)b;
    d[2] = (int)(short)c;
    return 1;
}

RFN long long r_div_euclid(long long a, long long b) {
    long long q = a / b;
    if (a % b < 0) q = b > 0 ? q - 1 : q + 1;
    return q;
}

// `predict`: the baseline moved on along its move since the prior.
RFN void r_predict(RPos base, RPos prior, u32 back, u32 prior_ticks, long long out[3]) {
    long long p = prior_ticks > 1 ? (long long)prior_ticks : 1;
    long long b[3] = {base.x, base.y, base.z}, a[3] = {prior.x, prior.y, prior.z};
    for (int k = 0; k < 3; k++) {
        long long n = (b[k] - a[k]) * (long long)back;
        out[k] = b[k] + r_div_euclid(2 * n + p, 2 * p);
    }
}

RFN int r_valid_back(u32 back) { return back >= 1 && back <= R_MAX_BACK; }

// `DeltaRecord::bits`: 0 for a record no datagram can carry.
RFN u32 r_bits(const RRecord* r, RPos origin, u32 usual) {
    u32 back_bits = r->back == usual ? 1u : 7u;
    switch (r->form) {
    case R_SAME:
        return r_valid_back(r->back) ? 3u + back_bits : 0u;
    case R_DELTA: {
        if (!r_valid_back(r->back)) return 0;
        int c = r_class_of(0, r->v[0], r->v[1], r->v[2]);
        return c < 0 ? 0u : 1u + back_bits + 1u + 2u + 3u * r_delta_width((u32)c);
    }
    case R_PREDICTED: {
        if (!r_valid_back(r->back) || r->prior < 1 || (u64)r->back + (u64)r->prior > R_MAX_BACK) return 0;
        int c = r_class_of(0, r->v[0], r->v[1], r->v[2]);
        u32 prior_bits = r->prior == r->back ? 1u : 7u;
        return c < 0 ? 0u : 1u + back_bits + 1u + prior_bits + 2u + 3u * r_delta_width((u32)c);
    }
    default: {
        int c = r_class_of(1, (long long)r->v[0] - origin.x, (long long)r->v[1] - origin.y,
                           (long long)r->v[2] - origin.z);
        return c < 0 ? 3u + 2u + 96u : 2u + 2u + 2u + 3u * r_near_width((u32)c);
    }
    }
}

// An optional baseline: `valid` 0 is `None`.
typedef struct {
    u64 tick;
    RPos pos;
    u32 valid;
} RBase;

RFN int r_pos_eq(RPos a, RPos b) { return a.x == b.x && a.y == b.y && a.z == b.z; }

// `DeltaRecord::choose`.
RFN RRecord r_choose(u64 id, u32 kind, RPos pos, u64 tick, RBase baseline, RBase prior) {
    RRecord r;
    r.id = id;
    r.kind = (u8)kind;
    r.back = 0;
    r.prior = 0;
    r.form = R_ABSOLUTE;
    r.v[0] = pos.x;
    r.v[1] = pos.y;
    r.v[2] = pos.z;
    if (!baseline.valid || tick < baseline.tick) return r;
    u64 back = tick - baseline.tick;
    if (back < 1 || back > R_MAX_BACK) return r;
    if (r_pos_eq(baseline.pos, pos)) {
        r.form = R_SAME;
        r.back = (u8)back;
        return r;
    }
    long long from[3] = {baseline.pos.x, baseline.pos.y, baseline.pos.z};
    RRecord plain = r, predicted = r;
    int has_plain = r_delta_to(pos, from, plain.v);
    plain.form = R_DELTA;
    plain.back = (u8)back;
    int has_predicted = 0;
    if (prior.valid && baseline.tick >= prior.tick) {
        u64 n = baseline.tick - prior.tick;
        if (n >= 1 && back + n <= R_MAX_BACK) {
            long long guess[3];
            r_predict(baseline.pos, prior.pos, (u32)back, (u32)n, guess);
            has_predicted = r_delta_to(pos, guess, predicted.v);
            predicted.form = R_PREDICTED;
            predicted.back = (u8)back;
            predicted.prior = (u8)n;
        }
    }
    RPos zero = {0, 0, 0};
    if (has_plain && has_predicted) return r_bits(&predicted, zero, 0) < r_bits(&plain, zero, 0) ? predicted : plain;
    if (has_plain) return plain;
    if (has_predicted) return predicted;
    return r;
}

// `charge_bits`.
RFN u32 r_charge_bits(const RRecord* r, RPos origin) {
    u32 b = r_bits(r, origin, 0);
    return b == 0 ? R_MAX_RECORD_LEN * 8u : b + R_ID_CHARGE_BITS;
}

// `AckField::contains`.
RFN int r_ack_contains(u64 newest, u64 bits, u64 sequence) {
    if (sequence > newest) return 0;
    u64 back = newest - sequence;
    if (back == 0) return 1;
    if (back <= R_ACK_BITS) return (int)((bits >> (back - 1)) & 1ull);
    return 0;
}

// `QuantPos::from_f32` for one component: in f64, `v * 64` and `± 0.5` are exact; the
// conversion truncates and saturates, NaN to 0 (Rust's `as`).
RFN int r_quant(float v) {
    double s = (double)v * 64.0;
    double t = trunc(s + copysign(0.5, s));
    if (isnan(t)) return 0;
    if (t >= 2147483647.0) return 2147483647;
    if (t <= -2147483648.0) return (int)(-2147483647 - 1);
    return (int)t;
}

// A candidate's distance from the player's centre as `InterestManager` computes it:
// `((dx² + dy²) + dz²)`, then the square root.
RFN float r_distance(const float* p, const float* centre) {
    float d0 = p[0] - centre[0], d1 = p[1] - centre[1], d2 = p[2] - centre[2];
    return sqrtf(d0 * d0 + d1 * d1 + d2 * d2);
}

// A candidate as `InterestManager` builds it: the object's quantized position and its
// distance from the player's centre.
RFN RCand r_candidate(u32 slot, u64 id, u32 kind, const float* p, const float* centre) {
    RCand c;
    c.id = id;
    c.slot = slot;
    c.kind = kind;
    c.pos.x = r_quant(p[0]);
    c.pos.y = r_quant(p[1]);
    c.pos.z = r_quant(p[2]);
    c.distance = r_distance(p, centre);
    return c;
}

// ---- the replica (crates/interest/src/replica.rs) ----

RFN RTrack r_track_new(u64 id, u32 slot) {
    RTrack t;
    t.id = id;
    t.acked_tick = R_NONE;
    t.sent_tick = R_NONE;
    t.acked.x = t.acked.y = t.acked.z = 0;
    t.sent = t.acked;
    t.priority = 0.0f;
    t.slot = slot;
    t.prior_back = 0;
    t.sent_moved = 0;
    t.prior_offset[0] = t.prior_offset[1] = t.prior_offset[2] = 0;
    return t;
}

RFN RBase r_track_acked(const RTrack* t, u64 floor) {
    RBase b;
    b.valid = t->acked_tick != R_NONE && t->acked_tick >= floor;
    b.tick = t->acked_tick;
    b.pos = t->acked;
    return b;
}

RFN RBase r_track_prior(const RTrack* t, RBase acked) {
    RBase b;
    b.valid = acked.valid && t->prior_back > 0;
    b.tick = acked.tick - (u64)t->prior_back;
    // Wrapping, as the Rust.
    b.pos.x = (int)((u32)t->acked.x + (u32)(int)t->prior_offset[0]);
    b.pos.y = (int)((u32)t->acked.y + (u32)(int)t->prior_offset[1]);
    b.pos.z = (int)((u32)t->acked.z + (u32)(int)t->prior_offset[2]);
    return b;
}

RFN int r_fits_i16(long long d) { return d >= -32768 && d <= 32767; }

// `Track::acknowledge`.
RFN void r_track_acknowledge(RTrack* t, u64 tick, RPos pos) {
    if (t->acked_tick != R_NONE && t->acked_tick >= tick) return;
    long long o[3] = {(long long)t->acked.x - pos.x, (long long)t->acked.y - pos.y, (long long)t->acked.z - pos.z};
    int fits = r_fits_i16(o[0]) && r_fits_i16(o[1]) && r_fits_i16(o[2]);
    int has_back = t->acked_tick != R_NONE && tick - t->acked_tick < R_MAX_BACK;
    if (has_back && fits) {
        t->prior_back = (u8)(tick - t->acked_tick);
        t->prior_offset[0] = (short)o[0];
        t->prior_offset[1] = (short)o[1];
        t->prior_offset[2] = (short)o[2];
    } else {
        t->prior_back = 0;
        t->prior_offset[0] = t->prior_offset[1] = t->prior_offset[2] = 0;
    }
    t->acked_tick = tick;
    t->acked = pos;
}

// `ReplicationConfig::bound_ticks`.
RFN float r_bound_ticks(const RConfig* c, float distance) {
    float near_bound = fmaxf(c->near_bound, 1.0f), far_bound = fmaxf(c->far_bound, 1.0f);
    float span = fmaxf(c->far_units - c->near_units, 1.17549435e-38f);
    float along = (distance - c->near_units) / span;
    if (along < 0.0f) along = 0.0f;
    if (along > 1.0f) along = 1.0f;
    if (isnan(along)) return near_bound;
    return near_bound + fmaxf(far_bound - near_bound, 0.0f) * along;
}

RFN u32 r_float_bits(float f) {
#ifdef __CUDACC__
    return __float_as_uint(f);
#else
    u32 b;
    memcpy(&b, &f, 4);
    return b;
#endif
}

// `Due::rank`'s upper word (the id is the lower).
RFN u64 r_rank_hi(int eager, int first, float priority, float distance) {
    const u32 magnitude = 0x7fffffffu;
    u64 p = (u64)(magnitude - (r_float_bits(priority) & magnitude));
    u64 d = (u64)(r_float_bits(distance) & magnitude);
    return ((u64)(eager ? 1 : 0) << 63) | ((u64)(first ? 0 : 1) << 62) | (p << 31) | d;
}

// Orders of the sorts below: `a` before `b`.
RFN int r_due_less(const RDue* a, const RDue* b) {
    if (a->hi != b->hi) return a->hi < b->hi;
    if (a->id != b->id) return a->id < b->id;
    return a->track < b->track;
}
RFN int r_chosen_less(const RChosen* a, const RChosen* b) {
    if (a->rec.id != b->rec.id) return a->rec.id < b->rec.id;
    return a->track < b->track;
}

// Heapsort of `n` items of `T` by `LESS(&a, &b)` (no allocation, any n).
#define R_SIFT(T, a, start, end, LESS)                                                                  \
    do {                                                                                                \
        u32 root_ = (start);                                                                            \
        for (;;) {                                                                                      \
            u32 child_ = 2 * root_ + 1;                                                                 \
            if (child_ >= (end)) break;                                                                 \
            if (child_ + 1 < (end) && LESS(&(a)[child_], &(a)[child_ + 1])) child_++;                   \
            if (!LESS(&(a)[root_], &(a)[child_])) break;                                                \
            T tmp_ = (a)[root_];                                                                        \
            (a)[root_] = (a)[child_];                                                                   \
            (a)[child_] = tmp_;                                                                         \
            root_ = child_;                                                                             \
        }                                                                                               \
    } while (0)
#define R_HEAPSORT(T, a, n, LESS)                                                                       \
    do {                                                                                                \
        u32 n_ = (n);                                                                                   \
        for (u32 s_ = n_ / 2; s_-- > 0;) R_SIFT(T, a, s_, n_, LESS);                                    \
        for (u32 e_ = n_; e_ > 1; e_--) {                                                               \
            T tmp2_ = (a)[0];                                                                           \
            (a)[0] = (a)[e_ - 1];                                                                       \
            (a)[e_ - 1] = tmp2_;                                                                        \
            R_SIFT(T, a, 0, e_ - 1, LESS);                                                              \
        }                                                                                               \
    } while (0)

// Index sorts by (id, index): `unmatched` holds indices into `next`, `orphans` into `old`.
typedef struct {
    u64 id;
    u32 index, pad;
} RKey;
RFN int r_key_less(const RKey* a, const RKey* b) {
    if (a->id != b->id) return a->id < b->id;
    return a->index < b->index;
}

// The end of `Replica::match_view`: tracks new this build by slot (`un`, indices into
// `next`) take the state of an old track no candidate took by slot (`orph`, indices into
// `old`) of the same id, an object whose slot changed; returns how many, each in
// `moved`.
RFN u32 r_match_moved(const RTrack* old, RTrack* next, RKey* un, u32 nun, RKey* orph, u32 norph, RMoved* moved) {
    if (nun == 0 || norph == 0) return 0;
    for (u32 k = 0; k < nun; k++) un[k].id = next[un[k].index].id;
    for (u32 k = 0; k < norph; k++) orph[k].id = old[orph[k].index].id;
    R_HEAPSORT(RKey, un, nun, r_key_less);
    R_HEAPSORT(RKey, orph, norph, r_key_less);
    u32 o = 0, nmoved = 0;
    for (u32 k = 0; k < nun; k++) {
        u64 id = un[k].id;
        while (o < norph && orph[o].id < id) o++;
        if (o < norph && orph[o].id == id) {
            u32 at = un[k].index;
            u32 slot = next[at].slot;
            const RTrack* from = &old[orph[o].index];
            moved[nmoved].from = from->slot;
            moved[nmoved].id = id;
            moved[nmoved].to = slot;
            nmoved++;
            next[at] = *from;
            next[at].slot = slot;
            o++;
        }
    }
    return nmoved;
}

// `Replica::match_view`: this build's tracks into `next` (one per candidate taken, in
// the view's order, its candidate in `cand_of`); returns how many there are. `un` and
// `moved` are scratch for `ncands` entries, `orph` for `nold`.
RFN u32 r_match_view(int has_own, u64 own_id, const RCand* cands, u32 ncands, const RTrack* old, u32 nold,
                     RTrack* next, u32* cand_of, RKey* un, RKey* orph, RMoved* moved, u32* nmoved,
                     u32* out_of_order) {
    u32 i = 0, n = 0, nun = 0, norph = 0, has_last = 0, last = 0;
    *nmoved = 0;
    *out_of_order = 0;
    // Unmatched: indices into next; orphans: into old.
    for (u32 j = 0; j < ncands; j++) {
        const RCand* c = &cands[j];
        if (has_own && own_id == c->id) continue;
        if (has_last && c->slot <= last) {
            *out_of_order += 1;
            continue;
        }
        has_last = 1;
        last = c->slot;
        while (i < nold && old[i].slot < c->slot) {
            orph[norph].index = i;
            norph++;
            i++;
        }
        cand_of[n] = j;
        if (i < nold && old[i].slot == c->slot) {
            i++;
            if (old[i - 1].id == c->id) {
                next[n++] = old[i - 1];
                continue;
            }
            orph[norph].index = i - 1;
            norph++;
        }
        un[nun].index = n;
        nun++;
        next[n++] = r_track_new(c->id, c->slot);
    }
    if (nun == 0) return n;
    for (; i < nold; i++) {
        orph[norph].index = i;
        norph++;
    }
    *nmoved = r_match_moved(old, next, un, nun, orph, norph, moved);
    return n;
}

// `NAME(items, n, slot, hint)`: the index of the item of `slot` in `items` (of type `T`,
// ascending by slot), or R_NO_SLOT. Tracks and candidates are both searched by slot. The
// search starts at `hint` and gallops outward, so an answer near it costs a few reads
// where bisecting costs a dozen dependent ones (the merge's: a candidate's track of the
// last build sits near the candidate's own index); a hint of R_NO_SLOT bisects.
#define R_FIND_BY_SLOT(NAME, T)                                                                         \
    RFN u32 NAME(const T* items, u32 n, u32 slot, u32 hint) {                                           \
        u32 lo = 0, hi = n; /* the first item not below `slot` is in [lo, hi] */                        \
        if (hint < n && items[hint].slot < slot) {                                                      \
            lo = hint + 1;                                                                              \
            for (u32 step = 1; lo < hi; step <<= 1) {                                                   \
                u32 probe = lo + step - 1;                                                              \
                if (probe >= n) break;                                                                  \
                if (items[probe].slot >= slot) {                                                        \
                    hi = probe;                                                                         \
                    break;                                                                              \
                }                                                                                       \
                lo = probe + 1;                                                                         \
            }                                                                                           \
        } else if (hint < n) {                                                                          \
            hi = hint;                                                                                  \
            for (u32 step = 1; lo < hi && step <= hi - lo; step <<= 1) {                                \
                u32 probe = hi - step;                                                                  \
                if (items[probe].slot < slot) {                                                         \
                    lo = probe + 1;                                                                     \
                    break;                                                                              \
                }                                                                                       \
                hi = probe;                                                                             \
            }                                                                                           \
        }                                                                                               \
        while (lo < hi) {                                                                               \
            u32 mid = lo + (hi - lo) / 2;                                                               \
            if (items[mid].slot < slot)                                                                 \
                lo = mid + 1;                                                                           \
            else                                                                                        \
                hi = mid;                                                                               \
        }                                                                                               \
        return lo < n && items[lo].slot == slot ? lo : R_NO_SLOT;                                       \
    }
R_FIND_BY_SLOT(r_find_slot, RTrack)
R_FIND_BY_SLOT(r_find_cand, RCand)

// One state of an acknowledged flight of `tick`: its object's baseline if newer (the own
// object's, or the track of its slot and id; nothing for an object that left the view).
RFN void r_ack_state(RHome* h, RTrack* tracks, u32 ntracks, const RState* st, u64 tick) {
    RTrack* t = 0;
    if (h->has_own && h->own.id == st->id) {
        t = &h->own;
    } else {
        u32 k = r_find_slot(tracks, ntracks, st->slot, R_NO_SLOT);
        if (k != R_NO_SLOT && tracks[k].id == st->id) t = &tracks[k];
    }
    if (t) r_track_acknowledge(t, tick, st->pos);
}

// Whether the link acknowledged a flight within `resend_ticks` (eager records go only
// over such a link): `heard` is one past the newest acknowledged flight's tick.
RFN int r_fresh_link(const RConfig* cfg, u64 heard, u64 now) {
    return heard != 0 && heard + cfg->resend_ticks > now;
}

// Whether `Replica::apply_acks` keeps a flight (0: acknowledged, unacknowledgeable or
// too old); `acked` is set if the player acknowledged it.
RFN int r_flight_kept(const RPlayer* p, const RFlight* fl, u64 floor, int* acked) {
    *acked = p->has_acks && r_ack_contains(p->ack_newest, p->ack_bits, fl->sequence);
    u64 behind = p->ack_newest > fl->sequence ? p->ack_newest - fl->sequence : 0;
    int unackable = p->has_acks && behind > R_ACK_BITS;
    return !(*acked || unackable || fl->tick < floor);
}

// Step 2 of `Replica::build` for one track (index `k`, candidate `cand`): its priority
// grows by its rate; if it is due, `due` describes it and 1 is returned.
// `fresh_link`: the player acknowledged a flight within `resend_ticks` (`r_fresh_link`).
RFN int r_priority(const RConfig* cfg, u64 now, u64 floor, int fresh_link, RTrack* t, const RCand* c, u32 k, u32 cand,
                   RDue* due) {
    RBase acked = r_track_acked(t, floor);
    int has_sent = t->sent_tick != R_NONE;
    int holds = acked.valid && r_pos_eq(acked.pos, c->pos) && (!has_sent || r_pos_eq(t->sent, c->pos));
    u64 since = now > t->sent_tick ? now - t->sent_tick : 0;
    int sending = has_sent && r_pos_eq(t->sent, c->pos) && since < cfg->resend_ticks;
    int stopped = sending && t->sent_moved && c->distance <= cfg->near_units && t->sent_tick + 1 == now;
    float rate;
    if (stopped)
        rate = 1.0f;
    else if (holds)
        rate = 1.0f / fmaxf(cfg->refresh, 1.0f);
    else if (sending)
        rate = 0.0f;
    else if (!acked.valid && !has_sent)
        rate = 1.0f;
    else
        rate = 1.0f / r_bound_ticks(cfg, c->distance);
    t->priority += rate;
    int eager = 0;
    if (t->priority < 1.0f) {
        // Near and not held, before its bound: offered after everything due.
        if (holds || !(rate > 0.0f) || !(c->distance <= cfg->near_units)) return 0;
        if (!acked.valid || !fresh_link) return 0;
        eager = 1;
    }
    int starving = !eager && rate > 0.0f && t->priority / rate + R_WAIT_SLACK >= cfg->max_wait;
    int first = eager || c->distance <= cfg->near_units || !acked.valid;
    due->hi = r_rank_hi(eager, first, t->priority, c->distance);
    due->id = c->id;
    due->track = k;
    due->cand = cand;
    due->starving = (u32)starving;
    due->eager = (u32)eager;
    return 1;
}

// `Replica::apply_acks`: flights in order; an acknowledged one's states become
// baselines; acknowledged, unacknowledgeable and too old flights are dropped (their
// states stay in the arena until `r_push_flight` compacts it).
RFN void r_apply_acks(RHome* h, const RPlayer* p, u64 now, RTrack* tracks, u32 ntracks, RFlight* flights,
                      const RState* states) {
    u64 floor = now > R_MAX_BACK - 1 ? now - (R_MAX_BACK - 1) : 0;
    u32 kept = 0;
    for (u32 f = 0; f < h->nflights; f++) {
        RFlight fl = flights[f];
        int acked;
        int keep = r_flight_kept(p, &fl, floor, &acked);
        if (acked) {
            if (fl.tick + 1 > h->heard) h->heard = fl.tick + 1;
            for (u32 s = 0; s < fl.len; s++) r_ack_state(h, tracks, ntracks, &states[fl.start + s], fl.tick);
        }
        if (keep) flights[kept++] = fl;
    }
    h->nflights = kept;
}

// Appends a flight of `len` states (the caller writes them at the returned start):
// the oldest flights go first while the player holds `R_FLIGHTS` or the states would
// exceed `R_STATES`; the arena is compacted when the states do not fit at its end.
RFN u32 r_push_flight(RHome* h, RFlight* flights, RState* states, u64 sequence, u64 tick, u32 len) {
    u32 total = 0;
    for (u32 f = 0; f < h->nflights; f++) total += flights[f].len;
    u32 drop = 0;
    while (drop < h->nflights && (h->nflights - drop >= R_FLIGHTS || total + len > R_STATES)) {
        total -= flights[drop].len;
        drop++;
    }
    u32 end = 0;
    for (u32 f = drop; f < h->nflights; f++) {
        flights[f - drop] = flights[f];
    }
    h->nflights -= drop;
    if (h->nflights > 0) end = flights[h->nflights - 1].start + flights[h->nflights - 1].len;
    if (end + len > R_STATES) {
        // Compact: the flights' states are in arena order, so moving each down is safe.
        u32 at = 0;
        for (u32 f = 0; f < h->nflights; f++) {
            for (u32 s = 0; s < flights[f].len; s++) states[at + s] = states[flights[f].start + s];
            flights[f].start = at;
            at += flights[f].len;
        }
        end = at;
    }
    RFlight* nf = &flights[h->nflights++];
    nf->sequence = sequence;
    nf->tick = tick;
    nf->start = end;
    nf->len = len;
    return end;
}

// `Filling`.
typedef struct {
    float budget;
    u32 datagrams, max_datagrams, in_datagram, room;
    float per_datagram, keep;
} RFilling;

// `Filling::offer`: 0 not taken, 1 taken within the budget, 2 taken over it.
RFN int r_offer(RFilling* f, u32 bits, int starving, int eager) {
    float cost = (float)bits / 8.0f;
    float free = f->budget - (eager ? f->keep : 0.0f);
    int fits = cost <= free || starving;
    if (fits && f->in_datagram + bits > f->room) {
        fits = f->datagrams < f->max_datagrams && (cost + f->per_datagram <= free || starving);
        if (fits) {
            f->datagrams += 1;
            f->in_datagram = 0;
            f->budget -= f->per_datagram;
        }
    }
    if (!fits) return 0;
    int over = cost > f->budget;
    f->budget -= cost;
    f->in_datagram += bits;
    return over ? 2 : 1;
}

RFN float r_per_tick(const RConfig* c) {
    if (isnan(c->budget)) return 0.0f;
    return fmaxf(c->budget, 0.0f);
}

// The smallest a record is charged, bytes (`MIN_COST`: a `Same` record).
#define R_MIN_COST ((float)(3 + 7 + R_ID_CHARGE_BITS) / 8.0f)

// Offers `d`'s record to the budget; a record taken joins `chosen`.
RFN void r_take(RFilling* fill, const RDue* d, const RCand* cands, const RTrack* next, u64 now, u64 floor, RPos origin,
                RChosen* chosen, u32* nchosen, RInfo* info) {
    const RCand* c = &cands[d->cand];
    const RTrack* t = &next[d->track];
    RBase acked = r_track_acked(t, floor);
    RRecord rec = r_choose(c->id, c->kind, c->pos, now, acked, r_track_prior(t, acked));
    int taken = r_offer(fill, r_charge_bits(&rec, origin), (int)d->starving, (int)d->eager);
    if (taken) {
        info->starving += taken == 2;
        chosen[*nchosen].rec = rec;
        chosen[*nchosen].track = d->track;
        chosen[*nchosen].cand = d->cand;
        *nchosen += 1;
    } else {
        info->deferred += d->eager ? 0u : 1u;
    }
}

// This build's own object (`has_own`: whether there is one): a new own object starts a
// new track; its state goes into each of this build's flights.
RFN void r_own_now(RHome* h, int has_own, u64 own_id, RPos own_pos) {
    if (has_own && (!h->has_own || h->own.id != own_id)) {
        h->own = r_track_new(own_id, R_NO_SLOT);
        h->has_own = 1;
    }
    h->has_own_now = (u32)has_own;
    h->own_now_id = own_id;
    h->own_now = own_pos;
}

// A build's budget and datagrams before anything is offered (`Filling` as
// `Replica::build` makes it): this tick's budget and the credit, less the first
// datagram with the own record (`info->own_record` if `info->has_own_record`).
RFN RFilling r_filling_new(const RConfig* cfg, const RHome* h, const RInfo* info, RPos origin) {
    u32 own_bits = info->has_own_record ? r_charge_bits(&info->own_record, origin) : 0u;
    float per_tick = r_per_tick(cfg);
    RFilling fill;
    fill.per_datagram = (float)R_DATAGRAM_OVERHEAD + (float)own_bits / 8.0f;
    fill.budget = per_tick + h->credit - fill.per_datagram;
    fill.datagrams = 1;
    fill.max_datagrams = cfg->max_datagrams > 1 ? cfg->max_datagrams : 1;
    fill.in_datagram = 0;
    fill.room = (R_MAX_BODY - R_DELTA_HEADER_LEN - R_MAX_RECORD_LEN) * 8u - R_STREAM_PARAMS_BITS - own_bits;
    // An infinite budget keeps nothing back from eager records.
    fill.keep = isinf(per_tick) ? 0.0f : per_tick;
    return fill;
}

// Step 3 of `Replica::build`, on the objects due sorted by `r_due_less`: taken into
// the budget in that order while it can pay the smallest record, then only the
// starving, in their order. The chosen records are appended to `chosen` in the order
// taken (`*nchosen` of them); `info->datagrams` is set, `info->deferred` and
// `info->starving` count on. (The host takes the order a slice at a time and checks
// the budget between slices; the same objects are taken either way: an object offered
// when the budget cannot pay the smallest record is refused.)
RFN void r_take_sorted(const RConfig* cfg, u64 now, u64 floor, const RHome* h, RPos origin, const RCand* cands,
                       const RTrack* next, const RDue* wanted, u32 nwanted, RChosen* chosen, u32* nchosen,
                       RInfo* info) {
    RFilling fill = r_filling_new(cfg, h, info, origin);
    *nchosen = 0;
    u32 k = 0;
    for (; k < nwanted && fill.budget >= R_MIN_COST; k++)
        r_take(&fill, &wanted[k], cands, next, now, floor, origin, chosen, nchosen, info);
    for (; k < nwanted; k++) {
        if (wanted[k].starving)
            r_take(&fill, &wanted[k], cands, next, now, floor, origin, chosen, nchosen, info);
        else
            info->deferred += wanted[k].eager ? 0u : 1u;
    }
    info->datagrams = fill.datagrams;
}

// The chosen records sorted by `r_chosen_less` (ids increasing): a repeated id goes once
// (the first of it); `info->count` is what is left.
RFN void r_chosen_unique(RChosen* chosen, u32 nchosen, RInfo* info) {
    u32 unique = 0;
    for (u32 k = 0; k < nchosen; k++) {
        if (unique > 0 && chosen[unique - 1].rec.id == chosen[k].rec.id) continue;
        chosen[unique++] = chosen[k];
    }
    info->deferred += nchosen - unique;
    info->count = unique;
}

// Step 3 of `Replica::build`: the objects due (`wanted`, any order) taken into the
// budget in the order of urgency; `chosen[0 .. info->count]` (ids increasing) and
// `info->datagrams` are the result. `info->own_record` and `info->has_own_record` are
// set, and `info->deferred` and `info->starving` count on. (The device sorts with a
// warp where this sorts on one thread; the steps between the sorts are these.)
RFN void r_take_due(const RConfig* cfg, u64 now, u64 floor, const RHome* h, RPos origin, const RCand* cands,
                    const RTrack* next, RDue* wanted, u32 nwanted, RChosen* chosen, RInfo* info) {
    R_HEAPSORT(RDue, wanted, nwanted, r_due_less);
    u32 nchosen = 0;
    r_take_sorted(cfg, now, floor, h, origin, cands, next, wanted, nwanted, chosen, &nchosen, info);
    R_HEAPSORT(RChosen, chosen, nchosen, r_chosen_less);
    r_chosen_unique(chosen, nchosen, info);
}

// The first half of `Replica::build`, up to the records it sends: matches the view,
// applies acknowledgements, accumulates priorities and takes the objects due into the
// budget; `chosen[0 .. info->count]` (ids increasing) and `info` are the result. The
// caller packs and seals `info->own_record` and the chosen records into
// `info->datagrams` datagrams at most, then calls `r_commit`.
//
// Scratch, each for `ncands` items: `next`, `cand_of`, `un`, `moved`, `wanted`,
// `chosen`; `orph` for `nold`.
RFN void r_select(const RConfig* cfg, u64 now, RHome* h, const RPlayer* p, int has_own, u64 own_id, u32 own_kind,
                  RPos own_pos, RPos origin, const RCand* cands, u32 ncands, const RTrack* old, u32 nold,
                  RFlight* flights, RState* states, RTrack* next, u32* cand_of, RKey* un, RKey* orph,
                  RMoved* moved, RDue* wanted, RChosen* chosen, RInfo* info) {
    u64 floor = now > R_MAX_BACK - 1 ? now - (R_MAX_BACK - 1) : 0;
    info->deferred = 0;
    info->starving = 0;
    info->unsorted = 0;
    r_own_now(h, has_own, own_id, own_pos);
    u32 nmoved = 0;
    u32 n = r_match_view(has_own, own_id, cands, ncands, old, nold, next, cand_of, un, orph, moved, &nmoved,
                         &info->out_of_order);
    if (nmoved > 0) {
        for (u32 f = 0; f < h->nflights; f++) {
            for (u32 s = 0; s < flights[f].len; s++) {
                RState* st = &states[flights[f].start + s];
                for (u32 m = 0; m < nmoved; m++) {
                    if (moved[m].from == st->slot && moved[m].id == st->id) {
                        st->slot = moved[m].to;
                        break;
                    }
                }
            }
        }
    }
    r_apply_acks(h, p, now, next, n, flights, states);

    int has_own_record = has_own && h->has_own;
    if (has_own_record) {
        RBase acked = r_track_acked(&h->own, floor);
        info->own_record = r_choose(own_id, own_kind, own_pos, now, acked, r_track_prior(&h->own, acked));
    }
    info->has_own_record = (u32)has_own_record;
    info->in_view = n;

    u32 nwanted = 0;
    int fresh = r_fresh_link(cfg, h->heard, now);
    for (u32 k = 0; k < n; k++) {
        if (r_priority(cfg, now, floor, fresh, &next[k], &cands[cand_of[k]], k, cand_of[k], &wanted[nwanted])) nwanted++;
    }

    r_take_due(cfg, now, floor, h, origin, cands, next, wanted, nwanted, chosen, info);
}

// What the datagrams took: the credit left (never more than a tick's worth).
RFN void r_commit_credit(const RConfig* cfg, RHome* h, const RCommit* done) {
    float per_tick = r_per_tick(cfg);
    float credit = per_tick + h->credit - done->spent;
    if (credit < 0.0f) credit = 0.0f;
    if (credit > per_tick) credit = per_tick;
    h->credit = credit;
}

// A datagram of `records` records in flight, the own object's state first if there is
// one; returns where its states start.
RFN u32 r_commit_flight(RHome* h, RFlight* flights, RState* states, u64 sequence, u64 now, u32 records) {
    u32 own = h->has_own_now ? 1u : 0u;
    u32 at = r_push_flight(h, flights, states, sequence, now, own + records);
    if (own) {
        states[at].id = h->own_now_id;
        states[at].slot = R_NO_SLOT;
        states[at].pos = h->own_now;
    }
    return at;
}

// A record sent: its track marked sent, its state into its flight at `st`.
RFN void r_commit_record(u64 now, const RChosen* chosen, const RCand* cands, RTrack* next, RState* st) {
    const RCand* c = &cands[chosen->cand];
    RTrack* t = &next[chosen->track];
    t->sent_moved = (u8)(t->sent_tick != R_NONE && !r_pos_eq(t->sent, c->pos));
    t->sent_tick = now;
    t->sent = c->pos;
    t->priority = 0.0f;
    st->id = c->id;
    st->slot = c->slot;
    st->pos = c->pos;
}

// The second half of `Replica::build`: the credit left, and, if the datagrams were
// sealed, one flight for each (the own object's state and its records' states) and the
// sent records' tracks marked sent.
RFN void r_commit(const RConfig* cfg, u64 now, RHome* h, const RCommit* done, const u32* ends, const RChosen* chosen,
                  const RCand* cands, RTrack* next, RFlight* flights, RState* states) {
    r_commit_credit(cfg, h, done);
    if (!done->ok) return;
    u32 start = 0;
    for (u32 d = 0; d < done->datagrams; d++) {
        u32 end = ends[d];
        u32 at = r_commit_flight(h, flights, states, done->first + d, now, end - start);
        u32 own = h->has_own_now ? 1u : 0u;
        for (u32 k = start; k < end; k++) r_commit_record(now, &chosen[k], cands, next, &states[at + own + (k - start)]);
        start = end;
    }
}
