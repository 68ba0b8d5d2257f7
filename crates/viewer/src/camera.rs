//! The third-person camera: behind the player (towards `-z`, since forward is `+z` and
//! movement is in world axes), above it, looking at a point over its head, and easing
//! towards that pose so 30 Hz position updates do not shake the picture.

/// A camera following the player, in world coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FollowCamera {
    /// Horizontal distance behind the player.
    pub distance: f32,
    /// Height of the eye above the player's centre.
    pub height: f32,
    /// Height of the looked-at point above the player's centre.
    pub look_height: f32,
    /// How fast the camera catches up, per second (1 − e^(−stiffness·dt) of the remaining
    /// gap is closed each frame).
    pub stiffness: f32,
    /// Lowest the eye may be above the terrain under it.
    pub min_clearance: f32,
    eye: Option<[f32; 3]>,
    target: [f32; 3],
}

impl Default for FollowCamera {
    fn default() -> Self {
        FollowCamera {
            distance: 9.0,
            height: 3.5,
            look_height: 1.5,
            stiffness: 8.0,
            min_clearance: 1.0,
            eye: None,
            target: [0.0; 3],
        }
    }
}

impl FollowCamera {
    /// Where the eye wants to be for a player at `player`, and the point it looks at.
    pub fn desired(&self, player: [f32; 3]) -> ([f32; 3], [f32; 3]) {
        let eye = [player[0], player[1] + self.height, player[2] - self.distance];
        let target = [player[0], player[1] + self.look_height, player[2]];
        (eye, target)
    }

    /// Moves towards the pose for `player` after `dt` seconds (the first call jumps
    /// there), keeping the eye `min_clearance` above `ground(x, z)`.
    pub fn update(&mut self, player: [f32; 3], dt: f32, ground: impl Fn(f32, f32) -> f32) -> ([f32; 3], [f32; 3]) {
        let (want_eye, want_target) = self.desired(player);
        let (mut eye, target) = match self.eye {
            None => (want_eye, want_target),
            Some(eye) => {
                let a = 1.0 - (-self.stiffness * dt.max(0.0)).exp();
                let step = |from: [f32; 3], to: [f32; 3]| std::array::from_fn(|k| from[k] + (to[k] - from[k]) * a);
                (step(eye, want_eye), step(self.target, want_target))
            }
        };
        eye[1] = eye[1].max(ground(eye[0], eye[2]) + self.min_clearance);
        self.eye = Some(eye);
        self.target = target;
        (eye, target)
    }

    /// The current eye, if the camera has been placed.
    pub fn eye(&self) -> Option<[f32; 3]> {
        self.eye
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_update_places_the_camera_behind_and_above() {
        let mut c = FollowCamera::default();
        let (eye, target) = c.update([100.0, 20.0, 50.0], 0.016, |_, _| 0.0);
        assert_eq!(eye, [100.0, 23.5, 41.0]);
        assert_eq!(target, [100.0, 21.5, 50.0]);
        assert_eq!(c.eye(), Some(eye));
    }

    #[test]
    fn follows_smoothly_and_converges() {
        let mut c = FollowCamera::default();
        c.update([0.0; 3], 0.016, |_, _| -100.0);
        // The player jumps 10 units forward: one frame closes part of the gap, not all.
        let (eye, _) = c.update([0.0, 0.0, 10.0], 1.0 / 60.0, |_, _| -100.0);
        let gap = 1.0 - (eye[2] + 9.0) / 10.0;
        let expected = (-8.0f32 / 60.0).exp();
        assert!((gap - expected).abs() < 1e-4, "gap {gap}, expected {expected}");
        for _ in 0..120 {
            c.update([0.0, 0.0, 10.0], 1.0 / 60.0, |_, _| -100.0);
        }
        let eye = c.eye().unwrap();
        assert!((eye[2] - 1.0).abs() < 1e-3 && (eye[1] - 3.5).abs() < 1e-3, "{eye:?}");
    }

    #[test]
    fn never_below_the_ground() {
        let mut c = FollowCamera::default();
        // A hill behind the player, higher than the eye would be.
        let (eye, _) = c.update([0.0, 0.0, 0.0], 0.016, |_, z| if z < -5.0 { 30.0 } else { 0.0 });
        assert_eq!(eye[1], 31.0);
    }
}
