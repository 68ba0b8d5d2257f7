//! The 5-bit action mask a player (or an NPC) holds: the reference's arrow keys and space.

use serde::{Deserialize, Serialize};

/// A set of held inputs. Bit 0 forward (+z), bit 1 back (−z), bit 2 right (+x),
/// bit 3 left (−x), bit 4 jump; the higher bits are always zero.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Action(u8);

impl Action {
    /// Move towards +z.
    pub const FORWARD: u8 = 1 << 0;
    /// Move towards −z.
    pub const BACK: u8 = 1 << 1;
    /// Move towards +x.
    pub const RIGHT: u8 = 1 << 2;
    /// Move towards −x.
    pub const LEFT: u8 = 1 << 3;
    /// Jump (only takes effect when standing on something).
    pub const JUMP: u8 = 1 << 4;
    /// Every valid bit.
    pub const ALL: u8 = 0b1_1111;
    /// No input held.
    pub const NONE: Action = Action(0);

    /// The action for a raw mask, or `None` if a bit above bit 4 is set.
    pub const fn from_bits(bits: u8) -> Option<Action> {
        if bits & !Self::ALL == 0 { Some(Action(bits)) } else { None }
    }

    /// The action for a raw mask with the invalid bits dropped.
    pub const fn from_bits_truncate(bits: u8) -> Action {
        Action(bits & Self::ALL)
    }

    /// The raw mask.
    pub const fn bits(self) -> u8 {
        self.0
    }

    /// Whether every bit of `flag` is held.
    pub const fn has(self, flag: u8) -> bool {
        self.0 & flag == flag
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_high_bits() {
        assert_eq!(Action::from_bits(0b10_0000), None);
        assert_eq!(Action::from_bits(0b1_0001).map(Action::bits), Some(0b1_0001));
        assert_eq!(Action::from_bits_truncate(0xff).bits(), Action::ALL);
        assert!(Action::from_bits_truncate(Action::JUMP | Action::LEFT).has(Action::JUMP));
    }
}
