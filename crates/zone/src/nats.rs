//! The fabric between processes: NATS core subjects, one per zone.
//!
//! Zone `z` of cluster `c` listens on `myriad.c.zone.z`; a border state for it is
//! published there. NATS delivers a publisher's messages in order and at most once;
//! loss (a slow consumer, a restarted server) shows as a stalled neighbour, which the
//! fault path handles, never as a wrong state. The client runs on its own small tokio
//! runtime, so a zone's tick stays a plain blocking loop.

use std::time::Instant;

use futures_util::StreamExt;

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::layout::ZoneId;

/// A zone's endpoint on a NATS server.
pub struct NatsFabric {
    rt: tokio::runtime::Runtime,
    client: async_nats::Client,
    sub: async_nats::Subscriber,
    cluster: String,
    max: usize,
    sent: u64,
    received: u64,
}

/// The subject zone `z` of `cluster` listens on.
pub fn zone_subject(cluster: &str, z: ZoneId) -> String {
    format!("myriad.{cluster}.zone.{}", z.0)
}

/// Checks a cluster name: letters, digits, `-` and `_`, so it is one subject token.
pub fn check_cluster_name(cluster: &str) -> Result<(), ZoneError> {
    let ok = !cluster.is_empty()
        && cluster.len() <= 64
        && cluster.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok { Ok(()) } else { Err(ZoneError::Layout(format!("cluster name {cluster:?}: use 1-64 of [A-Za-z0-9_-]"))) }
}

fn fabric_err(what: &str, e: impl std::fmt::Display) -> ZoneError {
    ZoneError::Fabric(format!("{what}: {e}"))
}

impl NatsFabric {
    /// Connects to `url` as zone `zone` of `cluster` and subscribes to its subject; when
    /// this returns, messages published to the zone are delivered.
    pub fn connect(url: &str, cluster: &str, zone: ZoneId) -> Result<NatsFabric, ZoneError> {
        check_cluster_name(cluster)?;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(|e| fabric_err("runtime", e))?;
        let name = format!("myriad-{cluster}-zone-{}", zone.0);
        let (client, sub) = rt.block_on(async {
            // The address is not logged: it may carry credentials.
            let client = async_nats::ConnectOptions::new()
                .name(name)
                .connect(url)
                .await
                .map_err(|e| fabric_err("connecting to NATS", e))?;
            let sub = client.subscribe(zone_subject(cluster, zone)).await.map_err(|e| fabric_err("subscribing", e))?;
            // The subscription is on the server once a flush returns.
            client.flush().await.map_err(|e| fabric_err("flushing", e))?;
            Ok::<_, ZoneError>((client, sub))
        })?;
        let max = client.server_info().max_payload;
        Ok(NatsFabric { rt, client, sub, cluster: cluster.to_string(), max, sent: 0, received: 0 })
    }

    /// The client, for other subjects of the same process (heartbeats, checkpoints).
    pub fn client(&self) -> &async_nats::Client {
        &self.client
    }
}

impl Fabric for NatsFabric {
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.sent += bytes.len() as u64;
        let subject = zone_subject(&self.cluster, to);
        self.rt.block_on(self.client.publish(subject, bytes.into())).map_err(|e| fabric_err("publishing", e))
    }

    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        let wait = deadline.saturating_duration_since(Instant::now());
        let sub = &mut self.sub;
        // The timer must be made inside the runtime.
        match self.rt.block_on(async { tokio::time::timeout(wait, sub.next()).await }) {
            Err(_) => Ok(None),
            Ok(Some(m)) => {
                self.received += m.payload.len() as u64;
                Ok(Some(m.payload.to_vec()))
            }
            Ok(None) => Err(ZoneError::Fabric("the NATS subscription ended".into())),
        }
    }

    fn max_message(&self) -> usize {
        self.max
    }

    fn bytes(&self) -> (u64, u64) {
        (self.sent, self.received)
    }
}
