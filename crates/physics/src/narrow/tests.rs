//! Hand-computed cases for each pair, then properties over random shapes.

use super::*;
use myriad_core::ShapeKind;
use proptest::prelude::*;

fn sphere(p: Vec3, r: f32) -> Body {
    Body { kind: ShapeKind::Sphere, pos: p, half: Vec3::splat(r), radius: r }
}
fn cuboid(p: Vec3, h: Vec3) -> Body {
    Body { kind: ShapeKind::Box, pos: p, half: h, radius: 0.0 }
}
fn capsule(p: Vec3, r: f32, hh: f32) -> Body {
    Body { kind: ShapeKind::Capsule, pos: p, half: Vec3::new(r, hh + r, r), radius: r }
}
fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}
fn close(c: Option<Contact>, normal: Vec3, depth: f32) {
    let c = c.expect("expected a contact");
    assert!((c.normal - normal).length() < 1e-5, "normal {} != {normal}", c.normal);
    assert!((c.depth - depth).abs() < 1e-5, "depth {} != {depth}", c.depth);
}

#[test]
fn sphere_sphere_cases() {
    // Overlapping along x by 0.5.
    close(contact(&sphere(v(0., 0., 0.), 1.), &sphere(v(1.5, 0., 0.), 1.)), Vec3::X, 0.5);
    // Touching is not a contact; separated neither.
    assert_eq!(contact(&sphere(v(0., 0., 0.), 1.), &sphere(v(2., 0., 0.), 1.)), None);
    assert_eq!(contact(&sphere(v(0., 0., 0.), 1.), &sphere(v(0., 5., 0.), 1.)), None);
    // One inside the other.
    close(contact(&sphere(v(0., 0., 0.), 3.), &sphere(v(0., 0., 1.), 0.5)), Vec3::Z, 2.5);
    // Equal centres: the fallback normal, full depth.
    close(contact(&sphere(v(4., 4., 4.), 1.), &sphere(v(4., 4., 4.), 2.)), FALLBACK_NORMAL, 3.0);
}

#[test]
fn sphere_box_cases() {
    let b = cuboid(v(0., 0., 0.), v(1., 1., 1.));
    // Sphere to the right of the box, overlapping by 0.25: normal from sphere to box = −x.
    close(contact(&sphere(v(1.25, 0., 0.), 0.5), &b), Vec3::NEG_X, 0.25);
    // Seen from the box the normal flips.
    close(contact(&b, &sphere(v(1.25, 0., 0.), 0.5)), Vec3::X, 0.25);
    // Touching and separated.
    assert_eq!(contact(&sphere(v(2., 0., 0.), 1.), &b), None);
    // Off a corner: the gap to (1, 1, 0) is 0.8·√2 ≈ 1.13 > 1.
    assert_eq!(contact(&sphere(v(1.8, 1.8, 0.), 1.), &b), None);
    // Near a corner: closest point (1,1,0), distance 0.5·√2.
    let d = 0.5f32 * 2f32.sqrt();
    close(contact(&sphere(v(1.5, 1.5, 0.), 1.), &b), v(-1., -1., 0.).normalize(), 1.0 - d);
    // Centre inside, nearest face +y at distance 0.2: the sphere leaves upwards, the
    // normal from sphere to box points down.
    close(contact(&sphere(v(0., 0.8, 0.), 0.5), &b), Vec3::NEG_Y, 0.7);
    // Centre exactly at the box centre: all faces tie, the first (−x face) wins.
    close(contact(&sphere(v(0., 0., 0.), 0.5), &b), Vec3::X, 1.5);
}

