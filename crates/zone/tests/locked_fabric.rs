//! The locked-down fabric on a real `nats-server` of the test's own, configured by
//! `fabric_auth`: a gateway's credentials cannot publish zone states, heartbeats,
//! control, cut moves, states, views or checkpoints (the server refuses, nothing reaches
//! the zones); a zone's cannot publish claims, intents, cut moves, subscriptions or
//! another zone's heartbeat; the legitimate flows (zones over NATS, the checkpoint
//! store, subscriptions and views by role, the supervisor's halt and cut move heard by a
//! gateway too) still work; a wrong password is refused;
//! `tls://` works with the
//! cluster's authority. Needs the `nats-server` program; skips with a message without it,
//! fails under `MYRIAD_REQUIRE_NATS=1`.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use myriad_core::{ActionScript, ObjectState};
use myriad_physics::TickConstants;
use myriad_testenv::nats_server;
use myriad_zone::checkpoint::{CheckpointStore, JetStreamCheckpoints};
use myriad_zone::fabric_auth::{NatsAuth, Role, RoleCredentials, new_credentials, render_server_config};
use myriad_zone::nats::NatsLink;
use myriad_zone::{ClusterKey, Fabric, NatsFabric, RunOptions, ZoneId, ZoneLayout, pair_reach, run_zoned};

mod common;
use common::{clustered, cpu, single};

