//! The network side: one background thread with its own tokio runtime holds the
//! [`Connection`], sends the held keys every tick, measures the ping, and publishes an
//! immutable [`Snapshot`] after each burst of datagrams and [`REDRAW_HZ`] times a second
//! while objects are in view. The render loop only ever swaps an `Arc` out of a mutex, so
//! a slow network never stalls a frame and a slow frame never delays receiving.
//!
//! A snapshot holds the world as the client library's mirror renders it at the time it is
//! taken ([`WorldMirror::rendered`]): interpolated between the states around a render
//! time that trails the server by the configured delay, extrapolated a capped time when
//! updates are late, then held. So the drawn world moves smoothly between the server's
//! ticks instead of jumping at each update.
//!
//! When a session ends (the server's Disconnect, silence through the client library's
//! probes, an unreachable port after the server exited), the thread logs in again with
//! the same credentials after the [`Backoff`] delays, publishing each step as the
//! snapshot's [`Link`]; see [`crate::reconnect`] for which ends are not retried. The
//! credentials stay inside the [`Connection`] for that purpose and are never printed.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Event, SessionEnd, WorldMirror};
use myriad_protocol::MAX_DATAGRAM;
use myriad_protocol::login::{LoginAccepted, MapData};

use crate::hud::{PingTracker, RateMeter};
use crate::input::HeldKeys;
use crate::reconnect::{Backoff, Link, end_reason, login_failure};
use crate::scene::ViewObject;

/// Snapshots published a second while objects are in view (each with the positions at
/// its own render time), so interpolated motion is as smooth as a 60 Hz display.
pub const REDRAW_HZ: f64 = 60.0;

/// The world as the network thread last saw it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Snapshot {
    /// Increases with every publication.
    pub generation: u64,
    /// The [`Login::number`] of the session this world came from.
    pub login: u64,
    /// Newest tick received in this session (a restarted server counts afresh).
    pub tick: u64,
    /// The player's object where it is drawn (as last heard before the first update
    /// of it can be rendered).
    pub own_position: Option<[f32; 3]>,
    /// Every mirrored object (stale ones included, marked), where it is drawn.
    pub objects: Vec<ViewObject>,
    /// Last keep-alive round trip.
    pub ping: Option<Duration>,
    /// Received bytes per second.
    pub bytes_per_s: f64,
    /// Time dilation in thousandths.
    pub dilation_permille: u16,
    /// The link to the server: connected, or why not and what happens next.
    pub link: Link,
}

/// One successful login: the player's object, the map, and which login of the run it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Login {
    /// 1 for the first login of the run, one more for every login after a session ended.
    pub number: u64,
    /// The login's answer (player id, shape, tick rate, map description).
    pub accepted: LoginAccepted,
    /// Terrain and statics.
    pub map: MapData,
}

impl Login {
    fn of(conn: &Connection) -> Login {
        Login {
            number: conn.stats().reconnects + 1,
            accepted: conn.accepted().clone(),
            map: conn.map().cloned().unwrap_or_default(),
        }
    }
}

/// What the render thread and the network thread share.
#[derive(Debug, Default)]
pub struct Shared {
    snapshot: Mutex<Arc<Snapshot>>,
    login: Mutex<Option<Arc<Login>>>,
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

    /// Publishes the last snapshot again with another link state. Objects are marked
    /// stale while the session is down: nothing refreshes them.
    fn publish_link(&self, link: Link) {
        let mut s = Snapshot::clone(&self.snapshot());
        s.generation += 1;
        if !link.is_connected() {
            s.objects.iter_mut().for_each(|o| o.stale = true);
        }
        s.link = link;
        self.publish(s);
    }

    fn set_login(&self, login: Arc<Login>) {
        *self.login.lock().unwrap_or_else(|e| e.into_inner()) = Some(login);
    }

    fn quit_requested(&self) -> bool {
        self.quit.load(Ordering::Relaxed)
    }
}

/// A logged-in session running on its own thread.
pub struct Session {
    /// Snapshots and keys.
    pub shared: Arc<Shared>,
    first: Arc<Login>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session").field("entity", &self.login().accepted.entity_id).finish_non_exhaustive()
    }
}

