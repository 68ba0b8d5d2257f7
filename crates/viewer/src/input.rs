//! Keys to the protocol's action mask: arrows move (up = forward `+z`, right = `+x`),
//! space jumps. WASD does the same for keyboards without arrows.

use myriad_protocol::ActionMask;
use three_d::Key;

/// The action bit a key drives, if any.
pub fn action_bit(key: Key) -> Option<u8> {
    Some(match key {
        Key::ArrowUp | Key::W => ActionMask::FORWARD,
        Key::ArrowDown | Key::S => ActionMask::BACK,
        Key::ArrowRight | Key::D => ActionMask::RIGHT,
        Key::ArrowLeft | Key::A => ActionMask::LEFT,
        Key::Space => ActionMask::JUMP,
        _ => return None,
    })
}

/// Which action keys are held, and the presses since the network thread last looked.
///
/// A press shorter than one tick would otherwise fall between two sends and be lost (a
/// tap of space is typically 50–100 ms, a tick 33 ms, but the key-up may come first):
/// presses are *latched* until [`HeldKeys::take_mask`] reports them once.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HeldKeys {
    held: u8,
    latched: u8,
}

impl HeldKeys {
    /// Records a key going down (`pressed`) or up; returns whether it is an action key.
    pub fn handle(&mut self, key: Key, pressed: bool) -> bool {
        let Some(bit) = action_bit(key) else { return false };
        if pressed {
            self.held |= bit;
            self.latched |= bit;
        } else {
            self.held &= !bit;
        }
        true
    }

    /// Releases every key (the window lost focus: key-ups will not arrive).
    pub fn release_all(&mut self) {
        self.held = 0;
    }

    /// The keys held now.
    pub fn held(&self) -> u8 {
        self.held
    }

    /// The mask to send: keys held now or pressed since the last call. Opposite
    /// directions held together cancel out, as they would on the server.
    pub fn take_mask(&mut self) -> u8 {
        let mut mask = self.held | self.latched;
        self.latched = 0;
        for (a, b) in [(ActionMask::FORWARD, ActionMask::BACK), (ActionMask::LEFT, ActionMask::RIGHT)] {
            if mask & (a | b) == a | b {
                mask &= !(a | b);
            }
        }
        mask
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrows_and_space_map_to_the_protocol_bits() {
        let mut k = HeldKeys::default();
        assert!(k.handle(Key::ArrowUp, true));
        assert!(k.handle(Key::ArrowRight, true));
        assert!(!k.handle(Key::Q, true));
        assert_eq!(k.take_mask(), ActionMask::FORWARD | ActionMask::RIGHT);
        assert_eq!(k.take_mask(), 0b0101, "held keys stay in the mask");
        k.handle(Key::ArrowUp, false);
        assert_eq!(k.take_mask(), ActionMask::RIGHT);
        assert_eq!(action_bit(Key::ArrowDown), Some(ActionMask::BACK));
        assert_eq!(action_bit(Key::ArrowLeft), Some(ActionMask::LEFT));
        assert!(ActionMask::new(ActionMask::FORWARD | ActionMask::BACK | ActionMask::JUMP).is_some());
    }

    #[test]
    fn a_short_jump_is_sent_once() {
        let mut k = HeldKeys::default();
        k.handle(Key::Space, true);
        k.handle(Key::Space, false);
        assert_eq!(k.held(), 0);
        assert_eq!(k.take_mask(), ActionMask::JUMP);
        assert_eq!(k.take_mask(), 0);
    }

    #[test]
    fn opposite_keys_cancel_and_focus_loss_releases() {
        let mut k = HeldKeys::default();
        k.handle(Key::ArrowLeft, true);
        k.handle(Key::ArrowRight, true);
        k.handle(Key::ArrowUp, true);
        assert_eq!(k.take_mask(), ActionMask::FORWARD);
        k.release_all();
        assert_eq!(k.take_mask(), 0);
    }
}
