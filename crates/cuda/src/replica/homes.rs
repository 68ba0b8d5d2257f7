//! Where each player's replica lives in the device arrays (its *home*), kept on the
//! host: a home per player key, its index reused once the player is forgotten, and each
//! build's placement (every player's home, whether it starts afresh, the homes of
//! players left out whose tracks are carried).
//!
//! The tick hands its players in the same order build after build (sessions change
//! rarely), so a player found at the place it had in the last build takes its home from
//! there, without a hash look-up: at 50,000 players the homes' bookkeeping, a look-up a
//! player and a pass over the map, took 1.3 ms a build (profiled on a lent H100's host).

/// One home's bookkeeping, by home index.
#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    /// The player's key (meaningful while `live`).
    key: u64,
    /// The build that last served it.
    seen: u64,
    /// Its tracks after that build.
    tracks: u32,
    /// Whether a player holds it (else it is in the free list).
    live: bool,
}

/// The homes of every player the device holds; see the module docs.
#[derive(Debug, Default)]
pub(super) struct Homes {
    /// By player key: a look-up for a player not found at its last place (the keys are
    /// the server's own session ids, not a peer's, so a fast hash).
    by_key: foldhash::HashMap<u64, u32>,
    slots: Vec<Slot>,
    free: Vec<u32>,
    /// The last build's players in order, `(key, home)`.
    last: Vec<(u64, u32)>,
    /// Scratch for the next `last`.
    next: Vec<(u64, u32)>,
}

/// A build's placement, its vectors kept from build to build.
#[derive(Debug, Default)]
pub(super) struct Placed {
    /// Each player's home, and whether it starts afresh.
    pub homes: Vec<(u32, bool)>,
    /// `(home, tracks)` of each player left out whose tracks move to this build's
    /// buffer, by home.
    pub carried: Vec<(u32, u32)>,
}

/// A key twice among one build's players.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Twice(pub u64);

impl Homes {
    /// Forgets every player: all start afresh.
    pub fn clear(&mut self) {
        self.by_key.clear();
        self.slots.clear();
        self.free.clear();
        self.last.clear();
    }

    /// Players held.
    pub fn len(&self) -> usize {
        self.by_key.len()
    }

    /// Home indices in use or free: what the device arrays must hold.
    pub fn span(&self) -> usize {
        self.slots.len()
    }

    /// Notes the tracks `home`'s player has after this build.
    pub fn set_tracks(&mut self, home: u32, tracks: u32) {
        self.slots[home as usize].tracks = tracks;
    }

    /// Build `build`'s placement of the players `keys` (in order) into `out`; players
    /// left out for more than `forget_after` builds are forgotten, their homes freed.
    /// A key twice is an error, after which nothing here is to be trusted (`clear`).
    pub fn place(
        &mut self,
        keys: impl ExactSizeIterator<Item = u64>,
        build: u64,
        forget_after: u64,
        out: &mut Placed,
    ) -> Result<(), Twice> {
        out.homes.clear();
        out.carried.clear();
        self.next.clear();
        let players = keys.len();
        for (i, key) in keys.enumerate() {
            let known = match self.last.get(i) {
                Some(&(k, home)) if k == key => Some(home),
                _ => self.by_key.get(&key).copied(),
            };
            let (home, fresh) = match known {
                Some(home) => {
                    let slot = &mut self.slots[home as usize];
                    if slot.seen == build {
                        return Err(Twice(key));
                    }
                    slot.seen = build;
                    (home, false)
                }
                None => {
                    let home = self.free.pop().unwrap_or(self.slots.len() as u32);
                    if home as usize == self.slots.len() {
                        self.slots.push(Slot::default());
                    }
                    self.slots[home as usize] = Slot { key, seen: build, tracks: 0, live: true };
                    self.by_key.insert(key, home);
                    (home, true)
                }
            };
            out.homes.push((home, fresh));
            self.next.push((key, home));
        }
        std::mem::swap(&mut self.last, &mut self.next);
        // Every player of this build holds a distinct live home: when they are all the
        // live homes, nobody was left out.
        if self.by_key.len() > players {
            for (home, slot) in self.slots.iter_mut().enumerate() {
                if !slot.live || slot.seen == build {
                    continue;
                }
                if build - slot.seen > forget_after {
                    self.by_key.remove(&slot.key);
                    slot.live = false;
                    self.free.push(home as u32);
                } else if slot.tracks > 0 {
                    out.carried.push((home as u32, slot.tracks));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn place(h: &mut Homes, keys: &[u64], build: u64, out: &mut Placed) -> Result<(), Twice> {
        h.place(keys.iter().copied(), build, 2, out)
    }

    #[test]
    fn players_keep_their_homes_in_any_order() {
        let (mut h, mut out) = (Homes::default(), Placed::default());
        place(&mut h, &[10, 20, 30], 1, &mut out).unwrap();
        assert_eq!(out.homes, [(0, true), (1, true), (2, true)]);
        // The same order: the same homes, none fresh.
        place(&mut h, &[10, 20, 30], 2, &mut out).unwrap();
        assert_eq!(out.homes, [(0, false), (1, false), (2, false)]);
        // Shuffled, with a newcomer: found by key.
        place(&mut h, &[30, 40, 10, 20], 3, &mut out).unwrap();
        assert_eq!(out.homes, [(2, false), (3, true), (0, false), (1, false)]);
        assert_eq!((h.len(), h.span()), (4, 4));
        assert!(out.carried.is_empty());
    }

    #[test]
    fn players_left_out_are_carried_then_forgotten() {
        let (mut h, mut out) = (Homes::default(), Placed::default());
        place(&mut h, &[1, 2, 3], 1, &mut out).unwrap();
        for (home, tracks) in [(0, 5), (1, 0), (2, 7)] {
            h.set_tracks(home, tracks);
        }
        // 1 and 3 left out: their tracks are carried, by home; 2 has none to carry.
        place(&mut h, &[2], 2, &mut out).unwrap();
        assert_eq!(out.homes, [(1, false)]);
        assert_eq!(out.carried, [(0, 5), (2, 7)]);
        place(&mut h, &[2], 3, &mut out).unwrap();
        assert_eq!(out.carried, [(0, 5), (2, 7)]);
        // Left out for more than two builds: forgotten, their homes free for newcomers,
        // and a forgotten player who comes back starts afresh.
        place(&mut h, &[2], 4, &mut out).unwrap();
        assert!(out.carried.is_empty());
        assert_eq!(h.len(), 1);
        place(&mut h, &[2, 9, 1], 5, &mut out).unwrap();
        let fresh: Vec<bool> = out.homes.iter().map(|&(_, f)| f).collect();
        assert_eq!(fresh, [false, true, true]);
        assert_eq!(h.span(), 3, "the freed homes were reused");
        let mut homes: Vec<u32> = out.homes.iter().map(|&(home, _)| home).collect();
        homes.sort_unstable();
        assert_eq!(homes, [0, 1, 2]);
    }

    #[test]
    fn a_player_twice_in_a_build_is_refused() {
        let (mut h, mut out) = (Homes::default(), Placed::default());
        assert_eq!(place(&mut h, &[5, 6, 5], 1, &mut out), Err(Twice(5)));
        h.clear();
        place(&mut h, &[5, 6], 2, &mut out).unwrap();
        // Twice at the places of the last build's first player, and by key.
        assert_eq!(place(&mut h, &[5, 5], 3, &mut out), Err(Twice(5)));
        h.clear();
        place(&mut h, &[5, 6], 4, &mut out).unwrap();
        assert_eq!(place(&mut h, &[6, 6], 5, &mut out), Err(Twice(6)));
    }
}
