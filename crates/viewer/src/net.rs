//! The network side: one background thread with its own tokio runtime holds the
//! [`Connection`], sends the held keys every tick, measures the ping, and publishes an
//! immutable [`Snapshot`] after each burst of datagrams. The render loop only ever swaps
//! an `Arc` out of a mutex, so a slow network never stalls a frame and a slow frame never
//! delays receiving.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Event};
use myriad_protocol::MAX_DATAGRAM;
use myriad_protocol::login::{LoginAccepted, MapData};

use crate::hud::{PingTracker, RateMeter};
use crate::input::HeldKeys;
use crate::scene::ViewObject;

/// The world as the network thread last saw it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Snapshot {
    /// Increases with every publication.
    pub generation: u64,
    /// Newest tick received.
    pub tick: u64,
    /// The player's object as last heard.
    pub own_position: Option<[f32; 3]>,
    /// Every mirrored object (stale ones included, marked).
    pub objects: Vec<ViewObject>,
    /// Last keep-alive round trip.
    pub ping: Option<Duration>,
    /// Received bytes per second.
    pub bytes_per_s: f64,
    /// Time dilation in thousandths.
    pub dilation_permille: u16,
    /// Why the session ended, if it did.
    pub ended: Option<String>,
}

/// What the render thread and the network thread share.
#[derive(Debug, Default)]
pub struct Shared {
    snapshot: Mutex<Arc<Snapshot>>,
    keys: Mutex<HeldKeys>,
    quit: AtomicBool,
}

impl Shared {
    /// The newest snapshot (cheap: clones an `Arc`).
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshot.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Updates the held keys.
    pub fn with_keys<R>(&self, f: impl FnOnce(&mut HeldKeys) -> R) -> R {
        f(&mut self.keys.lock().unwrap_or_else(|e| e.into_inner()))
    }

    fn publish(&self, s: Snapshot) {
        *self.snapshot.lock().unwrap_or_else(|e| e.into_inner()) = Arc::new(s);
    }
}

/// A logged-in session running on its own thread.
pub struct Session {
    /// The login's answer (player id, shape, tick rate, map description).
    pub accepted: LoginAccepted,
    /// Terrain and statics.
    pub map: MapData,
    /// Snapshots and keys.
    pub shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session").field("entity", &self.accepted.entity_id).finish_non_exhaustive()
    }
}

impl Session {
    /// Logs in (with the map) on a new thread and starts the session loop there; returns
    /// once the login succeeded or failed.
    pub fn start(mut config: ClientConfig, credentials: Credentials) -> Result<Session, ClientError> {
        config.want_map = true;
        // Keep-alives are sent by the ping probe below, on its own schedule.
        config.keepalive_every = Duration::ZERO;
        let shared = Arc::new(Shared::default());
        let (tx, rx) = mpsc::channel();
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("myriad-viewer-net".into())
            .spawn(move || {
                let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = tx.send(Err(ClientError::Io { what: "starting the network runtime", source: e }));
                        return;
                    }
                };
                rt.block_on(async move {
                    let mut conn = match Connection::connect(config, credentials).await {
                        Ok(c) => c,
                        Err(e) => {
                            let _ = tx.send(Err(e));
                            return;
                        }
                    };
                    let map = conn.map().cloned().unwrap_or_default();
                    if tx.send(Ok((conn.accepted().clone(), map))).is_err() {
                        return;
                    }
                    run(&mut conn, &thread_shared).await;
                    let _ = conn.disconnect().await;
                });
            })
            .map_err(|e| ClientError::Io { what: "starting the network thread", source: e })?;
        match rx.recv() {
            Ok(Ok((accepted, map))) => Ok(Session { accepted, map, shared, thread: Some(thread) }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => Err(ClientError::Protocol("the network thread ended during the login".into())),
        }
    }

    /// Asks the network thread to say goodbye to the server and waits up to `timeout`.
    pub fn stop(&mut self, timeout: Duration) {
        self.shared.quit.store(true, Ordering::Relaxed);
        let Some(thread) = self.thread.take() else { return };
        let end = Instant::now() + timeout;
        while !thread.is_finished() && Instant::now() < end {
            std::thread::sleep(Duration::from_millis(5));
        }
        if thread.is_finished() {
            let _ = thread.join();
        }
    }
}

/// Objects not heard of for this long are forgotten (they left the view long ago).
const FORGET_AFTER: Duration = Duration::from_secs(10);

async fn run(conn: &mut Connection, shared: &Shared) {
    let socket = conn.socket();
    let tick_rate = f64::from(conn.accepted().tick_rate_hz.max(1));
    let mut send_every = tokio::time::interval(Duration::from_secs_f64(1.0 / tick_rate));
    send_every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut buf = vec![0u8; MAX_DATAGRAM + 64];
    let mut ping = PingTracker::new(Duration::from_secs(1), Duration::from_secs(3));
    let mut rate = RateMeter::new(Duration::from_secs(1));
    let mut generation = 0u64;
    let mut ended: Option<String> = None;
    while !shared.quit.load(Ordering::Relaxed) {
        let mut changed = false;
        tokio::select! {
            r = socket.recv(&mut buf) => {
                let mut next = r;
                // Drain the burst (a tick may span several datagrams) before publishing.
                loop {
                    match next {
                        Ok(n) => {
                            let now = Instant::now();
                            match conn.handle_datagram(&mut buf[..n], now) {
                                Event::Update { .. } => changed = true,
                                Event::KeepAlive => {
                                    changed |= ping.echoed(now).is_some();
                                }
                                Event::Disconnected(reason) => {
                                    ended = Some(format!("the server ended the session: {reason:?}"));
                                    changed = true;
                                }
                                _ => {}
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                        Err(e) => {
                            // ICMP port unreachable after a server exit shows up here.
                            ended = Some(format!("receiving: {e}"));
                            changed = true;
                            break;
                        }
                    }
                    next = socket.try_recv(&mut buf);
                }
            }
            _ = send_every.tick() => {
                let now = Instant::now();
                if ended.is_none() {
                    // Resends Ready until the session starts, probes a silent server.
                    if let Err(e) = conn.on_timer(now).await {
                        ended = Some(format!("sending: {e}"));
                    }
                    let mask = shared.with_keys(|k| k.take_mask());
                    if let Err(e) = conn.send_action(mask).await {
                        ended = Some(format!("sending: {e}"));
                    }
                    if ping.due(now) && conn.keepalive_if_due().await.is_ok() {
                        ping.sent(now);
                    }
                }
                let before = conn.mirror().fresh();
                conn.mirror_mut().mark_stale(now);
                conn.mirror_mut().forget_older_than(FORGET_AFTER, now);
                changed |= conn.mirror().fresh() != before;
                rate.update(conn.stats(), now);
            }
        }
        if changed {
            generation += 1;
            shared.publish(snapshot(conn, generation, &ping, &rate, ended.clone()));
        }
        if ended.is_some() {
            // Nothing more will come; keep the last picture and idle until asked to quit.
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

fn snapshot(
    conn: &Connection,
    generation: u64,
    ping: &PingTracker,
    rate: &RateMeter,
    ended: Option<String>,
) -> Snapshot {
    let objects = conn
        .mirror()
        .iter()
        .map(|(id, o)| ViewObject { id, kind: o.kind, position: o.position, stale: o.stale })
        .collect();
    Snapshot {
        generation,
        tick: conn.stats().last_tick,
        own_position: conn.own_position(),
        objects,
        ping: ping.last(),
        bytes_per_s: rate.bytes_per_s(),
        dilation_permille: conn.dilation_permille(),
        ended,
    }
}
