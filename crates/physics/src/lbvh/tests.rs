//! The tree must find exactly what brute force finds, on every kind of input.

use super::*;
use myriad_core::Vec3;
use myriad_core::rng::Stream;

fn brute_pairs(boxes: &[Aabb]) -> Vec<u64> {
    let mut out = Vec::new();
    for i in 0..boxes.len() {
        for j in i + 1..boxes.len() {
            if boxes[i].overlaps(&boxes[j]) {
                out.push((i as u64) << 32 | j as u64);
            }
        }
    }
    out
}

fn tree_pairs(boxes: &[Aabb], bounds: &Aabb) -> Vec<u64> {
    let mut t = Lbvh::default();
    t.build(boxes, bounds);
    let mut out = Vec::new();
    t.self_pairs(&mut out);
    out.sort_unstable();
    out
}

fn random_boxes(seed: u64, n: usize, bounds: &Aabb, max_half: f32) -> Vec<Aabb> {
    let mut s = Stream::new(seed, 0);
    let size = bounds.size();
    (0..n)
        .map(|_| {
            let c = bounds.min + Vec3::new(s.unit(), s.unit(), s.unit()) * size;
            let h = Vec3::new(s.range(0.05, max_half), s.range(0.05, max_half), s.range(0.05, max_half));
            Aabb::from_center_half(c, h)
        })
        .collect()
}

#[test]
fn pairs_match_brute_force_on_random_boxes() {
    let bounds = Aabb::new(Vec3::new(-5000.0, -10.0, 2000.0), Vec3::new(-4900.0, 30.0, 2100.0));
    let boxes = random_boxes(1, 3000, &bounds, 2.0);
    let expected = brute_pairs(&boxes);
    assert!(expected.len() > 500, "the test needs many pairs, got {}", expected.len());
    assert_eq!(tree_pairs(&boxes, &bounds), expected);
}

#[test]
fn pairs_match_brute_force_with_duplicate_codes() {
    // 2,000 boxes on only 10 distinct centres: masses of identical Morton codes.
    let bounds = Aabb::new(Vec3::ZERO, Vec3::splat(100.0));
    let mut s = Stream::new(2, 0);
    let centres: Vec<Vec3> = (0..10).map(|_| Vec3::new(s.unit(), s.unit(), s.unit()) * 100.0).collect();
    let boxes: Vec<Aabb> =
        (0..2000).map(|i| Aabb::from_center_half(centres[i % 10], Vec3::splat(0.5 + (i % 3) as f32 * 0.1))).collect();
    let expected = brute_pairs(&boxes);
    assert!(expected.len() >= 10 * 199 * 200 / 2);
    assert_eq!(tree_pairs(&boxes, &bounds), expected);
    // All identical.
    let same = vec![Aabb::from_center_half(Vec3::splat(5.0), Vec3::ONE); 700];
    assert_eq!(tree_pairs(&same, &bounds).len(), 700 * 699 / 2);
}

#[test]
fn pairs_match_brute_force_on_a_clustered_crowd() {
    let bounds = Aabb::new(Vec3::ZERO, Vec3::splat(1024.0));
    let mut s = Stream::new(3, 0);
    let boxes: Vec<Aabb> = (0..4000)
        .map(|i| {
            let hub = Vec3::new(100.0 + 400.0 * (i % 3) as f32, 5.0, 500.0);
            let c = hub + Vec3::new(s.normalish(), s.normalish() * 0.2, s.normalish()) * 6.0;
            Aabb::from_center_half(c, Vec3::splat(0.5))
        })
        .collect();
    let expected = brute_pairs(&boxes);
    assert!(expected.len() > 10_000, "{} pairs", expected.len());
    assert_eq!(tree_pairs(&boxes, &bounds), expected);
}

#[test]
fn queries_match_brute_force_and_survive_refit() {
    let bounds = Aabb::new(Vec3::splat(-100.0), Vec3::splat(100.0));
    let mut boxes = random_boxes(4, 2000, &bounds, 3.0);
    let mut t = Lbvh::default();
    t.build(&boxes, &bounds);
    let queries = random_boxes(5, 200, &bounds, 30.0);
    let check = |t: &Lbvh, boxes: &[Aabb]| {
        for q in &queries {
            let mut got = Vec::new();
            t.query(q, |i| got.push(i));
            got.sort_unstable();
            let want: Vec<u32> = (0..boxes.len() as u32).filter(|&i| boxes[i as usize].overlaps(q)).collect();
            assert_eq!(got, want);
        }
    };
    check(&t, &boxes);
    // Move everything; refit keeps queries exact.
    for (i, b) in boxes.iter_mut().enumerate() {
        let shift = Vec3::new((i % 7) as f32 - 3.0, 0.5, -((i % 5) as f32));
        *b = Aabb::new(b.min + shift, b.max + shift);
    }
    t.refit(&boxes);
    check(&t, &boxes);
    let mut pairs = Vec::new();
    t.self_pairs(&mut pairs);
    pairs.sort_unstable();
    assert_eq!(pairs, brute_pairs(&boxes));
}

#[test]
fn tiny_trees() {
    let bounds = Aabb::new(Vec3::ZERO, Vec3::ONE);
    assert!(tree_pairs(&[], &bounds).is_empty());
    let one = [Aabb::from_center_half(Vec3::splat(0.5), Vec3::splat(0.1))];
    assert!(tree_pairs(&one, &bounds).is_empty());
    let mut t = Lbvh::default();
    t.build(&one, &bounds);
    let mut hits = Vec::new();
    t.query(&Aabb::new(Vec3::ZERO, Vec3::ONE), |i| hits.push(i));
    assert_eq!(hits, vec![0]);
    let two = [one[0], one[0]];
    assert_eq!(tree_pairs(&two, &bounds), vec![1]);
}

#[test]
fn objects_outside_the_bounds_are_still_found() {
    // Morton codes clamp to the edge; the boxes themselves are exact.
    let bounds = Aabb::new(Vec3::ZERO, Vec3::splat(10.0));
    let boxes = random_boxes(6, 500, &Aabb::new(Vec3::splat(-50.0), Vec3::splat(60.0)), 5.0);
    assert_eq!(tree_pairs(&boxes, &bounds), brute_pairs(&boxes));
}
