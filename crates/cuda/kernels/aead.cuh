// ChaCha20-Poly1305 (RFC 8439) for sealing datagrams on the device: the same AEAD the
// host seals with through `ring` (crates/protocol/src/aead.rs), so the bytes on the wire
// do not depend on where a datagram was sealed (the GPU suite's `device_outbound` test
// compares them byte for byte). A warp seals one datagram: each lane makes one 64-byte
// ChaCha20 block of the keystream (lane 0 the block of counter 0, whose first 32 bytes are
// the Poly1305 key), then one lane runs Poly1305 over the associated data and the
// ciphertext, in 26-bit limbs (the "donna" formulation).
#pragma once
#include "common.cuh"

__device__ __forceinline__ u32 rotl32(u32 v, u32 n) { return (v << n) | (v >> (32 - n)); }

#define CHACHA_QR(a, b, c, d)                                                                      \
    a += b; d ^= a; d = rotl32(d, 16);                                                             \
    c += d; b ^= c; b = rotl32(b, 12);                                                             \
    a += b; d ^= a; d = rotl32(d, 8);                                                              \
    c += d; b ^= c; b = rotl32(b, 7);

// The ChaCha20 block of `key` (8 little-endian words), `counter` and `nonce` (3 words),
// as 16 little-endian words.
__device__ void chacha20_block(const u32 key[8], u32 counter, const u32 nonce[3], u32 out[16]) {
    u32 x[16] = {0x61707865u, 0x3320646eu, 0x79622d32u, 0x6b206574u, key[0], key[1], key[2], key[3],
                 key[4], key[5], key[6], key[7], counter, nonce[0], nonce[1], nonce[2]};
    u32 s[16];
#pragma unroll
    for (int i = 0; i < 16; i++) s[i] = x[i];
#pragma unroll
    for (int round = 0; round < 10; round++) {
        CHACHA_QR(x[0], x[4], x[8], x[12]);
        CHACHA_QR(x[1], x[5], x[9], x[13]);
        CHACHA_QR(x[2], x[6], x[10], x[14]);
        CHACHA_QR(x[3], x[7], x[11], x[15]);
        CHACHA_QR(x[0], x[5], x[10], x[15]);
        CHACHA_QR(x[1], x[6], x[11], x[12]);
        CHACHA_QR(x[2], x[7], x[8], x[13]);
        CHACHA_QR(x[3], x[4], x[9], x[14]);
    }
#pragma unroll
    for (int i = 0; i < 16; i++) out[i] = x[i] + s[i];
}

// Little-endian u32 from four bytes.
__device__ __forceinline__ u32 le32(const u8* p) {
    return (u32)p[0] | ((u32)p[1] << 8) | ((u32)p[2] << 16) | ((u32)p[3] << 24);
}

// Poly1305 state: the accumulator and the clamped key, in 26-bit limbs.
struct Poly1305 {
    u32 h[5], r[5], s[4];
    u32 pad[4];
};

// `key` is the 32-byte one-time key as 8 little-endian words (r, then s).
__device__ void poly1305_init(Poly1305* p, const u32 key[8]) {
    u32 t0 = key[0], t1 = key[1], t2 = key[2], t3 = key[3];
    // r &= 0x0ffffffc0ffffffc0ffffffc0fffffff, split into 26-bit limbs.
    p->r[0] = t0 & 0x3ffffff;
    p->r[1] = ((t0 >> 26) | (t1 << 6)) & 0x3ffff03;
    p->r[2] = ((t1 >> 20) | (t2 << 12)) & 0x3ffc0ff;
    p->r[3] = ((t2 >> 14) | (t3 << 18)) & 0x3f03fff;
    p->r[4] = (t3 >> 8) & 0x00fffff;
    for (int i = 1; i < 5; i++) p->s[i - 1] = p->r[i] * 5;
    for (int i = 0; i < 5; i++) p->h[i] = 0;
    for (int i = 0; i < 4; i++) p->pad[i] = key[4 + i];
}

// One full 16-byte block `m` (four little-endian words); every block of the AEAD's MAC
// input is full (its parts are padded to 16), so the high bit is always set.
__device__ void poly1305_block(Poly1305* p, u32 m0, u32 m1, u32 m2, u32 m3) {
    const u32 M = 0x3ffffff;
    u32 h0 = p->h[0] + (m0 & M);
    u32 h1 = p->h[1] + (((m0 >> 26) | (m1 << 6)) & M);
    u32 h2 = p->h[2] + (((m1 >> 20) | (m2 << 12)) & M);
    u32 h3 = p->h[3] + (((m2 >> 14) | (m3 << 18)) & M);
    u32 h4 = p->h[4] + ((m3 >> 8) | (1u << 24));
    u32 r0 = p->r[0], r1 = p->r[1], r2 = p->r[2], r3 = p->r[3], r4 = p->r[4];
    u32 s1 = p->s[0], s2 = p->s[1], s3 = p->s[2], s4 = p->s[3];
    u64 d0 = (u64)h0 * r0 + (u64)h1 * s4 + (u64)h2 * s3 + (u64)h3 * s2 + (u64)h4 * s1;
    u64 d1 = (u64)h0 * r1 + (u64)h1 * r0 + (u64)h2 * s4 + (u64)h3 * s3 + (u64)h4 * s2;
    u64 d2 = (u64)h0 * r2 + (u64)h1 * r1 + (u64)h2 * r0 + (u64)h3 * s4 + (u64)h4 * s3;
    u64 d3 = (u64)h0 * r3 + (u64)h1 * r2 + (u64)h2 * r1 + (u64)h3 * r0 + (u64)h4 * s4;
    u64 d4 = (u64)h0 * r4 + (u64)h1 * r3 + (u64)h2 * r2 + (u64)h3 * r1 + (u64)h4 * r0;
    u32 c = (u32)(d0 >> 26);
    h0 = (u32)d0 & M;
    d1 += c; c = (u32)(d1 >> 26); h1 = (u32)d1 & M;
    d2 += c; c = (u32)(d2 >> 26); h2 = (u32)d2 & M;
    d3 += c; c = (u32)(d3 >> 26); h3 = (u32)d3 & M;
    d4 += c; c = (u32)(d4 >> 26); h4 = (u32)d4 & M;
    h0 += c * 5; c = h0 >> 26; h0 &= M;
    h1 += c;
    p->h[0] = h0; p->h[1] = h1; p->h[2] = h2; p->h[3] = h3; p->h[4] = h4;
}

