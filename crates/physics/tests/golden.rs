//! A pinned state hash: the same scenario, seed and tick count must give this exact world
//! on every machine and with every backend. If a change is *meant* to alter the physics,
//! update the value here with a note in the commit saying why; if it changes by
//! accident, something broke determinism (float operation order, a platform-dependent
//! function, iteration order).

use myriad_core::{ScenarioSpec, Vec3};
use myriad_physics::{BackendKind, TickConstants, create_backend};

/// Scenario below, 120 ticks, default physics constants.
const GOLDEN: u64 = 0x3e25_4a7b_5870_977a;

#[test]
fn state_hash_matches_the_pinned_value_on_every_backend() {
    let mut spec = ScenarioSpec::custom(2024);
    spec.dynamic = 900;
    spec.users = 90;
    spec.static_objects = 120;
    spec.world_size = 80.0;
    spec.origin = Vec3::new(123.5, -7.0, -4096.0);
    spec.terrain_samples = 81;
    spec.max_height = 5.0;
    let start = spec.build().unwrap();
    let k = TickConstants::default();
    for kind in BackendKind::ALL {
        let mut w = start.clone();
        let mut b = create_backend(kind).unwrap();
        for _ in 0..120 {
            b.step(&mut w, &k).unwrap();
        }
        assert_eq!(w.state_hash(), GOLDEN, "{kind}: {:#018x}", w.state_hash());
    }
}