#[test]
fn sphere_capsule_cases() {
    let c = capsule(v(0., 0., 0.), 0.5, 1.0); // segment y ∈ [−1, 1]
    // Beside the segment.
    close(contact(&sphere(v(1.0, 0.5, 0.), 0.75), &c), Vec3::NEG_X, 0.25);
    // Above the top end: closest point (0,1,0).
    close(contact(&sphere(v(0., 2.0, 0.), 0.75), &c), Vec3::NEG_Y, 0.25);
    assert_eq!(contact(&sphere(v(0., 2.5, 0.), 1.0), &c), None);
    // Zero-height capsule behaves as a sphere.
    let ball = capsule(v(0., 0., 0.), 0.5, 0.0);
    close(contact(&ball, &sphere(v(0., 0., 0.9), 0.5)), Vec3::Z, 0.1);
    // Centre on the axis: the capsule is lifted until its bottom end clears the sphere:
    // (0.3 − (−1)) + (0.2 + 0.5).
    close(contact(&sphere(v(0., 0.3, 0.), 0.2), &c), FALLBACK_NORMAL, 2.0);
}

#[test]
fn box_box_cases() {
    let a = cuboid(v(0., 0., 0.), v(1., 1., 1.));
    // Resting on top with 0.1 overlap in y and full overlap in x, z.
    close(contact(&a, &cuboid(v(0.2, 1.9, 0.), v(1., 1., 1.))), Vec3::Y, 0.1);
    close(contact(&cuboid(v(0.2, 1.9, 0.), v(1., 1., 1.)), &a), Vec3::NEG_Y, 0.1);
    // Touching faces and separated.
    assert_eq!(contact(&a, &cuboid(v(2., 0., 0.), v(1., 1., 1.))), None);
    assert_eq!(contact(&a, &cuboid(v(0., 0., 3.), v(1., 1., 1.))), None);
    // One inside the other: least overlap on z (centre offset 0.5 → 1.5 + ... ).
    close(contact(&a, &cuboid(v(0., 0., 0.5), v(0.2, 0.9, 0.2))), Vec3::Z, 0.7);
    // Equal centres and sizes: ties go to x, positive.
    close(contact(&a, &a), Vec3::X, 2.0);
}

#[test]
fn box_capsule_cases() {
    let b = cuboid(v(0., 0., 0.), v(1., 1., 1.));
    // Capsule standing on the box: bottom end at y = 1.0 + 0.4 − ... segment [1.3, 2.3],
    // radius 0.5 → sphere at (0, 1.3, 0) penetrates the top face by 0.2.
    close(contact(&b, &capsule(v(0., 1.8, 0.), 0.5, 0.5)), Vec3::Y, 0.2);
    // Beside the box, y ranges overlapping: horizontal normal.
    close(contact(&b, &capsule(v(1.3, 0., 0.), 0.5, 2.0)), Vec3::X, 0.2);
    close(contact(&capsule(v(1.3, 0., 0.), 0.5, 2.0), &b), Vec3::NEG_X, 0.2);
    // Below the box.
    close(contact(&b, &capsule(v(0., -1.8, 0.), 0.5, 0.5)), Vec3::NEG_Y, 0.2);
    assert_eq!(contact(&b, &capsule(v(0., 3.0, 0.), 0.5, 0.5)), None);
    // A capsule through the middle of a flat box leaves sideways, not vertically: the
    // segment [−2, 2] is far longer than the box is thick.
    close(contact(&cuboid(v(0., 0., 0.), v(1., 0.1, 1.)), &capsule(v(0.6, 0., 0.), 0.5, 2.0)), Vec3::X, 0.9);
    // Zero-height capsule equals a sphere.
    assert_eq!(contact(&b, &capsule(v(1.2, 0.3, 0.1), 0.5, 0.0)), contact(&b, &sphere(v(1.2, 0.3, 0.1), 0.5)));
}

