//! The fabric between processes: NATS core subjects.
//!
//! Subjects of cluster `c` (all documented in `docs/zones.md`):
//! - `myriad.c.zone.<z>`: border states for zone `z`;
//! - `myriad.c.control`: the supervisor's halt and start, to every zone (and heard by
//!   the gateways, for the cuts a run starts from);
//! - `myriad.c.heartbeat.<z>`: zone `z`'s heartbeat, to the supervisor;
//! - `myriad.c.states`: every zone's owned objects after each step, to the gateways;
//! - `myriad.c.intents`: the gateways' players' joins, actions and leaves, to every zone;
//! - `myriad.c.cuts`: the supervisor's cut moves, to every zone (and heard by the
//!   gateways, for their operators' map of the cuts);
//! - `myriad.c.subscriptions`: the gateways' subscriptions (states by interest), to every
//!   zone;
//! - `myriad.c.view.<g>`: every zone's view for gateway `g` after each step.
//!
//! Who may publish and subscribe to each is [`crate::fabric_auth`]'s table; every
//! connection presents a [`NatsAuth`] (none: a server without auth).
//!
//! NATS delivers a publisher's messages in order and at most once; a loss (a slow
//! consumer, a restarted server) shows as a stalled neighbour, which the fault path
//! handles, never as a wrong state. The client runs on its own small tokio runtime, so a
//! zone's tick stays a plain blocking loop.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use futures_util::stream::SelectAll;

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::fabric_auth::{CA_ENV, CREDS_ENV, NatsAuth, PASSWORD_ENV, USER_ENV};
use crate::layout::ZoneId;
use crate::wire::{ClusterKey, Load, Message, ZoneState, encode_control};

/// How long [`NatsLink::echo`] waits for its probe.
const ECHO_WAIT: Duration = Duration::from_secs(10);

/// The subject zone `z` of `cluster` listens on.
pub fn zone_subject(cluster: &str, z: ZoneId) -> String {
    format!("myriad.{cluster}.zone.{}", z.0)
}

/// The subject of the supervisor's orders.
pub fn control_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.control")
}

/// The subject of zone `z`'s heartbeats: a subject per zone, so that the server's
/// permissions let only zone `z`'s user speak for it ([`crate::fabric_auth`]).
pub fn heartbeat_subject(cluster: &str, z: ZoneId) -> String {
    format!("myriad.{cluster}.heartbeat.{}", z.0)
}

/// Every zone's heartbeat subject, for the supervisor.
pub fn heartbeats_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.heartbeat.*")
}

/// The subject of the zones' states for the gateways.
pub fn states_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.states")
}

/// The subject of the gateways' intents for the zones.
pub fn intents_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.intents")
}

/// The subject of the supervisor's cut moves for the zones.
pub fn cuts_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.cuts")
}

/// The subject of the gateways' subscriptions for the zones.
pub fn subscriptions_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.subscriptions")
}

/// The subject of the zones' views for gateway `g`.
pub fn view_subject(cluster: &str, g: u16) -> String {
    format!("myriad.{cluster}.view.{g}")
}

/// Every gateway's view subject (the zones publish, the gateways subscribe, each to its
/// own).
pub fn views_subject(cluster: &str) -> String {
    format!("myriad.{cluster}.view.*")
}

/// Checks a cluster name: letters, digits, `-` and `_`, so it is one subject token.
pub fn check_cluster_name(cluster: &str) -> Result<(), ZoneError> {
    let ok = !cluster.is_empty()
        && cluster.len() <= 64
        && cluster.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok { Ok(()) } else { Err(ZoneError::Layout(format!("cluster name {cluster:?}: use 1-64 of [A-Za-z0-9_-]"))) }
}

pub(crate) fn fabric_err(what: &str, e: impl std::fmt::Display) -> ZoneError {
    ZoneError::Fabric(format!("{what}: {e}"))
}

/// A NATS connection on its own runtime.
pub struct NatsLink {
    /// The runtime the client's tasks run on.
    pub rt: Arc<tokio::runtime::Runtime>,
    /// The client.
    pub client: async_nats::Client,
    refusals: Arc<Mutex<Refusals>>,
}

