//! A pinned state hash: the same scenario, seed and tick count must give this exact world
//! on every machine and with every backend. If a change is *meant* to alter the physics,
//! update the value here with a note in the commit saying why; if it changes by
//! accident, something broke determinism (float operation order, a platform-dependent
//! function, iteration order).

use myriad_physics::conformance::golden_hash;
use myriad_physics::{BackendKind, create_cpu_backend};

/// [`myriad_physics::conformance::golden_world`], 120 ticks, default physics constants.
const GOLDEN: u64 = 0x3e25_4a7b_5870_977a;

#[test]
fn state_hash_matches_the_pinned_value_on_every_backend() {
    for kind in BackendKind::ALL {
        let hash = golden_hash(create_cpu_backend(kind).unwrap().as_mut());
        assert_eq!(hash, GOLDEN, "{kind}: {hash:#018x}");
    }
}
