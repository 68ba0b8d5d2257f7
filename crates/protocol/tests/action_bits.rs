//! The action bits exist twice: `myriad_core::Action` (what the simulation applies) and
//! [`ActionMask`] (what travels on the wire). The protocol does not depend on the world
//! model at run time, so the two definitions are pinned here instead: the server copies
//! the wire mask into the world bit for bit, and any drift would move players the wrong
//! way without an error.

use myriad_core::Action;
use myriad_protocol::ActionMask;

#[test]
fn every_action_bit_is_the_same_in_core_and_on_the_wire() {
    assert_eq!(ActionMask::FORWARD, Action::FORWARD, "FORWARD");
    assert_eq!(ActionMask::BACK, Action::BACK, "BACK");
    assert_eq!(ActionMask::RIGHT, Action::RIGHT, "RIGHT");
    assert_eq!(ActionMask::LEFT, Action::LEFT, "LEFT");
    assert_eq!(ActionMask::JUMP, Action::JUMP, "JUMP");
    assert_eq!(ActionMask::VALID, Action::ALL, "the valid-bits mask");
}

#[test]
fn every_byte_is_valid_in_both_or_in_neither() {
    for bits in 0..=u8::MAX {
        let wire = ActionMask::new(bits).map(ActionMask::bits);
        let core = Action::from_bits(bits).map(Action::bits);
        assert_eq!(wire, core, "mask {bits:#04x}");
    }
}