/// The errors the server sent this connection (permissions violations above all): NATS
/// refuses a publish or subscribe it does not allow with an error *event*, never with a
/// failed publish.
#[derive(Debug, Default)]
struct Refusals {
    count: u64,
    /// The latest few, for diagnostics and tests.
    latest: VecDeque<String>,
}

impl NatsLink {
    /// Connects to `url` under the connection name `name`, presenting `auth`. The address
    /// is never logged: it may carry credentials. Every error the server reports later (a
    /// publish or subscribe the credentials do not allow) is logged, counted
    /// (`myriad_nats_server_errors_total`) and kept ([`NatsLink::server_errors`]).
    pub fn connect(url: &str, name: String, auth: &NatsAuth) -> Result<NatsLink, ZoneError> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(|e| fabric_err("runtime", e))?;
        let refusals = Arc::new(Mutex::new(Refusals::default()));
        let seen = refusals.clone();
        let options = auth.options(url).name(name).event_callback(move |event| {
            if let async_nats::Event::ServerError(e) = &event {
                tracing::warn!(error = %e, "the NATS server refused something");
                metrics::counter!("myriad_nats_server_errors_total").increment(1);
                let mut r = seen.lock().expect("not poisoned");
                r.count += 1;
                if r.latest.len() == 16 {
                    r.latest.pop_front();
                }
                r.latest.push_back(e.to_string());
            }
            async {}
        });
        let client = rt.block_on(options.connect(url)).map_err(|e| {
            use async_nats::ConnectErrorKind as K;
            match (e.kind(), auth.user_name()) {
                (K::AuthorizationViolation | K::Authentication, Some(user)) => ZoneError::Fabric(format!(
                    "NATS refused user {user:?}: wrong user or password ({USER_ENV}/{PASSWORD_ENV} or {CREDS_ENV})"
                )),
                (K::AuthorizationViolation | K::Authentication, None) => ZoneError::Fabric(format!(
                    "NATS wants credentials: set {USER_ENV} and {PASSWORD_ENV}, or {CREDS_ENV}"
                )),
                // A certificate the client does not trust comes back as an I/O error.
                (K::Tls, _) | (K::Io, _) if matches!(e.kind(), K::Tls) || e.to_string().contains("certificate") => {
                    fabric_err(&format!("TLS to NATS (is {CA_ENV} the server's authority?)"), e)
                }
                _ => fabric_err("connecting to NATS", e),
            }
        })?;
        Ok(NatsLink { rt: Arc::new(rt), client, refusals })
    }

    /// How many errors the server has reported on this connection, and the latest few
    /// (for example `nats: Permissions Violation for Publish to "myriad.c.zone.0"`).
    pub fn server_errors(&self) -> (u64, Vec<String>) {
        let r = self.refusals.lock().expect("not poisoned");
        (r.count, r.latest.iter().cloned().collect())
    }

    /// Waits until the server has answered everything sent so far (a round trip), so
    /// that any refusal of it has been reported.
    pub fn flush(&self) -> Result<(), ZoneError> {
        self.rt.block_on(self.client.flush()).map_err(|e| fabric_err("flushing", e))
    }

    /// Subscribes to `subject`. The subscription is written to the socket when this
    /// returns, not yet taken by the server: a message another connection publishes
    /// right after may still miss it. [`NatsLink::echo`] is the round trip that settles
    /// it.
    pub fn subscribe(&self, subject: String) -> Result<async_nats::Subscriber, ZoneError> {
        self.rt.block_on(async {
            let sub = self.client.subscribe(subject).await.map_err(|e| fabric_err("subscribing", e))?;
            self.client.flush().await.map_err(|e| fabric_err("flushing", e))?;
            Ok(sub)
        })
    }

    /// Publishes a probe on `subject`, which `stream` (this connection's subscriptions)
    /// receives, and waits for it to come back: the server takes a connection's
    /// operations in order, so every subscription made before is then in force. (A
    /// flush only writes to the socket; async-nats offers no PING round trip.) Messages
    /// that arrive before the probe are returned, in order, for the caller to take
    /// first.
    pub fn echo<S>(&self, subject: &str, stream: &mut S) -> Result<VecDeque<Vec<u8>>, ZoneError>
    where
        S: futures_util::Stream<Item = async_nats::Message> + Unpin,
    {
        let probe = format!("myriad-probe {}", self.client.new_inbox()).into_bytes();
        self.publish(subject.to_string(), probe.clone())?;
        let deadline = Instant::now() + ECHO_WAIT;
        let mut early = VecDeque::new();
        loop {
            match self.next_before(stream, deadline)? {
                Some(m) if m == probe => return Ok(early),
                Some(m) => early.push_back(m),
                None => {
                    return Err(ZoneError::Fabric(format!(
                        "NATS did not echo a probe on {subject} within {ECHO_WAIT:?} (may this user publish there?)"
                    )));
                }
            }
        }
    }

    /// The next message of `sub`'s stream, or `None` once `deadline` has passed.
    pub fn next_before<S>(&self, sub: &mut S, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError>
    where
        S: futures_util::Stream<Item = async_nats::Message> + Unpin,
    {
        let wait = deadline.saturating_duration_since(Instant::now());
        // The timer must be made inside the runtime.
        match self.rt.block_on(async { tokio::time::timeout(wait, sub.next()).await }) {
            Err(_) => Ok(None),
            Ok(Some(m)) => Ok(Some(m.payload.to_vec())),
            Ok(None) => Err(ZoneError::Fabric("the NATS subscription ended".into())),
        }
    }

    /// Publishes `bytes` on `subject`.
    pub fn publish(&self, subject: String, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.rt.block_on(self.client.publish(subject, bytes.into())).map_err(|e| fabric_err("publishing", e))
    }
}

