// Narrow phase, the per-object gather of responses and the integration, one thread per
// dynamic object, as crates/physics/src/cpu/pipeline.rs:
// - narrow static: the object's static primitives by ascending index, each response
//   summed in that order into the object's accumulator;
// - narrow dynamic: the object's dynamic neighbours by ascending slot; the response of
//   pair (a, b), a < b, is computed exactly as the CPU computes it (contact(a, b), share
//   one half) by both objects, and added as `b` by b and as `a` by a. The CPU order
//   "statics by primitive, then dynamics by the other's slot" is kept exactly, with no
//   atomics on floats;
// - forces: NPC action, the summed response, gravity, friction, action, Verlet, limits.
#include "narrow.cuh"

__device__ __forceinline__ Body load_body(const float* pos, const float* half, const float* radius,
                                          const u8* shape, u32 i) {
    Body b;
    b.kind = shape[i];
    b.pos = load3(pos, i);
    b.half = load3(half, i);
    b.radius = radius[i];
    return b;
}

__device__ __forceinline__ V3 velocity(const float* pos, const float* prev, u32 i) {
    return vsub(load3(pos, i), load3(prev, i));
}

// acc: 6 floats an object (dx, dv); sup: the "supported" bit; counters[0]: contacts.
extern "C" __global__ void k_narrow_static(u32 n, const Params* kp, const float* pos,
                                           const float* prev, const float* half,
                                           const float* radius, const u8* shape,
                                           const float* spos, const float* shalf,
                                           const float* sradius, const u8* sshape,
                                           const u32* offsets, const u32* prims, u32 cap,
                                           float* acc, u8* sup, u32* counters) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    const Params k = *kp;
    Body me = load_body(pos, half, radius, shape, i);
    V3 v = velocity(pos, prev, i);
    V3 dx = v3(0.0f, 0.0f, 0.0f), dv = v3(0.0f, 0.0f, 0.0f);
    bool supported = false;
    u32 contacts = 0;
    // A list reaching past `cap` was not written: skip it (the host sees the total,
    // grows the buffer and redoes the step, discarding this one).
    u32 end = offsets[i + 1] <= cap ? offsets[i + 1] : offsets[i];
    for (u32 e = offsets[i]; e < end; e++) {
        u32 p = prims[e];
        Body s = load_body(spos, shalf, sradius, sshape, p);
        Contact c;
        Response r;
        if (!contact(s, me, &c)) continue;
        if (!respond(c, v3(0.0f, 0.0f, 0.0f), v, 1.0f, k, &r)) continue;
        contacts++;
        dx = vadd(dx, r.dx);
        dv = vadd(dv, r.dv);
        supported |= r.normal_y > k.support_min_y;
    }
    store3(acc, 2 * i, dx);
    store3(acc, 2 * i + 1, dv);
    sup[i] = supported;
    if (contacts) atomicAdd(&counters[0], contacts);
}

extern "C" __global__ void k_narrow_dynamic(u32 n, const Params* kp, const float* pos,
                                            const float* prev, const float* half,
                                            const float* radius, const u8* shape,
                                            const u32* offsets, const u32* others, u32 cap,
                                            float* acc, u8* sup, u32* counters) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    const Params k = *kp;
    Body me = load_body(pos, half, radius, shape, i);
    V3 vme = velocity(pos, prev, i);
    V3 dx = load3(acc, 2 * i), dv = load3(acc, 2 * i + 1);
    bool supported = sup[i] != 0;
    u32 contacts = 0;
    u32 end = offsets[i + 1] <= cap ? offsets[i + 1] : offsets[i];
    for (u32 e = offsets[i]; e < end; e++) {
        u32 j = others[e];
        Body other = load_body(pos, half, radius, shape, j);
        V3 vo = velocity(pos, prev, j);
        Contact c;
        Response r;
        if (j > i) {
            // This object is `a` of pair (i, j).
            if (!contact(me, other, &c) || !respond(c, vme, vo, 0.5f, k, &r)) continue;
            contacts++;
            dx = vsub(dx, r.dx);
            dv = vsub(dv, r.dv);
            supported |= -r.normal_y > k.support_min_y;
        } else {
            // This object is `b` of pair (j, i).
            if (!contact(other, me, &c) || !respond(c, vo, vme, 0.5f, k, &r)) continue;
            dx = vadd(dx, r.dx);
            dv = vadd(dv, r.dv);
            supported |= r.normal_y > k.support_min_y;
        }
    }
    store3(acc, 2 * i, dx);
    store3(acc, 2 * i + 1, dv);
    sup[i] = supported;
    if (contacts) atomicAdd(&counters[1], contacts);
}

