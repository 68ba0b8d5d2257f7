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
use myriad_store::{HashCost, MapId, Persister, PersisterConfig, PlayerState, Shape, Store, StoreError, UserId};

const PLAYERS: u32 = 10_000;
const ROUNDS: i64 = 5;

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
    eprintln!("[{:?}] seed_users({PLAYERS}) at the test cost: {:.2} s", db.backend(), t.elapsed().as_secs_f64());
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
            shape: Shape::Capsule { radius: 0.5, half_height: 0.9 },
            position: [i as f32 + r as f32, 1.0, r as f32 * 0.5],
            updated_at_ms: 1_000 + r,
        })
        .collect()
}

async fn bench_persistence(db: TestDb) {
    let (map, users) = players(&db).await;
    for batch in [100usize, 1000, 10_000] {
        let mut rows = 0usize;
        let t = Instant::now();
        for r in 0..ROUNDS {
            let states = round(&users, map, r + batch as i64 * 10);
            for chunk in states.chunks(batch) {
                rows += db.store.save_player_states(chunk).await.unwrap() as usize;
            }
        }
        let secs = t.elapsed().as_secs_f64();
        eprintln!(
            "[{:?}] save_player_states, {batch} rows per call: {rows} rows in {secs:.2} s = {:.0} rows/s",
            db.backend(),
            rows as f64 / secs
        );
    }

    let p = Persister::start(
        db.store.clone(),
        PersisterConfig { interval: Duration::from_secs(3600), ..PersisterConfig::default() },
    )
    .unwrap();
    let t = Instant::now();
    let mut submit_time = Duration::ZERO;
    for r in 0..ROUNDS {
        let states = round(&users, map, 1_000_000 + r);
        let s = Instant::now();
        p.submit_many(&states).unwrap();
        submit_time += s.elapsed();
        p.flush().await.unwrap();
    }
    let secs = t.elapsed().as_secs_f64();
    let stats = p.stats();
    eprintln!(
        "[{:?}] Persister submit_many+flush: {} rows in {secs:.2} s = {:.0} rows/s; \
         submit_many costs {:.0} ns per state on the caller's thread",
        db.backend(),
        stats.rows_written,
        stats.rows_written as f64 / secs,
        submit_time.as_nanos() as f64 / (ROUNDS as f64 * f64::from(PLAYERS))
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
        db.backend(),
        HashCost::DEFAULT,
        t.elapsed().as_secs_f64()
    );
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()) * 2;
    for (label, password_of) in [
        ("right password", (|i: u32| format!("password{i}")) as fn(u32) -> String),
        ("wrong password", |i: u32| format!("wrong{i}")),
    ] {
        let t = Instant::now();
        let mut tasks = Vec::new();
        for w in 0..workers {
            let store = store.clone();
            tasks.push(tokio::spawn(async move {
                let mut n = 0u32;
                for k in 0..16u32 {
                    let i = (w as u32 * 16 + k) % users;
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
        let secs = t.elapsed().as_secs_f64();
        eprintln!(
            "[{:?}] check_credentials ({label}), {workers} concurrent callers: {n} in {secs:.2} s = {:.1} logins/s",
            db.backend(),
            f64::from(n) / secs
        );
    }

    // Timing of a known user with a wrong password against an unknown user.
    let mut known = Duration::ZERO;
    let mut unknown = Duration::ZERO;
    for i in 0..16 {
        let t = Instant::now();
        let _ = store.check_credentials(&format!("user{}", i % users), "nope").await;
        known += t.elapsed();
        let t = Instant::now();
        let _ = store.check_credentials(&format!("ghost{i}"), "nope").await;
        unknown += t.elapsed();
    }
    eprintln!(
        "[{:?}] sequential failed login: known user {:.1} ms, unknown user {:.1} ms (mean of 16)",
        db.backend(),
        known.as_secs_f64() * 1000.0 / 16.0,
        unknown.as_secs_f64() * 1000.0 / 16.0
    );
    store.close().await;
}