impl Session {
    /// Logs in (with the map) on a new thread and starts the session loop there; returns
    /// once the login succeeded or failed. A failed first login is an error (a wrong
    /// password or address should be said at once); after that, ended sessions are
    /// followed by new logins (module docs).
    pub fn start(mut config: ClientConfig, credentials: Credentials) -> Result<Session, ClientError> {
        config.want_map = true;
        // Keep-alives are sent by the ping probe below, on its own schedule.
        config.keepalive_every = Duration::ZERO;
        let silence_timeout = config.silence_timeout;
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
                    let login = Arc::new(Login::of(&conn));
                    thread_shared.set_login(login.clone());
                    if tx.send(Ok(login)).is_err() {
                        return;
                    }
                    if stay_connected(&mut conn, &thread_shared, silence_timeout).await {
                        let _ = conn.disconnect().await;
                    }
                });
            })
            .map_err(|e| ClientError::Io { what: "starting the network thread", source: e })?;
        match rx.recv() {
            Ok(Ok(first)) => Ok(Session { shared, first, thread: Some(thread) }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => Err(ClientError::Protocol("the network thread ended during the login".into())),
        }
    }

    /// The newest login: the first one until a session ended and a new login succeeded.
    pub fn login(&self) -> Arc<Login> {
        self.shared.login.lock().unwrap_or_else(|e| e.into_inner()).clone().unwrap_or_else(|| self.first.clone())
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

/// How often a wait checks whether the viewer is quitting.
const QUIT_POLL: Duration = Duration::from_millis(50);

/// How a session loop ended.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Outcome {
    /// The viewer is quitting; the session is still up.
    Quit,
    /// The session is over.
    Ended {
        /// Why, in words.
        reason: String,
        /// Whether a new login may help.
        retry: bool,
    },
}

/// Runs sessions until the viewer quits, logging in again after each one that ended.
/// Returns whether the last session is still up (and deserves a Disconnect).
async fn stay_connected(conn: &mut Connection, shared: &Shared, silence_timeout: Duration) -> bool {
    loop {
        let (reason, retry) = match run(conn, shared, silence_timeout).await {
            Outcome::Quit => return true,
            Outcome::Ended { reason, retry } => (reason, retry),
        };
        if !retry || !log_in_again(conn, shared, reason.clone()).await {
            if !retry {
                shared.publish_link(Link::Disconnected { reason });
            }
            // Keep the last picture until the window closes.
            wait_for_quit(shared).await;
            return false;
        }
        shared.set_login(Arc::new(Login::of(conn)));
    }
}

/// Logs in again after the [`Backoff`] delays until it works (true), a failure that
/// another attempt cannot mend (published as [`Link::Disconnected`]), or the viewer quits
/// (false for both).
async fn log_in_again(conn: &mut Connection, shared: &Shared, mut reason: String) -> bool {
    let mut backoff = Backoff::new(fastrand::u64(..));
    let mut at_least = Duration::ZERO;
    loop {
        let at = Instant::now() + backoff.next_delay().max(at_least);
        shared.publish_link(Link::Reconnecting { reason: reason.clone(), at });
        tokio::select! {
            () = tokio::time::sleep_until(at.into()) => {}
            () = wait_for_quit(shared) => return false,
        }
        shared.publish_link(Link::LoggingIn);
        let attempt = tokio::select! {
            r = conn.reconnect() => r,
            () = wait_for_quit(shared) => return false,
        };
        match attempt {
            Ok(()) => return true,
            Err(e) => {
                let failure = login_failure(&e);
                if !failure.retry {
                    shared.publish_link(Link::Disconnected { reason: failure.reason });
                    return false;
                }
                reason = failure.reason;
                at_least = failure.at_least;
            }
        }
    }
}

async fn wait_for_quit(shared: &Shared) {
    while !shared.quit_requested() {
        tokio::time::sleep(QUIT_POLL).await;
    }
}