__constant__ u8 NPC_MOVES[9] = {0, 1, 2, 4, 8, 1 | 4, 1 | 8, 2 | 4, 2 | 8};

// `period` and `turn_phase` come from the host's NpcTurn::at(tick, period): an NPC turns
// at this tick when its own phase equals `turn_phase`.
extern "C" __global__ void k_forces(u32 n, const Params* kp, u64 seed, u64 tick, u32 period,
                                    u32 turn_phase, float* pos, float* prev, const float* half,
                                    const u8* kind, const u32* id, u8* action, u8* flags,
                                    const float* acc, const u8* sup,
                                    const unsigned short* samples) {
    u32 i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    const Params k = *kp;
    u8 act = action[i];
    if (kind[i] == 0) {
        // integrate::NpcTurn::action: Lemire's multiply-shift, no division.
        u32 phase = (u32)(((hash3(seed, id[i], ~0ull) >> 32) * (u64)period) >> 32);
        if (phase == turn_phase) {
            u64 r = hash3(seed, id[i], tick);
            act = NPC_MOVES[((r >> 32) * 9ull) >> 32] | ((r & 15) == 0 ? 16 : 0);
        }
    }
    V3 p = load3(pos, i), pv = load3(prev, i), h = load3(half, i);
    V3 dx = load3(acc, 2 * i), dv = load3(acc, 2 * i + 1);
    bool supported = sup[i] != 0;
    // Accum::apply.
    p = vadd(p, dx);
    pv = vadd(pv, vsub(dx, dv));
    // integrate::integrate.
    bool standing = (flags[i] & 1) != 0 || supported;
    V3 v = vsub(p, pv);
    float vx = v.x * k.air_keep, vy = v.y * k.air_keep, vz = v.z * k.air_keep;
    if (standing) {
        vx *= k.ground_keep;
        vz *= k.ground_keep;
        float ax = 0.0f, az = 0.0f;
        if (act & 4) ax += 1.0f;
        if (act & 8) ax -= 1.0f;
        if (act & 1) az += 1.0f;
        if (act & 2) az -= 1.0f;
        if (ax != 0.0f && az != 0.0f) {
            const float diagonal = __uint_as_float(0x3f3504f3u); // FRAC_1_SQRT_2 as f32
            ax *= diagonal;
            az *= diagonal;
        }
        vx += ax * k.move_accel;
        vz += az * k.move_accel;
        if (act & 16) vy = k.jump_velocity;
    }
    vy -= k.gravity_dt2;
    V3 old = p;
    p = v3(old.x + vx, old.y + vy, old.z + vz);
    pv = old;
    // integrate::enforce_limits.
    V3 lo = v3(k.bmin[0] + h.x, k.bmin[1] + h.y, k.bmin[2] + h.z);
    V3 hi = v3(k.bmax[0] - h.x, k.bmax[1] - h.y, k.bmax[2] - h.z);
    if (p.x < lo.x) {
        p.x = lo.x;
        pv.x = p.x;
    } else if (p.x > hi.x) {
        p.x = hi.x;
        pv.x = p.x;
    }
    if (p.z < lo.z) {
        p.z = lo.z;
        pv.z = p.z;
    } else if (p.z > hi.z) {
        p.z = hi.z;
        pv.z = p.z;
    }
    if (p.y > hi.y) {
        p.y = hi.y;
        pv.y = p.y;
    }
    float floor = fmaxf(height_at(k, samples, p.x, p.z) + h.y, lo.y);
    if (p.y < floor) {
        p.y = floor;
        pv.y = p.y;
    }
    u8 on_terrain = p.y <= floor + k.ground_tolerance ? 1 : 0;
    store3(pos, i, p);
    store3(prev, i, pv);
    action[i] = act;
    flags[i] = on_terrain | (supported ? 2 : 0);
}
