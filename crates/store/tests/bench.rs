//! Throughput measurements, ignored by default. Run in release:
//!
//! ```text
//! MYSQL_URL=mysql://myriad:myriad@127.0.0.1:3306/test \
//!   cargo test -p myriad-store --release --test bench -- --ignored --nocapture --test-threads 1
//! ```
//!
//! Prints rows/s of batched player-state upserts (direct and through the Persister) and
//! logins/s at the default Argon2id cost, on SQLite and (with `MYSQL_URL`) MariaDB.

mod common;

use std::time::{Duration, Instant};

use common::TestDb;
use myriad_store::{HashCost, MapId, Persister, PersisterConfig, PlayerState, Store, StoreError, StoredShape, UserId};

const PLAYERS: u32 = 10_000;
const ROUNDS: i64 = 7;

backend_tests!(
    #[ignore = "benchmark; run with --ignored --nocapture in release"]
    bench_persistence,
    #[ignore = "benchmark; run with --ignored --nocapture in release"]
    bench_login,
);

async fn players(db: &TestDb) -> (MapId, Vec<UserId>) {
    let map = db.map("bench").await;
    let t = Instant::now();
    db.store.seed_users(PLAYERS).await.unwrap();
    eprintln!("[{:?}] seed_users({PLAYERS}) at the test cost: {:.2} s", db.dialect(), t.elapsed().as_secs_f64());
    let mut users = Vec::new();
    for i in 0..PLAYERS {
        users.push(db.store.find_user(&format!("user{i}")).await.unwrap().unwrap().id);
    }
    (map, users)
}

fn round(users: &[UserId], map: MapId, r: i64) -> Vec<PlayerState> {
    users
        .iter()
        .enumerate()
        .map(|(i, &u)| PlayerState {
            user_id: u,
            map_id: map,
            shape: StoredShape::Capsule { radius: 0.5, half_height: 0.9 },
            position: [i as f32 + r as f32, 1.0, r as f32 * 0.5],
            updated_at_ms: 1_000 + r,
        })
        .collect()
}

/// "best / median" of per-round rates: the machine is shared, so the best round is the
/// closest to what the code can do and the median shows the typical case.
fn summary(rates: Vec<f64>) -> String {
    summary_with(rates, 0)
}

fn summary_with(mut rates: Vec<f64>, decimals: usize) -> String {
    rates.sort_by(f64::total_cmp);
    let best = rates.last().copied().unwrap_or(0.0);
    let median = rates.get(rates.len() / 2).copied().unwrap_or(0.0);
    format!("best {best:.decimals$} / median {median:.decimals$}")
}

async fn bench_persistence(db: TestDb) {
    let (map, users) = players(&db).await;
    for batch in [100usize, 1000, 10_000] {
        let mut rates = Vec::new();
        for r in 0..ROUNDS {
            let states = round(&users, map, r + batch as i64 * 10);
            let t = Instant::now();
            let mut rows = 0;
            for chunk in states.chunks(batch) {
                rows += db.store.save_player_states(chunk).await.unwrap();
            }
            rates.push(rows as f64 / t.elapsed().as_secs_f64());
        }
        eprintln!(
            "[{:?}] save_player_states, {batch} rows per call, {PLAYERS} rows per round: {} rows/s",
            db.dialect(),
            summary(rates)
        );
    }

    let p = Persister::start(
        db.store.clone(),
        PersisterConfig { interval: Duration::from_secs(3600), ..PersisterConfig::default() },
    )
    .unwrap();
    let mut rates = Vec::new();
    let mut submit_ns = Vec::new();
    for r in 0..ROUNDS {
        let states = round(&users, map, 1_000_000 + r);
        let t = Instant::now();
        p.submit_many(&states).unwrap();
        submit_ns.push(-(t.elapsed().as_nanos() as f64 / f64::from(PLAYERS)));
        let rows = p.flush().await.unwrap().rows_written;
        rates.push(rows as f64 / t.elapsed().as_secs_f64());
    }
    submit_ns.sort_by(f64::total_cmp);
    eprintln!(
        "[{:?}] Persister submit_many + flush, {PLAYERS} rows per round: {} rows/s; \
         submit_many on the caller's thread: best {:.0} / median {:.0} ns per state",
        db.dialect(),
        summary(rates),
        -submit_ns[submit_ns.len() - 1],
        -submit_ns[submit_ns.len() / 2],
    );
}

async fn bench_login(db: TestDb) {
    let mut config = db.config.clone();
    config.hash_cost = HashCost::DEFAULT;
    let store = Store::open(&config).await.unwrap();
    let users = 32u32;
    let t = Instant::now();
    store.seed_users(users).await.unwrap();
    eprintln!(
        "[{:?}] seed_users({users}) at the default cost {:?}: {:.2} s",
        db.dialect(),
        HashCost::DEFAULT,
        t.elapsed().as_secs_f64()
    );
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()) * 2;
    // Warm-up: start the blocking-pool threads and fault in their hashing memory.
    for i in 0..workers as u32 {
        let _ = store.check_credentials(&format!("user{i}"), "warm-up").await;
    }
    for (label, password_of) in [
        ("right password", (|i: u32| format!("password{i}")) as fn(u32) -> String),
        ("wrong password", |i: u32| format!("wrong{i}")),
    ] {
        let mut rates = Vec::new();
        for _ in 0..3 {
            let t = Instant::now();
            let mut tasks = Vec::new();
            for w in 0..workers {
                let store = store.clone();
                tasks.push(tokio::spawn(async move {
                    let mut n = 0u32;
                    for k in 0..8u32 {
                        let i = (w as u32 * 8 + k) % users;
                        let r = store.check_credentials(&format!("user{i}"), &password_of(i)).await;
                        assert!(r.is_ok() || matches!(r, Err(StoreError::WrongCredentials)));
                        n += 1;
                    }
                    n
                }));
            }
            let mut n = 0;
            for task in tasks {
                n += task.await.unwrap();
            }
            rates.push(f64::from(n) / t.elapsed().as_secs_f64());
        }
        eprintln!(
            "[{:?}] check_credentials ({label}), {workers} concurrent callers: {} logins/s",
            db.dialect(),
            summary_with(rates, 1),
        );
    }

    // Timing of a known user with a wrong password against an unknown user.
    let mut known = Vec::new();
    let mut unknown = Vec::new();
    for i in 0..16 {
        let t = Instant::now();
        let _ = store.check_credentials(&format!("user{}", i % users), "nope").await;
        known.push(t.elapsed());
        let t = Instant::now();
        let _ = store.check_credentials(&format!("ghost{i}"), "nope").await;
        unknown.push(t.elapsed());
    }
    known.sort();
    unknown.sort();
    eprintln!(
        "[{:?}] one failed login, sequential, fastest / median of 16: known user {:.1} / {:.1} ms, \
         unknown user {:.1} / {:.1} ms",
        db.dialect(),
        known[0].as_secs_f64() * 1000.0,
        known[8].as_secs_f64() * 1000.0,
        unknown[0].as_secs_f64() * 1000.0,
        unknown[8].as_secs_f64() * 1000.0,
    );
    store.close().await;
}