/// A `nats-server` with the configuration of cluster `c`, on a free port, in a folder of
/// its own; stopped and removed when dropped.
struct Server {
    child: Child,
    dir: PathBuf,
    url: String,
    creds: Vec<RoleCredentials>,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl Server {
    /// Starts one for cluster `cluster`; `extra` is appended to the configuration (TLS).
    fn start(exe: &Path, cluster: &str, extra: impl FnOnce(&Path) -> String, scheme: &str) -> Server {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
        let dir = std::env::temp_dir().join(format!("myriad-locked-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let creds = new_credentials(cluster, 4).unwrap();
        let listen = format!("127.0.0.1:{port}");
        let mut config = render_server_config(cluster, &creds, &listen, &dir.join("js")).unwrap();
        config.push_str(&extra(&dir));
        let path = dir.join("nats-server.conf");
        myriad_zone::fabric_auth::write_private(&path, &config).unwrap();
        let child = Command::new(exe)
            .arg("-c")
            .arg(&path)
            .arg("-l")
            .arg(dir.join("nats.log"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let server = Server { child, dir, url: format!("{scheme}://{listen}"), creds };
        let start = Instant::now();
        while std::net::TcpStream::connect(&listen).is_err() {
            assert!(start.elapsed() < Duration::from_secs(10), "nats-server did not start: {}", server.log());
            std::thread::sleep(Duration::from_millis(50));
        }
        server
    }

    fn auth(&self, role: Role) -> NatsAuth {
        self.creds.iter().find(|c| c.role == role).unwrap().auth()
    }

    fn link(&self, role: Role) -> NatsLink {
        NatsLink::connect(&self.url, format!("test-{}", role.name()), &self.auth(role)).unwrap()
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("nats.log")).unwrap_or_default()
    }
}

/// The server's errors on `link` once it has reported at least `n` (they reach the
/// client as events, a moment after the flush that made the server answer).
fn errors_after(link: &NatsLink, n: u64) -> Vec<String> {
    let start = Instant::now();
    while link.server_errors().0 < n && start.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let (count, errors) = link.server_errors();
    assert_eq!(count, n, "{errors:?}");
    errors
}

/// Nothing arrives on `sub` within a short wait.
fn silent(link: &NatsLink, sub: &mut async_nats::Subscriber, what: &str) {
    let got = link.next_before(sub, Instant::now() + Duration::from_millis(300)).unwrap();
    assert_eq!(got, None, "{what} reached its listener");
}

#[test]
fn a_gateway_cannot_speak_for_zones_or_the_supervisor_and_a_zone_cannot_claim() {
    let Some(exe) = nats_server() else { return };
    let server = Server::start(&exe, "c", |_| String::new(), "nats");
    let zone = server.link(Role::Zone(ZoneId(0)));
    let other_zone = server.link(Role::Zone(ZoneId(1)));
    let supervisor = server.link(Role::Supervisor);
    let gateway = server.link(Role::Gateway);
    let other_gateway = server.link(Role::Gateway);
    let mut borders = zone.subscribe("myriad.c.zone.0".into()).unwrap();
    let mut control = zone.subscribe("myriad.c.control".into()).unwrap();
    let mut intents = other_zone.subscribe("myriad.c.intents".into()).unwrap();
    let mut cuts = other_zone.subscribe("myriad.c.cuts".into()).unwrap();
    let mut beats = supervisor.subscribe("myriad.c.heartbeat.*".into()).unwrap();
    let mut states = other_gateway.subscribe("myriad.c.states".into()).unwrap();
    let mut claims = other_gateway.subscribe("myriad.c.sessions".into()).unwrap();
    let mut subscriptions = other_zone.subscribe("myriad.c.subscriptions".into()).unwrap();
    let mut views = other_gateway.subscribe("myriad.c.view.3".into()).unwrap();
    // A gateway hears the supervisor's starts and cut moves (its operators' map of the
    // cuts), read-only.
    let mut gateway_control = other_gateway.subscribe("myriad.c.control".into()).unwrap();
    let mut gateway_cuts = other_gateway.subscribe("myriad.c.cuts".into()).unwrap();
    // A subscription is written to the socket when `subscribe` returns, not yet taken by
    // the server, and these links have no subject of their own to echo a probe on
    // (`NatsLink::echo`): a message published by another link at once could miss it.
    std::thread::sleep(Duration::from_millis(300));

    // What each role may say still arrives: the silences below are refusals, not a deaf
    // listener.
    let heard = |link: &NatsLink, sub: &mut async_nats::Subscriber| {
        link.next_before(sub, Instant::now() + Duration::from_secs(20)).unwrap().expect("a message")
    };
    gateway.publish("myriad.c.intents".into(), b"join".to_vec()).unwrap();
    assert_eq!(heard(&other_zone, &mut intents), b"join");
    gateway.publish("myriad.c.sessions".into(), b"claim".to_vec()).unwrap();
    assert_eq!(heard(&other_gateway, &mut claims), b"claim");
    other_zone.publish("myriad.c.zone.0".into(), b"border".to_vec()).unwrap();
    assert_eq!(heard(&zone, &mut borders), b"border");
    other_zone.publish("myriad.c.heartbeat.1".into(), b"beat".to_vec()).unwrap();
    assert_eq!(heard(&supervisor, &mut beats), b"beat");
    other_zone.publish("myriad.c.states".into(), b"states".to_vec()).unwrap();
    assert_eq!(heard(&other_gateway, &mut states), b"states");
    supervisor.publish("myriad.c.control".into(), b"halt".to_vec()).unwrap();
    assert_eq!(heard(&zone, &mut control), b"halt");
    assert_eq!(heard(&other_gateway, &mut gateway_control), b"halt");
    supervisor.publish("myriad.c.cuts".into(), b"move".to_vec()).unwrap();
    assert_eq!(heard(&other_zone, &mut cuts), b"move");
    assert_eq!(heard(&other_gateway, &mut gateway_cuts), b"move");
    gateway.publish("myriad.c.subscriptions".into(), b"cells".to_vec()).unwrap();
    assert_eq!(heard(&other_zone, &mut subscriptions), b"cells");
    zone.publish("myriad.c.view.3".into(), b"view".to_vec()).unwrap();
    assert_eq!(heard(&other_gateway, &mut views), b"view");

    // A gateway's credentials: no border states, heartbeats, control, cut moves, states,
    // views or checkpoints.
    let forbidden = [
        "myriad.c.zone.0",
        "myriad.c.heartbeat.0",
        "myriad.c.control",
        "myriad.c.cuts",
        "myriad.c.states",
        "myriad.c.view.3",
        "$O.myriad-c.C.forged",
        "$JS.API.STREAM.CREATE.OBJ_myriad-c",
    ];
    for subject in forbidden {
        gateway.publish(subject.into(), b"forged".to_vec()).unwrap();
    }
    gateway.flush().unwrap();
    silent(&zone, &mut borders, "a gateway's border state");
    silent(&zone, &mut control, "a gateway's halt");
    silent(&other_zone, &mut cuts, "a gateway's cut move");
    silent(&other_gateway, &mut gateway_cuts, "a gateway's cut move, to another gateway");
    silent(&other_gateway, &mut gateway_control, "a gateway's halt, to another gateway");
    silent(&supervisor, &mut beats, "a gateway's heartbeat");
    silent(&other_gateway, &mut states, "a gateway's states");
    silent(&other_gateway, &mut views, "a gateway's view for another gateway");
    let errors = errors_after(&gateway, forbidden.len() as u64);
    for subject in forbidden {
        let refused = format!("Permissions Violation for Publish to \"{subject}\"");
        assert!(errors.iter().any(|e| e.contains(&refused)), "{refused} not in {errors:?}");
    }

    // A zone's credentials: no claims, no intents, no cut moves (a zone cannot move
    // the cuts for the others), no subscriptions.
    for subject in ["myriad.c.sessions", "myriad.c.intents", "myriad.c.cuts", "myriad.c.subscriptions"] {
        zone.publish(subject.into(), b"forged".to_vec()).unwrap();
    }
    zone.flush().unwrap();
    silent(&other_gateway, &mut claims, "a zone's claim");
    silent(&other_zone, &mut intents, "a zone's intents");
    silent(&other_zone, &mut cuts, "a zone's cut move");
    silent(&other_gateway, &mut gateway_cuts, "a zone's cut move, to a gateway");
    silent(&other_zone, &mut subscriptions, "a zone's subscription");
    let errors = errors_after(&zone, 4);
    assert!(errors.iter().all(|e| e.contains("Permissions Violation for Publish")), "{errors:?}");

    // Nor may a zone beat another zone's heartbeat (to hide its death).
    other_zone.publish("myriad.c.heartbeat.0".into(), b"forged".to_vec()).unwrap();
    other_zone.flush().unwrap();
    silent(&supervisor, &mut beats, "zone 1's heartbeat for zone 0");
    let errors = errors_after(&other_zone, 1);
    assert!(errors[0].contains("Permissions Violation for Publish to \"myriad.c.heartbeat.0\""), "{errors:?}");

    // Nor may a gateway listen to what is not its own (the zones' borders).
    let _spy = gateway.subscribe("myriad.c.zone.1".into()).unwrap();
    gateway.flush().unwrap();
    let errors = errors_after(&gateway, forbidden.len() as u64 + 1);
    assert!(errors.iter().any(|e| e.contains("Permissions Violation for Subscription to \"myriad.c.zone.1\"")));
    // The lawful links saw no refusal.
    for link in [&supervisor, &other_gateway] {
        assert_eq!(link.server_errors().0, 0, "{:?}", link.server_errors().1);
    }
}

#[test]
fn a_wrong_password_or_none_is_refused_with_a_clear_error() {
    let Some(exe) = nats_server() else { return };
    let server = Server::start(&exe, "c", |_| String::new(), "nats");
    let user = server.creds[1].user.clone();
    let wrong = NatsLink::connect(&server.url, "test".into(), &NatsAuth::user(&user, "not-the-password"));
    let e = wrong.err().expect("refused").to_string();
    assert!(e.contains(&format!("NATS refused user \"{user}\": wrong user or password")), "{e}");
    let none = NatsLink::connect(&server.url, "test".into(), &NatsAuth::default()).err().expect("refused");
    assert!(none.to_string().contains("NATS wants credentials"), "{none}");
}

/// Zones over the locked server end in one process's hash with the zone role's
/// credentials, and the checkpoint store works for the zones and the supervisor (put,
/// info, a chunked get, logs, forget, and the bucket's deletion) without one refusal.
#[test]
fn the_legitimate_flows_work_on_the_locked_server() {
    let Some(exe) = nats_server() else { return };
    let cluster = "lawful";
    let server = Server::start(&exe, cluster, |_| String::new(), "nats");
    let world = clustered(2, 4_000, 400, 1_500);
    let script = ActionScript::walkers(&world, 400, 60, 3);
    let layout = ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap();
    let fabrics = (0..4)
        .map(|z| {
            let auth = server.auth(Role::Zone(ZoneId(z)));
            NatsFabric::connect(&server.url, cluster, ZoneId(z), &auth).map(|f| Box::new(f) as Box<dyn Fabric>)
        })
        .collect::<Result<Vec<_>, _>>()
        .unwrap();
    let opts = RunOptions::new(60, Duration::from_secs(60));
    let run = run_zoned(&world, layout, &script, &TickConstants::default(), &cpu, fabrics, &opts).unwrap();
    assert_eq!(run.state_hash, single(&world, 60, &script));

    // Checkpoints of a zone of scenario 3's size (megabytes: many 128 kB chunks, so the
    // get streams them under JetStream's flow control).
    let key = ClusterKey::random();
    let n = world.dynamics.len();
    let objects: Vec<ObjectState> = (0..80_000)
        .map(|i| ObjectState { id: myriad_core::EntityId(i as u32 + 1), ..world.dynamics.state_of(i % n) })
        .collect();
    let zone = server.link(Role::Zone(ZoneId(0)));
    let mut store = JetStreamCheckpoints::open(zone.rt.clone(), zone.client.clone(), cluster, key.clone()).unwrap();
    let cuts = (vec![0.0, 100.0, 200.0], vec![0.0, 200.0]);
    store.put(ZoneId(0), 30, 1, &cuts, &objects).unwrap();
    store.put(ZoneId(0), 30, 1, &cuts, &objects).unwrap();
    store.put_log(ZoneId(0), 30, b"log").unwrap();
    assert!(store.has(ZoneId(0), 30).unwrap());
    assert_eq!(store.get(ZoneId(0), 30).unwrap().objects, objects);
    assert_eq!(store.get_log(ZoneId(0), 30).unwrap(), b"log");
    store.put(ZoneId(0), 60, 1, &cuts, &objects[..10]).unwrap();
    store.forget(ZoneId(0), 30).unwrap();
    assert!(!store.has(ZoneId(0), 30).unwrap());
    let supervisor = server.link(Role::Supervisor);
    let mut s = JetStreamCheckpoints::open(supervisor.rt.clone(), supervisor.client.clone(), cluster, key).unwrap();
    assert_eq!(s.latest_consistent(1, &[60, 30]).unwrap(), Some(60));
    let snap = s.get(ZoneId(0), 60).unwrap();
    assert_eq!((snap.objects.as_slice(), &snap.cuts), (&objects[..10], &cuts));
    s.delete().unwrap();
    for link in [&zone, &supervisor] {
        assert_eq!(link.server_errors().0, 0, "{:?}", link.server_errors().1);
    }
    assert!(!server.log().contains("Violation"), "{}", server.log());
}

/// A certificate authority, and certificates it signs: the server's for 127.0.0.1, and
/// a client's.
struct Pki {
    ca: PathBuf,
    server: (PathBuf, PathBuf),
    client: (PathBuf, PathBuf),
}

fn pki(dir: &Path) -> Pki {
    use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca = CertifiedIssuer::self_signed(ca_params, KeyPair::generate().unwrap()).unwrap();
    let leaf = |names: Vec<String>, stem: &str| {
        let key = KeyPair::generate().unwrap();
        let cert = CertificateParams::new(names).unwrap().signed_by(&key, &ca).unwrap();
        let (c, k) = (dir.join(format!("{stem}.pem")), dir.join(format!("{stem}-key.pem")));
        std::fs::write(&c, cert.pem()).unwrap();
        std::fs::write(&k, key.serialize_pem()).unwrap();
        (c, k)
    };
    let server = leaf(vec!["127.0.0.1".into(), "localhost".into()], "server");
    let client = leaf(vec!["client.myriad".into()], "client");
    let ca_path = dir.join("ca.pem");
    std::fs::write(&ca_path, ca.pem()).unwrap();
    Pki { ca: ca_path, server, client }
}

/// `tls://` connects with the cluster's authority (and, where the server verifies
/// clients, a client certificate), and not without them.
#[test]
fn tls_urls_need_the_clusters_authority() {
    let Some(exe) = nats_server() else { return };
    let pki_dir = std::env::temp_dir().join(format!("myriad-pki-{}", std::process::id()));
    std::fs::create_dir_all(&pki_dir).unwrap();
    let p = pki(&pki_dir);
    let tls = |verify: bool| {
        let (cert, key, ca) = (p.server.0.display(), p.server.1.display(), p.ca.display());
        move |_: &Path| {
            format!(
                "tls {{\n  cert_file: \"{cert}\"\n  key_file: \"{key}\"\n  ca_file: \"{ca}\"\n  verify: {verify}\n}}\n"
            )
        }
    };
    let server = Server::start(&exe, "c", tls(false), "tls");
    let zone = server.auth(Role::Zone(ZoneId(1)));
    let link = NatsLink::connect(&server.url, "tls".into(), &zone.clone().with_ca(p.ca.clone())).unwrap();
    let mut sub = link.subscribe("myriad.c.zone.1".into()).unwrap();
    link.publish("myriad.c.zone.1".into(), b"over tls".to_vec()).unwrap();
    assert_eq!(
        link.next_before(&mut sub, Instant::now() + Duration::from_secs(5)).unwrap(),
        Some(b"over tls".to_vec())
    );
    let e = NatsLink::connect(&server.url, "tls".into(), &zone).err().expect("an unknown authority is refused");
    assert!(e.to_string().contains("TLS to NATS"), "{e}");
    drop(server);

    // A server that verifies clients: the client certificate comes from the environment
    // (MYRIAD_NATS_CERT, MYRIAD_NATS_KEY) like the rest.
    let server = Server::start(&exe, "c", tls(true), "tls");
    let creds = server.creds.iter().find(|c| c.role == Role::Zone(ZoneId(1))).unwrap().clone();
    let vars = |with_cert: bool| {
        let mut v = vec![
            ("MYRIAD_NATS_USER", creds.user.clone()),
            ("MYRIAD_NATS_PASSWORD", creds.password.clone()),
            ("MYRIAD_NATS_CA", p.ca.display().to_string()),
        ];
        if with_cert {
            v.push(("MYRIAD_NATS_CERT", p.client.0.display().to_string()));
            v.push(("MYRIAD_NATS_KEY", p.client.1.display().to_string()));
        }
        NatsAuth::from_lookup(move |k| v.iter().find(|(n, _)| *n == k).map(|(_, x)| x.clone())).unwrap()
    };
    assert!(NatsLink::connect(&server.url, "tls".into(), &vars(false)).is_err(), "no client certificate");
    let link = NatsLink::connect(&server.url, "tls".into(), &vars(true)).unwrap();
    link.flush().unwrap();
    drop(server);
    std::fs::remove_dir_all(&pki_dir).unwrap();
}
