//! The reference's published results (docs/design.md, reference results), printed next
//! to ours.

/// Table 1 of the reference: physics ms per tick, `None` where it reported "-" (over a
/// second). Columns: CPU static, CPU dynamic, naive GPU static, naive GPU dynamic,
/// optimized GPU static, optimized GPU dynamic.
pub const TABLE1: [(&str, [Option<f64>; 6]); 3] = [
    ("1", [Some(396.5), Some(198.6), Some(5.1), Some(4.4), Some(0.2), Some(1.1)]),
    ("2", [None, None, Some(320.4), Some(175.3), Some(0.3), Some(2.1)]),
    ("3", [None, None, None, None, Some(2.2), Some(5.9)]),
];

/// Table 2 of the reference (optimized GPU): ms per stage, in the order of
/// [`STAGES`].
pub const TABLE2: [(&str, [f64; 9]); 3] = [
    ("1", [0.1, 0.8, 0.1, 0.2, 0.1, 0.1, 0.1, 1.1, 1.2]),
    ("2", [0.2, 0.7, 0.2, 1.2, 0.1, 0.2, 0.1, 1.8, 7.1]),
    ("3", [0.4, 1.4, 1.6, 3.9, 0.6, 0.6, 0.5, 10.5, 19.3]),
];

/// The stage names of Table 2, as our reports spell them: the server tick's stages up
/// to `send` (the server's list, which takes the physics stages from the backend).
pub const STAGES: &[&str] = myriad_server::STAGES.split_at(9).0;

/// The reference's machine.
pub const MACHINE: &str = "AMD Ryzen 9 5900X, NVIDIA GTX 1660";
