// Narrow phase and response: crates/physics/src/narrow/*.rs and response.rs, operation for
// operation. Shape kinds: 0 sphere, 1 box, 2 vertical capsule (compact form: half extents
// of the bounding box and a radius; a capsule's segment half length is half.y - radius).
#pragma once
#include "common.cuh"

struct Contact {
    V3 n;
    float depth;
};

__device__ __forceinline__ bool contact_sphere_sphere(V3 ca, float ra, V3 cb, float rb, Contact* c) {
    V3 d = vsub(cb, ca);
    float dist2 = vdot(d, d);
    float r = ra + rb;
    if (dist2 >= r * r) return false;
    float dist = sqrtf(dist2);
    c->n = dist > 0.0f ? v3(d.x / dist, d.y / dist, d.z / dist) : v3(0.0f, 1.0f, 0.0f);
    c->depth = r - dist;
    return true;
}

__device__ __forceinline__ float closest_height(float s0, float s1, float b0, float b1) {
    if (s0 > b1) return s0;
    if (s1 < b0) return s1;
    return (fmaxf(s0, b0) + fminf(s1, b1)) * 0.5f;
}

__device__ __forceinline__ bool segment_box(V3 c, float s0, float s1, float r, V3 bc, V3 bh,
                                            Contact* out) {
    V3 lo = vsub(bc, bh);
    V3 hi = vadd(bc, bh);
    V3 p = v3(c.x, closest_height(s0, s1, lo.y, hi.y), c.z);
    V3 q = v3(fminf(fmaxf(p.x, lo.x), hi.x), fminf(fmaxf(p.y, lo.y), hi.y),
              fminf(fmaxf(p.z, lo.z), hi.z));
    V3 d = vsub(q, p);
    float dist2 = vdot(d, d);
    if (dist2 > 0.0f) {
        if (dist2 >= r * r) return false;
        float dist = sqrtf(dist2);
        out->n = v3(d.x / dist, d.y / dist, d.z / dist);
        out->depth = r - dist;
        return true;
    }
    // The segment passes through the box: the shortest of six moves, ties to the first.
    float best = (p.x - lo.x) + r;
    V3 n = v3(1.0f, 0.0f, 0.0f);
    float w;
    w = (hi.x - p.x) + r;
    if (w < best) { best = w; n = v3(-1.0f, 0.0f, 0.0f); }
    w = (s1 - lo.y) + r;
    if (w < best) { best = w; n = v3(0.0f, 1.0f, 0.0f); }
    w = (hi.y - s0) + r;
    if (w < best) { best = w; n = v3(0.0f, -1.0f, 0.0f); }
    w = (p.z - lo.z) + r;
    if (w < best) { best = w; n = v3(0.0f, 0.0f, 1.0f); }
    w = (hi.z - p.z) + r;
    if (w < best) { best = w; n = v3(0.0f, 0.0f, -1.0f); }
    out->n = n;
    out->depth = best;
    return true;
}

__device__ __forceinline__ bool segment_segment(V3 ac, float a0, float a1, float ar, V3 bc, float b0,
                                                float b1, float br, Contact* out) {
    float ya, yb;
    if (a0 > b1) {
        ya = a0;
        yb = b1;
    } else if (a1 < b0) {
        ya = a1;
        yb = b0;
    } else {
        float m = (fmaxf(a0, b0) + fminf(a1, b1)) * 0.5f;
        ya = m;
        yb = m;
    }
    V3 pa = v3(ac.x, ya, ac.z);
    V3 pb = v3(bc.x, yb, bc.z);
    if (!contact_sphere_sphere(pa, ar, pb, br, out)) return false;
    if (pa.x == pb.x && pa.y == pb.y && pa.z == pb.z) {
        out->n = v3(0.0f, 1.0f, 0.0f);
        out->depth = (a1 - b0) + (ar + br);
    }
    return true;
}

__device__ __forceinline__ bool contact_box_box(V3 ac, V3 ah, V3 bc, V3 bh, Contact* out) {
    V3 d = vsub(bc, ac);
    float ox = (ah.x + bh.x) - fabsf(d.x);
    float oy = (ah.y + bh.y) - fabsf(d.y);
    float oz = (ah.z + bh.z) - fabsf(d.z);
    if (ox <= 0.0f || oy <= 0.0f || oz <= 0.0f) return false;
    if (ox <= oy && ox <= oz) {
        out->n = v3(d.x < 0.0f ? -1.0f : 1.0f, 0.0f, 0.0f);
        out->depth = ox;
    } else if (oy <= oz) {
        out->n = v3(0.0f, d.y < 0.0f ? -1.0f : 1.0f, 0.0f);
        out->depth = oy;
    } else {
        out->n = v3(0.0f, 0.0f, d.z < 0.0f ? -1.0f : 1.0f);
        out->depth = oz;
    }
    return true;
}

struct Body {
    u32 kind;
    V3 pos, half;
    float radius;
};

__device__ __forceinline__ bool flip(bool hit, Contact* c) {
    if (hit) c->n = vneg(c->n);
    return hit;
}

// narrow::contact: the normal points from a to b.
__device__ __forceinline__ bool contact(const Body& a, const Body& b, Contact* c) {
    float ahh = a.half.y - a.radius;
    float bhh = b.half.y - b.radius;
    switch (a.kind * 3 + b.kind) {
    case 0: return contact_sphere_sphere(a.pos, a.radius, b.pos, b.radius, c);
    case 1: return segment_box(a.pos, a.pos.y, a.pos.y, a.radius, b.pos, b.half, c);
    case 3: return flip(segment_box(b.pos, b.pos.y, b.pos.y, b.radius, a.pos, a.half, c), c);
    case 2:
        return segment_segment(a.pos, a.pos.y, a.pos.y, a.radius, b.pos, b.pos.y - bhh, b.pos.y + bhh,
                               b.radius, c);
    case 6:
        return flip(segment_segment(b.pos, b.pos.y, b.pos.y, b.radius, a.pos, a.pos.y - ahh,
                                    a.pos.y + ahh, a.radius, c),
                    c);
    case 4: return contact_box_box(a.pos, a.half, b.pos, b.half, c);
    case 5:
        return flip(segment_box(b.pos, b.pos.y - bhh, b.pos.y + bhh, b.radius, a.pos, a.half, c), c);
    case 7: return segment_box(a.pos, a.pos.y - ahh, a.pos.y + ahh, a.radius, b.pos, b.half, c);
    default:
        return segment_segment(a.pos, a.pos.y - ahh, a.pos.y + ahh, a.radius, b.pos, b.pos.y - bhh,
                               b.pos.y + bhh, b.radius, c);
    }
}

struct Response {
    V3 dx, dv;
    float normal_y;
};

// response::respond.
__device__ __forceinline__ bool respond(const Contact& c, V3 va, V3 vb, float share, const Params& k,
                                        Response* r) {
    V3 vrel = vsub(vb, va);
    float vn = vdot(vrel, c.n);
    if (vn > 0.0f) return false;
    float s = c.depth * share;
    float j = -(k.one_plus_e * vn) * share;
    r->dx = vscale(c.n, s);
    r->dv = vscale(c.n, j);
    r->normal_y = c.n.y;
    return true;
}