#[test]
fn capsule_capsule_cases() {
    let a = capsule(v(0., 0., 0.), 0.5, 1.0);
    // Side by side, overlapping ranges: horizontal.
    close(contact(&a, &capsule(v(0.8, 0.5, 0.), 0.5, 1.0)), Vec3::X, 0.2);
    // Stacked: a's top end (0,1,0), b's bottom end (0,1.8,0).
    close(contact(&a, &capsule(v(0., 2.8, 0.), 0.5, 1.0)), Vec3::Y, 0.2);
    close(contact(&capsule(v(0., 2.8, 0.), 0.5, 1.0), &a), Vec3::NEG_Y, 0.2);
    assert_eq!(contact(&a, &capsule(v(0., 3.0, 0.), 0.5, 1.0)), None);
    assert_eq!(contact(&a, &capsule(v(1.0, 0., 0.), 0.5, 1.0)), None);
    // Same axis, overlapping: b is lifted until its bottom end (0.5) clears a's top (1.0)
    // by the sum of the radii.
    close(contact(&a, &capsule(v(0., 0.5, 0.), 0.25, 0.0)), FALLBACK_NORMAL, 1.25);
}

/// Whether `p` lies strictly inside the body.
fn inside(b: &Body, p: Vec3) -> bool {
    match b.kind {
        ShapeKind::Sphere => (p - b.pos).length_squared() < b.radius * b.radius,
        ShapeKind::Box => ((p - b.pos).abs() - b.half).max_element() < 0.0,
        ShapeKind::Capsule => {
            let hh = b.half_height();
            let y = p.y.clamp(b.pos.y - hh, b.pos.y + hh);
            (p - Vec3::new(b.pos.x, y, b.pos.z)).length_squared() < b.radius * b.radius
        }
    }
}

/// A point inside both bodies on a 17³ grid over their common bounding box, if any.
fn common_point(a: &Body, b: &Body) -> Option<Vec3> {
    let lo = (a.pos - a.half).max(b.pos - b.half);
    let hi = (a.pos + a.half).min(b.pos + b.half);
    if lo.cmpgt(hi).any() {
        return None;
    }
    const N: usize = 17;
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                let t = Vec3::new(i as f32, j as f32, k as f32) / (N - 1) as f32;
                let p = lo + (hi - lo) * t;
                if inside(a, p) && inside(b, p) {
                    return Some(p);
                }
            }
        }
    }
    None
}

fn body() -> impl Strategy<Value = Body> {
    let p = (-2.0f32..2.0, -2.0f32..2.0, -2.0f32..2.0).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    (0u8..3, p, 0.1f32..1.5, 0.1f32..1.5, 0.1f32..1.5).prop_map(|(k, pos, a, b, c)| match k {
        0 => sphere(pos, a),
        1 => cuboid(pos, Vec3::new(a, b, c)),
        _ => capsule(pos, a, b - 0.1),
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(4000))]

    #[test]
    fn normals_are_unit_depths_positive_and_pairs_symmetric(a in body(), b in body()) {
        let ab = contact(&a, &b);
        let ba = contact(&b, &a);
        prop_assert_eq!(ab.is_some(), ba.is_some());
        if let (Some(ab), Some(ba)) = (ab, ba) {
            prop_assert!((ab.normal.length() - 1.0).abs() < 1e-5, "normal {}", ab.normal);
            prop_assert!(ab.depth > 0.0 && ab.depth.is_finite());
            prop_assert!((ab.depth - ba.depth).abs() <= 1e-5 * ab.depth.max(1.0));
            // Coinciding centres pick a fixed direction from either side; otherwise the
            // two views are exact opposites.
            if (a.pos - b.pos).abs().min_element() > 1e-3 {
                prop_assert!((ab.normal + ba.normal).length() < 1e-4, "{} vs {}", ab.normal, ba.normal);
            }
        }
    }

    #[test]
    fn agrees_with_sampled_overlap(a in body(), b in body()) {
        let c = contact(&a, &b);
        if let Some(p) = common_point(&a, &b) {
            prop_assert!(c.is_some(), "point {p} is inside both, but no contact");
        }
        if let Some(c) = c {
            // Moving b out along the normal by the depth (plus a hair) separates them.
            let moved = Body { pos: b.pos + c.normal * (c.depth + 1e-3), ..b };
            prop_assert!(common_point(&a, &moved).is_none(), "still overlapping after resolving {c:?}");
        }
    }
}