/// What a zone's heartbeat says; the zone updates it, a task publishes it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Beat {
    /// The epoch.
    pub run: u64,
    /// The tick.
    pub tick: u64,
    /// The state.
    pub state: ZoneState,
    /// The zone's load and cuts.
    pub load: Load,
}

/// Publishes a zone's heartbeat every period until dropped.
pub struct Heartbeat {
    beat: Arc<Mutex<Beat>>,
    task: tokio::task::JoinHandle<()>,
}

impl Heartbeat {
    /// Changes what the next heartbeats say.
    pub fn set(&self, beat: Beat) {
        *self.beat.lock().expect("not poisoned") = beat;
    }
}

impl Drop for Heartbeat {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A zone's endpoint: its border subject, the control subject, the gateways' intents and
/// subscriptions, and the supervisor's cut moves, merged.
pub struct NatsFabric {
    link: NatsLink,
    sub: SelectAll<async_nats::Subscriber>,
    /// Messages that arrived before the probe of [`NatsFabric::connect`], taken first.
    early: VecDeque<Vec<u8>>,
    cluster: String,
    zone: ZoneId,
    max: usize,
    sent: u64,
    received: u64,
}

impl NatsFabric {
    /// Connects to `url` as zone `zone` of `cluster`, presenting `auth`, and subscribes
    /// to its subject, the control subject, the intents, cuts and subscriptions
    /// subjects; when this returns, messages published to them are delivered.
    pub fn connect(url: &str, cluster: &str, zone: ZoneId, auth: &NatsAuth) -> Result<NatsFabric, ZoneError> {
        check_cluster_name(cluster)?;
        let link = NatsLink::connect(url, format!("myriad-{cluster}-zone-{}", zone.0), auth)?;
        let borders = link.subscribe(zone_subject(cluster, zone))?;
        let control = link.subscribe(control_subject(cluster))?;
        let intents = link.subscribe(intents_subject(cluster))?;
        let cuts = link.subscribe(cuts_subject(cluster))?;
        let subscriptions = link.subscribe(subscriptions_subject(cluster))?;
        let max = link.client.server_info().max_payload;
        let mut sub = futures_util::stream::select_all([borders, control, intents, cuts, subscriptions]);
        // Until the server has taken the subscriptions, a neighbour's first borders can
        // miss them, and the zone waits for them for ever (`myriad sim --zones 4
        // --nats` stalled at tick 0 about one run in eight): a probe on the zone's own
        // border subject settles them.
        let early = link.echo(&zone_subject(cluster, zone), &mut sub)?;
        Ok(NatsFabric { link, sub, early, cluster: cluster.to_string(), zone, max, sent: 0, received: 0 })
    }