// The tag, as four little-endian words.
__device__ void poly1305_finish(Poly1305* p, u32 tag[4]) {
    const u32 M = 0x3ffffff;
    u32 h0 = p->h[0], h1 = p->h[1], h2 = p->h[2], h3 = p->h[3], h4 = p->h[4];
    u32 c = h1 >> 26; h1 &= M;
    h2 += c; c = h2 >> 26; h2 &= M;
    h3 += c; c = h3 >> 26; h3 &= M;
    h4 += c; c = h4 >> 26; h4 &= M;
    h0 += c * 5; c = h0 >> 26; h0 &= M;
    h1 += c;
    // h + -p: keep it when it does not borrow (h >= p).
    u32 g0 = h0 + 5; c = g0 >> 26; g0 &= M;
    u32 g1 = h1 + c; c = g1 >> 26; g1 &= M;
    u32 g2 = h2 + c; c = g2 >> 26; g2 &= M;
    u32 g3 = h3 + c; c = g3 >> 26; g3 &= M;
    u32 g4 = h4 + c - (1u << 26);
    u32 keep_g = (g4 >> 31) - 1;  // all ones when g4 did not go negative
    h0 = (h0 & ~keep_g) | (g0 & keep_g);
    h1 = (h1 & ~keep_g) | (g1 & keep_g);
    h2 = (h2 & ~keep_g) | (g2 & keep_g);
    h3 = (h3 & ~keep_g) | (g3 & keep_g);
    h4 = (h4 & ~keep_g) | (g4 & keep_g);
    // Back to 32-bit words, plus s, modulo 2^128.
    u32 w0 = h0 | (h1 << 26), w1 = (h1 >> 6) | (h2 << 20), w2 = (h2 >> 12) | (h3 << 14),
        w3 = (h3 >> 18) | (h4 << 8);
    u64 f = (u64)w0 + p->pad[0];
    tag[0] = (u32)f;
    f = (u64)w1 + p->pad[1] + (f >> 32);
    tag[1] = (u32)f;
    f = (u64)w2 + p->pad[2] + (f >> 32);
    tag[2] = (u32)f;
    f = (u64)w3 + p->pad[3] + (f >> 32);
    tag[3] = (u32)f;
}

// Poly1305 over `len` bytes at `p` zero-padded to a multiple of 16 (one part of the
// AEAD's MAC input).
__device__ void poly1305_padded(Poly1305* st, const u8* p, u32 len) {
    for (u32 at = 0; at < len; at += 16) {
        u8 b[16];
#pragma unroll
        for (int k = 0; k < 16; k++) b[k] = at + k < len ? p[at + k] : 0;
        poly1305_block(st, le32(b), le32(b + 4), le32(b + 8), le32(b + 12));
    }
}

// Seals the datagram at `buf` (in shared memory) with the calling warp: `buf[0..hlen]` is
// the associated data (the clear header), `buf[hlen..hlen + len]` the plaintext, which is
// encrypted in place; the tag goes to `buf[hlen + len..+16]`. `key` is the session key
// (8 words), `nonce` the 3-word nonce. Every lane of the warp must call it; at most 31
// blocks of plaintext (1,984 bytes).
__device__ void seal_warp(u8* buf, u32 hlen, u32 len, const u32 key[8], const u32 nonce[3]) {
    u32 lane = threadIdx.x % 32;
    u32 ks[16];
    u32 blocks = (len + 63) / 64;
    if (lane <= blocks) chacha20_block(key, lane, nonce, ks);
    if (lane >= 1 && lane <= blocks) {
        u8* text = buf + hlen + (lane - 1) * 64;
        u32 n = min(64u, len - (lane - 1) * 64);
        for (u32 k = 0; k < n; k++) text[k] ^= (u8)(ks[k / 4] >> (8 * (k % 4)));
    }
    __syncwarp();
    if (lane == 0) {
        Poly1305 st;
        poly1305_init(&st, ks);
        poly1305_padded(&st, buf, hlen);
        poly1305_padded(&st, buf + hlen, len);
        poly1305_block(&st, hlen, 0, len, 0);
        u32 tag[4];
        poly1305_finish(&st, tag);
        u8* out = buf + hlen + len;
        for (int k = 0; k < 16; k++) out[k] = (u8)(tag[k / 4] >> (8 * (k % 4)));
    }
    __syncwarp();
}
