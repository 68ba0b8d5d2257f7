// Packing a player's chosen records into delta update bodies: `pack_deltas`
// (crates/protocol/src/delta.rs, protocol version 3) in C that compiles for the host
// (src/replica/host.c, whose test holds it to the Rust byte for byte) and for the device,
// where `k_replica_pack` (kernels/pack.cu) shares `r_pack`'s passes among a warp's lanes
// with the functions below (a record's bits, the writer, the header), and the GPU suite
// holds its bodies to the host's. The host only frames and seals the bodies.
//
// Every choice is the Rust one: the stream parameters (the usual back, the order of
// the id codes) from the same histograms and ties, the same greedy split into
// datagrams, the same bits in the same order, written as the Rust bit writer writes
// them (a 64-bit word at a time, little-endian; the tail's bytes only).
#pragma once

#include "replica.cuh"

// `DELTA_HEADER_LEN`'s fields: tick (8), dilation (2), origin (12), record count (2).
#define R_STREAM_AT R_DELTA_HEADER_LEN
// Each body's room in the output: `MAX_BODY` rounded up to 8 bytes, so that every body
// starts 8-aligned and its stream (at byte 24) takes whole aligned words.
#define R_BODY_STRIDE 1168u

// The bit writer (`BitWriter`): fields gathered in `word` from its low bit up.
typedef struct {
    u8* out;
    u32 flushed;
    u32 held;
    u64 word;
} RBits;

RFN void r_store64(u8* p, u64 v) {
#ifdef __CUDACC__
    *(u64*)p = v;  // 8-aligned: see R_BODY_STRIDE
#else
    memcpy(p, &v, 8);  // little-endian hosts only, as the device
#endif
}

RFN void r_put(RBits* w, u64 v, u32 n) {
    if (n == 0) return;
    v &= ~0ull >> (64 - n);
    w->word |= v << w->held;
    u32 total = w->held + n;
    if (total < 64) {
        w->held = total;
        return;
    }
    r_store64(w->out + w->flushed, w->word);
    w->flushed += 8;
    // The field's bits that did not fit start the next word (none: the word was empty).
    w->word = w->held == 0 ? 0 : v >> (64 - w->held);
    w->held = total - 64;
}

// Writes the held bits' bytes; returns the bytes written in all.
RFN u32 r_bits_finish(RBits* w) {
    u32 tail = (w->held + 7) / 8;
    for (u32 b = 0; b < tail; b++) w->out[w->flushed + b] = (u8)(w->word >> (8 * b));
    w->flushed += tail;
    w->word = 0;
    w->held = 0;
    return w->flushed;
}

// `w = v + 2^k` (65 bits): returns `n`, its top bit's index, and its bits below it in
// `low`.
RFN u32 r_eg_split(u64 v, u32 k, u64* low) {
    u64 s = v + (1ull << k);
    if (s < v) {
        // Carried out: w = 2^64 + s.
        *low = s;
        return 64;
    }
    u32 n = 63u - r_clz64(s);
    *low = s - (1ull << n);
    return n;
}

// `exp_golomb_bits`.
RFN u32 r_eg_bits(u64 v, u32 k) {
    u64 low;
    u32 n = r_eg_split(v, k, &low);
    return 2 * n - k + 1;
}

// `put_exp_golomb`: `n - k` zeros, a one, then the `n` low bits.
RFN void r_put_eg(RBits* w, u64 v, u32 k) {
    u64 low;
    u32 n = r_eg_split(v, k, &low);
    u32 zeros = n - k;
    if (zeros + 1 + n <= 64) {
        r_put(w, (1ull | low << 1) << zeros, zeros + 1 + n);
        return;
    }
    r_put(w, 0, zeros);
    r_put(w, 1, 1);
    r_put(w, low, n);
}

// `gap`: the first id whole, each later one less the previous and one (wrapping).
RFN u64 r_gap(int has_previous, u64 previous, u64 id) { return has_previous ? id - previous - 1 : id; }

// `StreamParams`.
typedef struct {
    u32 usual, k;
} RParams;

// The records with `pinned` (may be null) at `split`, as one sequence.
RFN const RRecord* r_packed_at(const RChosen* ch, const RRecord* pinned, u32 split, u32 j) {
    if (!pinned || j < split) return &ch[j].rec;
    return j == split ? pinned : &ch[j - 1].rec;
}