    /// The connection, for checkpoints.
    pub fn link(&self) -> &NatsLink {
        &self.link
    }

    /// Starts publishing this zone's heartbeat every `period`, signed with `key`.
    pub fn heartbeat(&self, key: ClusterKey, period: Duration) -> Heartbeat {
        let beat = Arc::new(Mutex::new(Beat { run: 0, tick: 0, state: ZoneState::Waiting, load: Load::default() }));
        let (b, client, zone) = (beat.clone(), self.link.client.clone(), self.zone);
        let subject = heartbeat_subject(&self.cluster, zone);
        let task = self.link.rt.spawn(async move {
            let mut every = tokio::time::interval(period);
            loop {
                every.tick().await;
                let Beat { run, tick, state, load } = *b.lock().expect("not poisoned");
                if let Ok(bytes) = encode_control(&key, &Message::Heartbeat { run, tick, zone, state, load }) {
                    // A lost heartbeat is what the supervisor's deadline is for.
                    let _ = client.publish(subject.clone(), bytes.into()).await;
                }
            }
        });
        Heartbeat { beat, task }
    }
}

impl Fabric for NatsFabric {
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.sent += bytes.len() as u64;
        self.link.publish(zone_subject(&self.cluster, to), bytes)
    }

    fn publish_states(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.sent += bytes.len() as u64;
        self.link.publish(states_subject(&self.cluster), bytes)
    }

    fn send_view(&mut self, gateway: u16, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.sent += bytes.len() as u64;
        self.link.publish(view_subject(&self.cluster, gateway), bytes)
    }

    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        let got = match self.early.pop_front() {
            Some(m) => Some(m),
            None => self.link.next_before(&mut self.sub, deadline)?,
        };
        self.received += got.as_ref().map_or(0, |b| b.len() as u64);
        Ok(got)
    }

    fn max_message(&self) -> usize {
        self.max
    }

    fn bytes(&self) -> (u64, u64) {
        (self.sent, self.received)
    }
}

/// A gateway's endpoint: intents and subscriptions out to every zone, the zones' states
/// and this gateway's views in, and the supervisor's starts and cut moves (for the map
/// of the cuts: `crate::gateway_cuts`).
pub struct NatsGatewayLink {
    link: NatsLink,
    states: SelectAll<async_nats::Subscriber>,
    cluster: String,
}

impl NatsGatewayLink {
    /// Connects to `url` as gateway `gateway` of `cluster`, presenting `auth`, and
    /// subscribes to the states subject, its view subject, the control and the cuts
    /// subjects.
    pub fn connect(url: &str, cluster: &str, gateway: u16, auth: &NatsAuth) -> Result<NatsGatewayLink, ZoneError> {
        check_cluster_name(cluster)?;
        let link = NatsLink::connect(url, format!("myriad-{cluster}-gateway-{gateway}"), auth)?;
        let mirror = link.subscribe(states_subject(cluster))?;
        let views = link.subscribe(view_subject(cluster, gateway))?;
        let control = link.subscribe(control_subject(cluster))?;
        let cuts = link.subscribe(cuts_subject(cluster))?;
        let states = futures_util::stream::select_all([mirror, views, control, cuts]);
        Ok(NatsGatewayLink { link, states, cluster: cluster.to_string() })
    }

    /// The connection.
    pub fn link(&self) -> &NatsLink {
        &self.link
    }
}

impl crate::fabric::GatewayLink for NatsGatewayLink {
    fn send_intents(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.link.publish(intents_subject(&self.cluster), bytes)
    }

    fn send_subscription(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.link.publish(subscriptions_subject(&self.cluster), bytes)
    }

    fn recv_states(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        self.link.next_before(&mut self.states, deadline)
    }

    fn flush(&mut self) {
        let client = &self.link.client;
        // Bounded: a NATS server that does not answer must not hold a shutdown.
        let _ = self.link.rt.block_on(async { tokio::time::timeout(Duration::from_secs(1), client.flush()).await });
    }
}
