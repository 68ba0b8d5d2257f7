//! The login's limits on failures and on work in flight: [`RateLimiter`] (failed
//! logins per address and per (account, address)) and [`InFlight`] (connections per
//! address, password checks per account); see the [module docs](super).

use std::collections::HashMap;
use std::hash::Hash;
use std::net::{IpAddr, Ipv6Addr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The key limits are counted under: an IPv4 address as is (an IPv4-mapped IPv6 one as
/// IPv4), an IPv6 address by its /64, the block one subscriber usually holds.
pub fn limit_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
    }
}

/// One (account, address)'s failures.
#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
}

/// Failed-login limits, checked before any password is hashed.
///
/// - Per **(account, address)**: after `per_account` failures the pair is locked for
///   1 s, and each further failure doubles the lock (2 s, 4 s, … up to the window).
///   The pair is forgotten two windows after its last failure, and at a success.
/// - Per **address**: `per_addr` failures within the window lock the address for every
///   account (one address guessing many accounts).
///
/// Nothing is counted per account alone: a stranger's failures never lock the owner out
/// from the owner's address. `docs/server.md` argues the choice.
#[derive(Debug)]
pub struct RateLimiter {
    window: Duration,
    per_addr: u32,
    per_account: u32,
    addrs: Mutex<HashMap<IpAddr, (u32, Instant)>>,
    pairs: Mutex<HashMap<(String, IpAddr), Failures>>,
}

/// Entries each table may hold before expired ones are swept.
const LIMITER_SWEEP: usize = 100_000;

impl RateLimiter {
    /// Allows `per_addr` failures per address per `window`, and `per_account` free
    /// failures per (account, address) before the backoff starts.
    pub fn new(window: Duration, per_addr: u32, per_account: u32) -> Self {
        Self { window, per_addr, per_account, addrs: Mutex::default(), pairs: Mutex::default() }
    }

    /// `Some(retry after)` if this address, or this account from this address, is
    /// locked out now.
    pub fn check(&self, addr: IpAddr, account: &str, now: Instant) -> Option<Duration> {
        let addr = limit_key(addr);
        let by_addr = {
            let map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
            map.get(&addr).and_then(|&(count, since)| {
                let age = now.saturating_duration_since(since);
                (count >= self.per_addr && age < self.window).then(|| self.window - age)
            })
        };
        let by_pair = {
            let map = self.pairs.lock().unwrap_or_else(|p| p.into_inner());
            map.get(&(account.to_ascii_lowercase(), addr)).and_then(|f| {
                let lock = self.lock_for(f.count)?;
                let age = now.saturating_duration_since(f.last);
                (age < lock).then(|| lock - age)
            })
        };
        by_addr.max(by_pair)
    }

    /// How long `count` failures lock their pair (none while under the free ones).
    fn lock_for(&self, count: u32) -> Option<Duration> {
        let over = count.checked_sub(self.per_account)?;
        let secs = 1u64.checked_shl(over.min(30)).unwrap_or(u64::MAX);
        Some(Duration::from_secs(secs).min(self.window))
    }

    /// Counts a failed login.
    pub fn failed(&self, addr: IpAddr, account: &str, now: Instant) {
        let addr = limit_key(addr);
        let window = self.window;
        {
            let mut map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
            // Bound the memory an attacker with many addresses can make us use.
            if map.len() > LIMITER_SWEEP {
                map.retain(|_, (_, since)| now.saturating_duration_since(*since) < window);
            }
            let entry = map.entry(addr).or_insert((0, now));
            if now.saturating_duration_since(entry.1) >= window {
                *entry = (0, now);
            }
            entry.0 += 1;
        }
        let mut map = self.pairs.lock().unwrap_or_else(|p| p.into_inner());
        if map.len() > LIMITER_SWEEP {
            map.retain(|_, f| now.saturating_duration_since(f.last) < window * 2);
        }
        let entry = map.entry((account.to_ascii_lowercase(), addr)).or_insert(Failures { count: 0, last: now });
        if now.saturating_duration_since(entry.last) >= window * 2 {
            entry.count = 0;
        }
        entry.count += 1;
        entry.last = now;
    }

    /// Failures counted against `addr` in the current window (the hashing queue's
    /// priority: fewer goes first).
    pub fn address_failures(&self, addr: IpAddr, now: Instant) -> u32 {
        let map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
        map.get(&limit_key(addr))
            .filter(|(_, since)| now.saturating_duration_since(*since) < self.window)
            .map_or(0, |(count, _)| *count)
    }

    /// A successful login clears the (account, address) pair (not the address's count:
    /// one address guessing many accounts must stay limited).
    pub fn succeeded(&self, addr: IpAddr, account: &str) {
        let key = (account.to_ascii_lowercase(), limit_key(addr));
        self.pairs.lock().unwrap_or_else(|p| p.into_inner()).remove(&key);
    }
}

/// Password checks of one account that may be queued or running at once; more are
/// refused with "busy" before any hashing.
pub(crate) const ACCOUNT_CHECKS_IN_FLIGHT: u32 = 2;

/// Things in flight per key (password checks per account, connections per address),
/// each counted by a slot that gives its place back on drop.
#[derive(Debug)]
pub(crate) struct InFlight<K> {
    counts: Mutex<HashMap<K, u32>>,
}

impl<K> Default for InFlight<K> {
    fn default() -> Self {
        InFlight { counts: Mutex::default() }
    }
}

/// One thing counted against its key; released on drop.
pub(crate) struct InFlightSlot<K: Eq + Hash> {
    owner: Arc<InFlight<K>>,
    key: K,
}