// `StreamParams::for_records` over the `n` records with the pinned one at `split`.
RFN RParams r_params(const RChosen* ch, u32 n, const RRecord* pinned, u32 split) {
    u32 backs[64], lengths[65];
    for (u32 b = 0; b < 64; b++) backs[b] = 0;
    for (u32 b = 0; b < 65; b++) lengths[b] = 0;
    u32 total = n + (pinned ? 1u : 0u);
    u64 previous = 0;
    for (u32 j = 0; j < total; j++) {
        const RRecord* r = r_packed_at(ch, pinned, split, j);
        u64 g = r_gap(j > 0, previous, r->id);
        previous = r->id;
        lengths[64 - r_clz64(g)]++;
        if (r->form != R_ABSOLUTE) backs[r->back & 63]++;
    }
    RParams p = {0, 0};
    u32 best = 0;
    // The most frequent back, the smallest of equals; none counted: 0.
    for (u32 b = 1; b < 64; b++) {
        if (backs[b] > best) {
            best = backs[b];
            p.usual = b;
        }
    }
    u32 longest = 0;
    for (u32 len = 0; len < 65; len++) {
        if (lengths[len] > 0) longest = len;
    }
    u64 least = ~0ull;
    u32 top = longest < 63 ? longest : 63;
    for (u32 k = 0; k <= top; k++) {
        u64 cost = 0;
        for (u32 len = 0; len <= longest; len++) {
            if (lengths[len] == 0) continue;
            u64 g = len == 0 ? 0 : 1ull << (len - 1);
            cost += (u64)lengths[len] * r_eg_bits(g, k);
        }
        if (cost < least) {
            least = cost;
            p.k = k;
        }
    }
    return p;
}

// A record's bits in the stream after `previous`; 0 for one no datagram carries.
RFN u32 r_stream_bits(const RRecord* r, int has_previous, u64 previous, RParams p, RPos origin) {
    u32 b = r_bits(r, origin, p.usual);
    return b == 0 ? 0 : r_eg_bits(r_gap(has_previous, previous, r->id), p.k) + b;
}

RFN void r_put_back(RBits* w, u32 back, RParams p) {
    if (back == p.usual) {
        r_put(w, 1, 1);
    } else {
        r_put(w, 0, 1);
        r_put(w, back, 6);
    }
}

RFN void r_put_delta(RBits* w, const int d[3]) {
    int c = r_class_of(0, d[0], d[1], d[2]);
    u32 width = r_delta_width(c < 0 ? 3u : (u32)c);
    r_put(w, (u64)(c < 0 ? 3 : c), 2);
    for (int a = 0; a < 3; a++) r_put(w, (u64)(long long)d[a], width);
}

// `DeltaRecord::write`.
RFN void r_put_record(RBits* w, const RRecord* r, int has_previous, u64 previous, RParams p, RPos origin) {
    r_put_eg(w, r_gap(has_previous, previous, r->id), p.k);
    switch (r->form) {
    case R_DELTA:
        r_put(w, 1, 1);
        r_put_back(w, r->back, p);
        r_put(w, 0, 1);
        r_put_delta(w, r->v);
        break;
    case R_PREDICTED:
        r_put(w, 1, 1);
        r_put_back(w, r->back, p);
        r_put(w, 1, 1);
        if (r->prior == r->back) {
            r_put(w, 1, 1);
        } else {
            r_put(w, 0, 1);
            r_put(w, r->prior, 6);
        }
        r_put_delta(w, r->v);
        break;
    case R_SAME:
        r_put(w, 4, 3);
        r_put_back(w, r->back, p);
        break;
    default: {
        long long o[3] = {(long long)r->v[0] - origin.x, (long long)r->v[1] - origin.y,
                          (long long)r->v[2] - origin.z};
        int c = r_class_of(1, o[0], o[1], o[2]);
        if (c >= 0) {
            r_put(w, 2, 2);
            r_put(w, r->kind, 2);
            r_put(w, (u64)c, 2);
            for (int a = 0; a < 3; a++) r_put(w, (u64)o[a], r_near_width((u32)c));
        } else {
            r_put(w, 0, 3);
            r_put(w, r->kind, 2);
            for (int a = 0; a < 3; a++) r_put(w, (u64)(u32)r->v[a], 32);
        }
    }
    }
}

