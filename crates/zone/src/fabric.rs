//! The fabric: how a zone's messages reach other zones. [`NatsFabric`](crate::NatsFabric)
//! carries them between processes and machines; [`MemoryFabric`] between threads of one
//! process (tests, and `myriad sim --zones K` without `--nats`). Zones see only this
//! trait, so the zoned step is the same code on both.

use std::sync::{Arc, Mutex, mpsc};
use std::time::Instant;

use crate::error::ZoneError;
use crate::layout::ZoneId;

/// Delivers opaque messages to zones. Messages may be lost, repeated, reordered or forged
/// by what lies underneath; the zone authenticates and orders them itself.
pub trait Fabric: Send {
    /// Sends one message to zone `to`.
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError>;
    /// Sends one message of this zone's states to every gateway (a live zone's, after
    /// each step).
    fn publish_states(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError>;
    /// Sends one message of this zone's view to gateway `gateway` (states by interest:
    /// [`crate::views`]).
    fn send_view(&mut self, gateway: u16, bytes: Vec<u8>) -> Result<(), ZoneError>;
    /// The next message addressed to this zone, or `None` once `deadline` has passed.
    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError>;
    /// The largest message it carries, in bytes.
    fn max_message(&self) -> usize;
    /// Payload bytes sent and received so far.
    fn bytes(&self) -> (u64, u64);
}

/// Channels between threads of one process.
pub struct MemoryFabric {
    peers: Vec<mpsc::Sender<Vec<u8>>>,
    /// Where states and views go: the in-process gateways' inboxes, by gateway.
    gateways: Routes,
    inbox: mpsc::Receiver<Vec<u8>>,
    sent: u64,
    received: u64,
}

impl MemoryFabric {
    /// One fabric endpoint per zone, `0..n`, all connected.
    pub fn mesh(n: usize) -> Vec<MemoryFabric> {
        let (senders, receivers): (Vec<_>, Vec<_>) = (0..n).map(|_| mpsc::channel()).unzip();
        receivers
            .into_iter()
            .map(|inbox| MemoryFabric {
                peers: senders.clone(),
                gateways: Routes::default(),
                inbox,
                sent: 0,
                received: 0,
            })
            .collect()
    }

    /// [`MemoryFabric::mesh`] with a port where gateways attach, at any time.
    pub fn mesh_with_port(n: usize) -> (Vec<MemoryFabric>, GatewayPort) {
        let mut zones = MemoryFabric::mesh(n);
        let routes = Routes::default();
        for z in &mut zones {
            z.gateways = routes.clone();
        }
        let port = GatewayPort { zones: zones[0].peers.clone(), routes };
        (zones, port)
    }

    /// [`MemoryFabric::mesh`] with gateway `gateway` attached: the zones' states and
    /// views for it reach the returned [`MemoryGatewayLink`], whose intents and
    /// subscriptions reach every zone.
    pub fn mesh_with_gateway(n: usize, gateway: u16) -> (Vec<MemoryFabric>, MemoryGatewayLink) {
        let (zones, mut links) = MemoryFabric::mesh_with_gateways(n, &[gateway]);
        (zones, links.pop().expect("one gateway"))
    }

    /// [`MemoryFabric::mesh`] with the gateways `gateways` attached, one link each.
    pub fn mesh_with_gateways(n: usize, gateways: &[u16]) -> (Vec<MemoryFabric>, Vec<MemoryGatewayLink>) {
        let (zones, port) = MemoryFabric::mesh_with_port(n);
        (zones, gateways.iter().map(|&g| port.attach(g)).collect())
    }
}

/// The gateways' routes of an in-process cluster, shared by its zones.
type Routes = Arc<Mutex<Vec<(u16, mpsc::Sender<Vec<u8>>)>>>;

/// Where gateways attach to an in-process cluster ([`MemoryFabric::mesh_with_port`]).
pub struct GatewayPort {
    zones: Vec<mpsc::Sender<Vec<u8>>>,
    routes: Routes,
}

impl GatewayPort {
    /// A link for gateway `gateway`, receiving the zones' states and its views from now
    /// on; a gateway of the same number attached before (a restarted gateway's earlier
    /// self) hears nothing more.
    pub fn attach(&self, gateway: u16) -> MemoryGatewayLink {
        let (states, inbox) = mpsc::channel();
        let mut routes = self.routes.lock().expect("not poisoned");
        routes.retain(|(g, _)| *g != gateway);
        routes.push((gateway, states));
        MemoryGatewayLink { zones: self.zones.clone(), inbox }
    }
}

/// How a gateway reaches the zones: intents out to every zone, states in from all.
/// [`crate::nats::NatsGatewayLink`] between processes, [`MemoryGatewayLink`] in one.
pub trait GatewayLink: Send {
    /// Sends one message of intents to every zone.
    fn send_intents(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError>;
    /// Sends one subscription to every zone (states by interest).
    fn send_subscription(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError>;
    /// The next message of states or of a view for this gateway, or `None` once
    /// `deadline` has passed.
    fn recv_states(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError>;
    /// Waits (briefly) until what was sent has left this process: before it exits.
    fn flush(&mut self) {}
}

/// A gateway's side of [`MemoryFabric::mesh_with_gateway`].
pub struct MemoryGatewayLink {
    zones: Vec<mpsc::Sender<Vec<u8>>>,
    inbox: mpsc::Receiver<Vec<u8>>,
}

impl GatewayLink for MemoryGatewayLink {
    fn send_intents(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        for z in &self.zones {
            // A zone that has finished its run no longer listens.
            let _ = z.send(bytes.clone());
        }
        Ok(())
    }

    fn send_subscription(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        // The same way as intents: every zone hears it.
        self.send_intents(bytes)
    }

    fn recv_states(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        let wait = deadline.saturating_duration_since(Instant::now());
        match self.inbox.recv_timeout(wait) {
            Ok(b) => Ok(Some(b)),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(ZoneError::Fabric("every zone is gone".into())),
        }
    }
}

impl Fabric for MemoryFabric {
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError> {
        let peer = self.peers.get(to.0 as usize).ok_or_else(|| ZoneError::Fabric(format!("no zone {}", to.0)))?;
        self.sent += bytes.len() as u64;
        // A peer that has finished its run no longer listens; that is not this zone's error.
        let _ = peer.send(bytes);
        Ok(())
    }

    fn publish_states(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        let routes = self.gateways.lock().expect("not poisoned");
        for (_, g) in routes.iter() {
            // A gateway that has stopped no longer listens; that is not this zone's error.
            let _ = g.send(bytes.clone());
        }
        if !routes.is_empty() {
            self.sent += bytes.len() as u64;
        }
        Ok(())
    }

    fn send_view(&mut self, gateway: u16, bytes: Vec<u8>) -> Result<(), ZoneError> {
        let routes = self.gateways.lock().expect("not poisoned");
        if let Some((_, g)) = routes.iter().find(|(id, _)| *id == gateway) {
            self.sent += bytes.len() as u64;
            let _ = g.send(bytes);
        }
        Ok(())
    }

    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        let wait = deadline.saturating_duration_since(Instant::now());
        match self.inbox.recv_timeout(wait) {
            Ok(b) => {
                self.received += b.len() as u64;
                Ok(Some(b))
            }
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(ZoneError::Fabric("every sender is gone".into())),
        }
    }

    fn max_message(&self) -> usize {
        // The same limit as a default NATS server, so that splitting is exercised here too.
        1 << 20
    }

    fn bytes(&self) -> (u64, u64) {
        (self.sent, self.received)
    }
}
