//! Scripted actions: which action each object holds from which tick on.
//!
//! A script is the input side of a reproducible run. `myriad sim --actions FILE` applies
//! it directly to the world, and the server's scripted harness sends the same actions
//! as sealed datagrams through its real receive path; both must end in the same state
//! hash, which is how the server's tick is checked against the simulation's.
//!
//! # Text form
//!
//! One action per line, `TICK ENTITY MASK`, with `#` starting a comment:
//!
//! ```text
//! # tick entity mask
//! 0    12     forward
//! 30   12     right+jump
//! 45   12     0
//! ```
//!
//! `MASK` is a number from 0 to 31 (the bits of [`Action`]) or key names joined by `+`
//! (`forward`, `back`, `right`, `left`, `jump`; `none` for 0). The action is set just
//! before the step that starts at `TICK` (while `world.tick == TICK`) and is held until
//! the object's next line. Lines may come in any order; for the same tick and entity the
//! last line wins.

use std::fmt::Write as _;

use crate::action::Action;
use crate::world::{EntityId, ObjectKind, World};

/// One scripted action.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScriptedAction {
    /// The tick whose step first sees the action.
    pub tick: u64,
    /// The object that holds it.
    pub entity: EntityId,
    /// What it holds.
    pub action: Action,
}

/// A bad script line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("action script line {line}: {reason}")]
pub struct ScriptError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong with it.
    pub reason: String,
}

/// A scripted sequence of actions, sorted by tick (see the module docs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ActionScript {
    entries: Vec<ScriptedAction>,
}

const NAMES: [(&str, u8); 5] = [
    ("forward", Action::FORWARD),
    ("back", Action::BACK),
    ("right", Action::RIGHT),
    ("left", Action::LEFT),
    ("jump", Action::JUMP),
];

fn parse_mask(word: &str) -> Result<Action, String> {
    if let Ok(n) = word.parse::<u8>() {
        return Action::from_bits(n).ok_or_else(|| format!("mask {n} has bits above 4 (0 to 31)"));
    }
    if word == "none" {
        return Ok(Action::NONE);
    }
    let mut bits = 0;
    for name in word.split('+') {
        let (_, bit) = NAMES
            .iter()
            .find(|(n, _)| *n == name)
            .ok_or_else(|| format!("unknown key {name:?} (forward, back, right, left, jump, none)"))?;
        bits |= bit;
    }
    Ok(Action::from_bits_truncate(bits))
}

impl ActionScript {
    /// A script of `entries` (sorted here by tick; order within a tick is kept).
    pub fn new(mut entries: Vec<ScriptedAction>) -> Self {
        entries.sort_by_key(|e| e.tick);
        ActionScript { entries }
    }

    /// Parses the text form.
    pub fn parse(text: &str) -> Result<Self, ScriptError> {
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let bad = |reason: String| ScriptError { line: i + 1, reason };
            let words: Vec<&str> = line.split_whitespace().collect();
            let [tick, entity, mask] = words[..] else {
                return Err(bad(format!("expected `TICK ENTITY MASK`, found {line:?}")));
            };
            let tick = tick.parse().map_err(|_| bad(format!("tick {tick:?} is not a whole number")))?;
            let entity = EntityId(entity.parse().map_err(|_| bad(format!("entity {entity:?} is not an id")))?);
            let action = parse_mask(mask).map_err(bad)?;
            entries.push(ScriptedAction { tick, entity, action });
        }
        Ok(ActionScript::new(entries))
    }

    /// The text form ([`ActionScript::parse`] reads it back).
    pub fn to_text(&self) -> String {
        let mut s = String::from("# tick entity mask\n");
        for e in &self.entries {
            let _ = writeln!(s, "{} {} {}", e.tick, e.entity.0, e.action.bits());
        }
        s
    }

    /// Every action, by tick.
    pub fn entries(&self) -> &[ScriptedAction] {
        &self.entries
    }

    /// The actions of `tick`, in script order.
    pub fn at(&self, tick: u64) -> &[ScriptedAction] {
        let start = self.entries.partition_point(|e| e.tick < tick);
        let end = self.entries.partition_point(|e| e.tick <= tick);
        &self.entries[start..end]
    }

    /// The objects the script drives, ascending.
    pub fn entities(&self) -> Vec<EntityId> {
        let mut ids: Vec<EntityId> = self.entries.iter().map(|e| e.entity).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }

    /// Sets the actions of the world's current tick; returns how many were set. An
    /// object not in the world is an error: the script and the world disagree.
    pub fn apply(&self, world: &mut World) -> Result<usize, ScriptError> {
        let tick = world.tick;
        for e in self.at(tick) {
            if !world.dynamics.set_action(e.entity, e.action) {
                return Err(ScriptError {
                    line: 0,
                    reason: format!("entity {} of tick {tick} is not in the world", e.entity.0),
                });
            }
        }
        Ok(self.at(tick).len())
    }

    /// A test script: the first `users` user objects of `world` walk for `ticks` ticks,
    /// each changing direction (and sometimes jumping) at its own pseudo-random ticks,
    /// drawn from `seed`.
    pub fn walkers(world: &World, users: usize, ticks: u64, seed: u64) -> Self {
        let d = &world.dynamics;
        let ids = d.ids().iter().zip(d.kinds()).filter(|(_, k)| **k == ObjectKind::User).map(|(id, _)| *id);
        let mut entries = Vec::new();
        for (n, id) in ids.take(users).enumerate() {
            let mut tick = crate::rng::hash3(seed, n as u64, 0) % 5;
            let mut turn = 0u64;
            while tick < ticks {
                let h = crate::rng::hash3(seed, n as u64, turn + 1);
                let action = Action::from_bits_truncate((h & 0x1f) as u8);
                entries.push(ScriptedAction { tick, entity: id, action });
                tick += 5 + (h >> 32) % 40;
                turn += 1;
            }
        }
        ActionScript::new(entries)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_round_trip_and_lookup() {
        let s = ActionScript::parse("# header\n30 7 right+jump\n0 7 forward # start\n\n45 8 0\n").unwrap();
        assert_eq!(s.entries().len(), 3);
        assert_eq!(s.at(0), &[ScriptedAction { tick: 0, entity: EntityId(7), action: Action::from_bits_truncate(1) }]);
        assert_eq!(s.at(30)[0].action.bits(), Action::RIGHT | Action::JUMP);
        assert!(s.at(31).is_empty());
        assert_eq!(s.entities(), vec![EntityId(7), EntityId(8)]);
        assert_eq!(ActionScript::parse(&s.to_text()).unwrap(), s);
    }

    #[test]
    fn bad_lines_are_named() {
        for (text, needle) in [
            ("0 1", "expected"),
            ("x 1 0", "tick"),
            ("0 y 0", "entity"),
            ("0 1 32", "bits above 4"),
            ("0 1 forward+fly", "fly"),
        ] {
            let e = ActionScript::parse(&format!("# ok\n{text}\n")).unwrap_err();
            assert_eq!(e.line, 2, "{text}");
            assert!(e.reason.contains(needle), "{text}: {e}");
        }
    }
}