/// One session: receives, sends the keys every tick, publishes snapshots, until the
/// viewer quits or the session ends.
async fn run(conn: &mut Connection, shared: &Shared, silence_timeout: Duration) -> Outcome {
    let socket = conn.socket();
    let tick_rate = f64::from(conn.accepted().tick_rate_hz.max(1));
    let mut send_every = tokio::time::interval(Duration::from_secs_f64(1.0 / tick_rate));
    send_every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut redraw_every = tokio::time::interval(Duration::from_secs_f64(1.0 / REDRAW_HZ));
    redraw_every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut buf = vec![0u8; MAX_DATAGRAM + 64];
    let mut ping = PingTracker::new(Duration::from_secs(1), Duration::from_secs(3));
    let mut rate = RateMeter::new(Duration::from_secs(1));
    let mut generation = shared.snapshot().generation;
    let mut tick = 0;
    let ended = |end: SessionEnd| {
        let (reason, retry) = end_reason(end, silence_timeout);
        Outcome::Ended { reason, retry }
    };
    // The link is up from the first snapshot of the session on.
    let mut changed = true;
    while !shared.quit_requested() {
        if changed {
            generation += 1;
            shared.publish(snapshot(conn, generation, tick, &ping, &rate, Instant::now()));
        }
        changed = false;
        tokio::select! {
            r = socket.recv(&mut buf) => {
                let mut next = r;
                // Drain the burst (a tick may span several datagrams) before publishing.
                loop {
                    match next {
                        Ok(n) => {
                            let now = Instant::now();
                            match conn.handle_datagram(&mut buf[..n], now) {
                                Event::Update { tick: t, .. } => {
                                    tick = tick.max(t);
                                    changed = true;
                                }
                                Event::KeepAlive => {
                                    changed |= ping.echoed(now).is_some();
                                }
                                Event::Disconnected(reason) => return ended(SessionEnd::Disconnected(reason)),
                                _ => {}
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                        // ICMP port unreachable after a server exit shows up here.
                        Err(e) => return Outcome::Ended { reason: format!("receiving: {e}"), retry: true },
                    }
                    next = socket.try_recv(&mut buf);
                }
            }
            // Between updates the drawn positions still move (interpolated): publish.
            _ = redraw_every.tick() => changed = !conn.mirror().is_empty(),
            _ = send_every.tick() => {
                let now = Instant::now();
                // Resends Ready until the session starts, probes a silent server.
                if let Err(e) = conn.on_timer(now).await {
                    return Outcome::Ended { reason: format!("sending: {e}"), retry: true };
                }
                if let Some(end) = conn.ended() {
                    return ended(end);
                }
                let mask = shared.with_keys(|k| k.take_mask());
                if let Err(e) = conn.send_action(mask).await {
                    return Outcome::Ended { reason: format!("sending: {e}"), retry: true };
                }
                if ping.due(now) && conn.keepalive_if_due().await.is_ok() {
                    ping.sent(now);
                }
                let before = conn.mirror().fresh();
                conn.mirror_mut().mark_stale(now);
                conn.mirror_mut().forget_older_than(FORGET_AFTER, now);
                changed |= conn.mirror().fresh() != before;
                rate.update(conn.stats(), now);
            }
        }
    }
    Outcome::Quit
}

fn snapshot(
    conn: &Connection,
    generation: u64,
    tick: u64,
    ping: &PingTracker,
    rate: &RateMeter,
    now: Instant,
) -> Snapshot {
    let objects = view_objects(conn.mirror(), now);
    let own = conn.accepted().entity_id;
    let own_position = objects.iter().find(|o| o.id == own).map(|o| o.position).or_else(|| conn.own_position());
    Snapshot {
        generation,
        login: conn.stats().reconnects + 1,
        tick,
        own_position,
        objects,
        ping: ping.last(),
        bytes_per_s: rate.bytes_per_s(),
        dilation_permille: conn.dilation_permille(),
        link: Link::Connected,
    }
}

/// Every mirrored object where it is drawn at `now` (nothing before the first update).
fn view_objects(mirror: &WorldMirror, now: Instant) -> Vec<ViewObject> {
    mirror
        .rendered(now)
        .map(|(id, o, r)| ViewObject { id, kind: o.kind, position: r.position, stale: o.stale })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_protocol::{QuantPos, ShapeKind, StateRecord};

    fn rec(id: u64, x: f32) -> StateRecord {
        StateRecord { id, kind: ShapeKind::Sphere, pos: QuantPos::from_f32([x, 0.0, 0.0]) }
    }

    #[test]
    fn snapshots_draw_the_world_interpolated_at_their_render_time() {
        let mut m = WorldMirror::new(Duration::from_secs(1));
        let t = Instant::now();
        assert!(view_objects(&m, t).is_empty(), "nothing before the first update");
        let tick = Duration::from_secs_f64(1.0 / 30.0);
        m.apply(10, [rec(1, 0.0), rec(2, 7.0)], t);
        m.apply(11, [rec(1, 1.0)], t + tick);
        // 1.5 ticks after tick 11 arrived the server is at about 12.5, and the default
        // two-tick delay draws about 10.5: halfway along object 1's step, not at its
        // newest state; object 2, heard once, where it was heard.
        let drawn = view_objects(&m, t + tick + tick.mul_f64(1.5));
        let x = |id: u64| drawn.iter().find(|o| o.id == id).map(|o| o.position[0]);
        let x1 = x(1).unwrap();
        assert!((0.4..0.6).contains(&x1), "object 1 drawn at x {x1}, between its states 0 and 1");
        assert_eq!(m.get(1).unwrap().position[0], 1.0, "the newest state is 1");
        assert_eq!(x(2), Some(7.0));
        // Later, past the newest state and the extrapolation cap: held, not run away.
        let late = view_objects(&m, t + Duration::from_secs(2));
        let x1 = late.iter().find(|o| o.id == 1).unwrap().position[0];
        assert!((1.0..=4.5).contains(&x1), "held after at most 100 ms of extrapolation: {x1}");
    }
}
