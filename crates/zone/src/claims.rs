//! Which gateway holds each account's session: a cluster-wide "second login replaces
//! the first".
//!
//! A gateway that admits a session publishes a signed claim (the account's name hashed,
//! the time, the gateway) on `myriad.c.sessions`; every gateway listens. A gateway that
//! holds a session of the same account, claimed earlier, ends it as `Replaced`. Claims
//! are ordered by (time, gateway), so two logins at once end with exactly one session
//! (given clocks within the time between two logins of one person).

use std::collections::HashMap;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use crate::error::ZoneError;
use crate::fabric_auth::NatsAuth;
use crate::nats::{NatsLink, check_cluster_name};
use crate::wire::{ClusterKey, Message, decode, encode_control};

/// The subject of the gateways' claims.
pub fn sessions_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.sessions")
}

/// An account's name as claims carry it: [`ClusterKey::digest64`] of the name in ASCII
/// lower case (names compare without case). Keyed, so that nobody outside the cluster
/// can pick an account name whose claim would end another account's session.
pub fn account_hash(key: &ClusterKey, name: &str) -> u64 {
    key.digest64(name.to_ascii_lowercase().as_bytes())
}

/// The claims of one gateway: its own, and what others' claims take from it.
#[derive(Debug)]
pub struct Claims {
    gateway: u16,
    key: ClusterKey,
    /// Our claims: account hash → (time, name).
    ours: HashMap<u64, (u64, String)>,
}

impl Claims {
    /// The claims of gateway `gateway` of the cluster whose key is `key`.
    pub fn new(gateway: u16, key: ClusterKey) -> Claims {
        Claims { gateway, key, ours: HashMap::new() }
    }

    /// Records a session of `name` admitted here at `time_ms`; returns the claim to send.
    pub fn claim(&mut self, name: &str, time_ms: u64) -> Message {
        let account = account_hash(&self.key, name);
        self.ours.insert(account, (time_ms, name.to_string()));
        Message::Claim { time_ms, account, gateway: self.gateway }
    }

    /// A claim heard on the subject: the name of our session it takes, if it is a newer
    /// claim of the same account by another gateway.
    pub fn heard(&mut self, m: &Message) -> Option<String> {
        let Message::Claim { time_ms, account, gateway } = *m else { return None };
        if gateway == self.gateway {
            return None;
        }
        let (ours, _) = self.ours.get(&account)?;
        if (time_ms, gateway) > (*ours, self.gateway) { self.ours.remove(&account).map(|(_, name)| name) } else { None }
    }
}

/// [`Claims`] over NATS: what a gateway's session registry (`myriad_server::registry`)
/// is made of.
pub struct NatsSessions {
    link: NatsLink,
    sub: async_nats::Subscriber,
    subject: String,
    key: ClusterKey,
    claims: Claims,
}

impl NatsSessions {
    /// Connects to `url` as gateway `gateway` of `cluster`, presenting `auth`, and
    /// listens for claims.
    pub fn connect(
        url: &str,
        cluster: &str,
        gateway: u16,
        key: ClusterKey,
        auth: &NatsAuth,
    ) -> Result<NatsSessions, ZoneError> {
        check_cluster_name(cluster)?;
        let link = NatsLink::connect(url, format!("myriad-{cluster}-gateway-{gateway}-sessions"), auth)?;
        let subject = sessions_subject(cluster);
        let sub = link.subscribe(subject.clone())?;
        Ok(NatsSessions { link, sub, subject, claims: Claims::new(gateway, key.clone()), key })
    }
}

impl NatsSessions {
    /// Claims the account `username` for a session admitted here.
    pub fn claim(&mut self, username: &str) {
        let now = SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0);
        let m = self.claims.claim(username, now);
        match encode_control(&self.key, &m).map_err(ZoneError::from) {
            Ok(bytes) => {
                if let Err(e) = self.link.publish(self.subject.clone(), bytes) {
                    // The session stays; only its exclusivity across gateways is lost.
                    tracing::warn!(error = %e, "a session claim was not published");
                    metrics::counter!("myriad_gateway_claim_errors_total").increment(1);
                }
            }
            Err(e) => tracing::error!(error = %e, "a session claim could not be encoded"),
        }
    }

    /// Accounts whose sessions here other gateways have claimed since; never blocks.
    pub fn taken(&mut self) -> Vec<String> {
        let mut taken = Vec::new();
        loop {
            match self.link.next_before(&mut self.sub, Instant::now()) {
                Ok(Some(bytes)) => match decode(&self.key, &bytes) {
                    Ok(m) => taken.extend(self.claims.heard(&m)),
                    Err(e) => {
                        metrics::counter!("myriad_gateway_rejected_total", "reason" => e.label()).increment(1);
                    }
                },
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!(error = %e, "reading session claims");
                    break;
                }
            }
        }
        taken
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_newer_claim_elsewhere_takes_the_session_an_older_one_does_not() {
        let key = ClusterKey::new(&[5; 32]).unwrap();
        let mut a = Claims::new(0, key.clone());
        let mut b = Claims::new(1, key);
        let mine = a.claim("Alice", 1_000);
        assert_eq!(b.heard(&mine), None, "b holds no session of alice");
        let theirs = b.claim("alice", 2_000);
        assert_eq!(a.heard(&theirs), Some("Alice".to_string()), "names compare without case");
        assert_eq!(b.heard(&mine), None, "an older claim takes nothing");
        assert_eq!(a.heard(&theirs), None, "taken once");
        // Two logins in the same millisecond: the higher gateway id wins, on both sides.
        let (x, y) = (a.claim("bob", 5_000), b.claim("bob", 5_000));
        assert_eq!(a.heard(&y), Some("bob".to_string()));
        assert_eq!(b.heard(&x), None);
        let own = a.claim("carol", 1);
        assert_eq!(a.heard(&own), None, "our own claims come back to us too");
    }

    #[test]
    fn account_hashes_fold_case_only() {
        let key = ClusterKey::new(&[5; 32]).unwrap();
        assert_eq!(account_hash(&key, "User1"), account_hash(&key, "user1"));
        assert_ne!(account_hash(&key, "user1"), account_hash(&key, "user2"));
    }
}