// The delta update header (`write_delta_header`), little-endian, byte by byte.
RFN void r_put_header(u8* body, u64 tick, u32 dilation, RPos origin, u32 count) {
    for (u32 b = 0; b < 8; b++) body[b] = (u8)(tick >> (8 * b));
    body[8] = (u8)dilation;
    body[9] = (u8)(dilation >> 8);
    int o[3] = {origin.x, origin.y, origin.z};
    for (u32 a = 0; a < 3; a++) {
        for (u32 b = 0; b < 4; b++) body[10 + 4 * a + b] = (u8)((u32)o[a] >> (8 * b));
    }
    body[22] = (u8)count;
    body[23] = (u8)(count >> 8);
}

// What packing one player did.
typedef struct {
    // Records packed (a prefix of the chosen), and of them relative to a baseline (the
    // pinned record's counted once when relative).
    u32 packed, relative;
    // Datagrams made; each one's body length and where its records end.
    u32 datagrams;
    u32 pad;
} RPacked;

// `pack_deltas`: the `n` chosen records (ids increasing) and `pinned` (may be null) into
// at most `max_datagrams` bodies at `bodies + d * R_BODY_STRIDE`, each
// `R_DELTA_HEADER_LEN` bytes of header and the bit stream; `lens[d]` is each body's
// length and `ends[d]` where its records end (both `max_datagrams` long).
RFN RPacked r_pack(u64 tick, u32 dilation, RPos origin, const RRecord* pinned, const RChosen* ch, u32 n,
                   u32 max_datagrams, u8* bodies, u32* lens, u32* ends) {
    RPacked done = {0, 0, 0, 0};
    u32 split = 0;
    if (pinned) {
        while (split < n && ch[split].rec.id < pinned->id) split++;
    }
    RParams p = r_params(ch, n, pinned, split);
    if (pinned && pinned->form != R_ABSOLUTE) done.relative = 1;
    u32 pinned_bits = 0;
    if (pinned) {
        pinned_bits = r_stream_bits(pinned, 0, 0, p, origin);
        if (pinned_bits == 0) return done;
    }
    u32 room = (R_MAX_BODY - R_DELTA_HEADER_LEN) * 8u - R_STREAM_PARAMS_BITS - pinned_bits;
    u32 packed = 0, datagrams = 0;
    while ((packed < n || (pinned && datagrams == 0)) && datagrams < max_datagrams) {
        u32 used = 0, end = packed;
        int has_previous = 0;
        u64 previous = 0;
        while (end < n) {
            u32 bits = r_stream_bits(&ch[end].rec, has_previous, previous, p, origin);
            if (bits == 0 || used + bits > room) break;
            used += bits;
            previous = ch[end].rec.id;
            has_previous = 1;
            end++;
        }
        u8* body = bodies + (u64)datagrams * R_BODY_STRIDE;
        RBits w = {body + R_STREAM_AT, 0, 0, 0};
        r_put(&w, p.usual, 6);
        r_put(&w, p.k, 6);
        const RRecord* pinned_left = pinned;
        u32 count = 0;
        has_previous = 0;
        previous = 0;
        for (u32 j = packed; j < end; j++) {
            const RRecord* r = &ch[j].rec;
            if (pinned_left && pinned_left->id < r->id) {
                r_put_record(&w, pinned_left, has_previous, previous, p, origin);
                previous = pinned_left->id;
                has_previous = 1;
                count++;
                pinned_left = 0;
            }
            r_put_record(&w, r, has_previous, previous, p, origin);
            previous = r->id;
            has_previous = 1;
            count++;
            done.relative += r->form != R_ABSOLUTE;
        }
        if (pinned_left) {
            r_put_record(&w, pinned_left, has_previous, previous, p, origin);
            count++;
        }
        lens[datagrams] = R_STREAM_AT + r_bits_finish(&w);
        r_put_header(body, tick, dilation, origin, count);
        ends[datagrams] = end;
        datagrams++;
        if (end == packed) break;  // only the pinned record went in: never loop on it
        packed = end;
    }
    done.packed = packed;
    done.datagrams = datagrams;
    return done;
}