impl<K: Eq + Hash + Clone> InFlight<K> {
    /// A slot for one more under `key`, unless `cap` are in flight.
    fn take(self: &Arc<Self>, key: K, cap: u32) -> Option<InFlightSlot<K>> {
        let mut map = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        let n = map.entry(key.clone()).or_insert(0);
        if *n >= cap {
            return None;
        }
        *n += 1;
        Some(InFlightSlot { owner: self.clone(), key })
    }
}

impl<K: Eq + Hash> Drop for InFlightSlot<K> {
    fn drop(&mut self) {
        let mut map = self.owner.counts.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = map.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.key);
            }
        }
    }
}

/// Password checks in flight per (case-folded) account.
pub(crate) type AccountsInFlight = InFlight<String>;

impl AccountsInFlight {
    /// A slot for one more check of `account`, unless `cap` are in flight.
    pub fn try_take(self: &Arc<Self>, account: &str, cap: u32) -> Option<InFlightSlot<String>> {
        self.take(account.to_ascii_lowercase(), cap)
    }
}

/// Login connections in flight per client address (see [`limit_key`]).
pub(crate) type ConnectionCounts = InFlight<IpAddr>;

impl ConnectionCounts {
    /// A slot for one more connection from `ip`, unless it already holds `cap`.
    pub fn try_take(self: &Arc<Self>, ip: IpAddr, cap: u32) -> Option<InFlightSlot<IpAddr>> {
        self.take(limit_key(ip), cap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_strangers_failures_never_lock_the_owner_out() {
        let l = RateLimiter::new(Duration::from_secs(60), 20, 3);
        let t0 = Instant::now();
        let stranger: IpAddr = "10.0.0.1".parse().unwrap();
        let owner: IpAddr = "10.0.0.2".parse().unwrap();
        for _ in 0..3 {
            assert!(l.check(stranger, "bob", t0).is_none(), "locked only after the third");
            l.failed(stranger, "BOB", t0);
        }
        // Locked for the stranger (case-insensitive account)…
        assert!(l.check(stranger, "bob", t0).is_some());
        // …never for the owner, from an address with no failures.
        assert!(l.check(owner, "bob", t0).is_none());
        // Nor for the stranger on another account (only the per-address limit spans
        // accounts).
        assert!(l.check(stranger, "alice", t0).is_none());
    }

    #[test]
    fn backoff_doubles_and_is_capped_by_the_window() {
        let l = RateLimiter::new(Duration::from_secs(10), 100, 2);
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let mut t = Instant::now();
        l.failed(a, "bob", t);
        assert!(l.check(a, "bob", t).is_none(), "one failure is free");
        let mut locks = Vec::new();
        for _ in 0..6 {
            l.failed(a, "bob", t);
            let lock = l.check(a, "bob", t).expect("locked after a failure over the free ones");
            locks.push(lock.as_secs());
            t += lock;
            assert!(l.check(a, "bob", t).is_none(), "the lock ends");
        }
        assert_eq!(locks, [1, 2, 4, 8, 10, 10]);
        // A success clears the pair.
        l.failed(a, "bob", t);
        l.succeeded(a, "bob");
        assert!(l.check(a, "bob", t).is_none());
    }

    #[test]
    fn per_address_limit_spans_accounts_and_expires() {
        let l = RateLimiter::new(Duration::from_secs(60), 3, 100);
        let t0 = Instant::now();
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        for name in ["carol", "dave", "erin"] {
            l.failed(a, name, t0);
        }
        assert!(l.check(a, "zed", t0).is_some());
        l.succeeded(a, "carol");
        assert!(l.check(a, "zed", t0).is_some(), "a success does not clear the address");
        assert!(l.check("10.0.0.2".parse().unwrap(), "zed", t0).is_none());
        assert!(l.check(a, "zed", t0 + Duration::from_secs(61)).is_none());
    }

    #[test]
    fn ipv6_clients_are_keyed_by_their_64_and_mapped_v4_as_v4() {
        let a: IpAddr = "2001:db8:1:2:aaaa::1".parse().unwrap();
        let b: IpAddr = "2001:db8:1:2:bbbb::9".parse().unwrap();
        let c: IpAddr = "2001:db8:1:3::1".parse().unwrap();
        assert_eq!(limit_key(a), limit_key(b));
        assert_ne!(limit_key(a), limit_key(c));
        let mapped: IpAddr = "::ffff:10.1.2.3".parse().unwrap();
        assert_eq!(limit_key(mapped), "10.1.2.3".parse::<IpAddr>().unwrap());
    }

    #[test]
    fn connection_caps_are_per_address_and_released() {
        let accounts = Arc::new(AccountsInFlight::default());
        let two: Vec<_> = (0..2).map(|_| accounts.try_take("Bob", 2).unwrap()).collect();
        assert!(accounts.try_take("bob", 2).is_none(), "case-folded, capped");
        assert!(accounts.try_take("alice", 2).is_some());
        drop(two);
        assert!(accounts.try_take("BOB", 2).is_some());

        let counts = Arc::new(ConnectionCounts::default());
        let a: IpAddr = "127.0.0.1".parse().unwrap();
        let b: IpAddr = "127.0.0.2".parse().unwrap();
        let held: Vec<_> = (0..3).map(|_| counts.try_take(a, 3).unwrap()).collect();
        assert!(counts.try_take(a, 3).is_none(), "a's cap is full");
        assert!(counts.try_take(b, 3).is_some(), "b is not affected");
        drop(held);
        assert!(counts.try_take(a, 3).is_some(), "closing frees the slots");
    }
}
