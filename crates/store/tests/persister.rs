//! Write-behind persister tests, each run on SQLite and on MySQL/MariaDB.

mod common;

use std::time::Duration;

use common::{TestDb, wait_for};
use myriad_store::{MapId, Persister, PersisterConfig, PlayerState, StoreError, StoredShape, SubmitError, UserId};

backend_tests!(
    coalesces_per_player,
    flushes_on_demand_only_when_asked,
    writes_periodically,
    bounds_the_queue,
    drops_rows_the_database_refuses,
    shutdown_flushes_and_closes,
    survives_a_database_outage,
    dropping_the_last_handle_writes_the_queue,
    checkpoint_writes_at_once,
    shutdown_on_a_dead_database_keeps_its_deadline_and_counts_the_loss,
);

fn snap(user: UserId, map: MapId, x: f32, t: i64) -> PlayerState {
    PlayerState {
        user_id: user,
        map_id: map,
        shape: StoredShape::Sphere { radius: 0.5 },
        position: [x, 1.0, 2.0],
        updated_at_ms: t,
    }
}

/// A persister that only writes when flushed (the interval is an hour).
fn manual() -> PersisterConfig {
    PersisterConfig { interval: Duration::from_secs(3600), ..PersisterConfig::default() }
}

async fn coalesces_per_player(db: TestDb) {
    let (a, b) = (db.user("pa").await, db.user("pb").await);
    let map = db.map("coalesce").await;
    let p = Persister::start(db.store.clone(), manual()).unwrap();
    for t in 0..10 {
        p.submit(snap(a, map, t as f32, 1000 + t)).unwrap();
    }
    p.submit(snap(b, map, -1.0, 5)).unwrap();
    let stats = p.stats();
    assert_eq!((stats.submitted, stats.coalesced, stats.queued), (11, 9, 2));
    let report = p.flush().await.unwrap();
    assert_eq!(report.rows_written, 2);
    let stats = p.stats();
    assert_eq!((stats.rows_written, stats.batches_written, stats.queued), (2, 1, 0));
    assert_eq!(db.store.get_player_state(a, map).await.unwrap().position[0], 9.0);
    assert_eq!(db.store.get_player_state(b, map).await.unwrap().position[0], -1.0);
    // Nothing queued: a flush writes nothing.
    assert_eq!(p.flush().await.unwrap().rows_written, 0);
}

async fn flushes_on_demand_only_when_asked(db: TestDb) {
    let user = db.user("flusher").await;
    let map = db.map("flush").await;
    let p = Persister::start(db.store.clone(), PersisterConfig { batch_size: 7, ..manual() }).unwrap();
    p.submit(snap(user, map, 4.0, 10)).unwrap();
    let others: Vec<UserId> = {
        db.store.seed_users(30).await.unwrap();
        let mut v = Vec::new();
        for i in 0..30 {
            v.push(db.store.find_user(&format!("user{i}")).await.unwrap().unwrap().id);
        }
        v
    };
    let states: Vec<PlayerState> = others.iter().map(|&u| snap(u, map, 1.0, 10)).collect();
    assert_eq!(p.submit_many(&states).unwrap(), 30);
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(db.store.find_player_state(user, map).await.unwrap().is_none());
    assert_eq!(p.stats().rows_written, 0);

    let report = p.flush().await.unwrap();
    assert_eq!(report.rows_written, 31);
    // 31 rows in batches of 7.
    assert_eq!(p.stats().batches_written, 5);
    assert_eq!(db.store.get_player_state(user, map).await.unwrap().position[0], 4.0);
    assert_eq!(db.store.list_player_states(map).await.unwrap().len(), 31);
}

async fn writes_periodically(db: TestDb) {
    let user = db.user("ticker").await;
    let map = db.map("periodic").await;
    let p = Persister::start(
        db.store.clone(),
        PersisterConfig { interval: Duration::from_millis(50), ..PersisterConfig::default() },
    )
    .unwrap();
    p.submit(snap(user, map, 8.0, 1)).unwrap();
    assert!(wait_for(Duration::from_secs(10), || p.stats().rows_written == 1).await);
    assert_eq!(db.store.get_player_state(user, map).await.unwrap().position[0], 8.0);
    assert_eq!(p.stats().queued, 0);
}

async fn bounds_the_queue(db: TestDb) {
    let map = db.map("bounded").await;
    let mut users = Vec::new();
    for i in 0..5 {
        users.push(db.user(&format!("b{i}")).await);
    }
    let p = Persister::start(db.store.clone(), PersisterConfig { max_pending: 3, ..manual() }).unwrap();
    for &u in &users[..3] {
        p.submit(snap(u, map, 1.0, 1)).unwrap();
    }
    assert_eq!(p.submit(snap(users[3], map, 1.0, 1)), Err(SubmitError::Full));
    assert_eq!(p.submit(snap(users[4], map, 1.0, 1)), Err(SubmitError::Full));
    // Queued players still get their newest state in.
    p.submit(snap(users[0], map, 2.0, 2)).unwrap();
    let stats = p.stats();
    assert_eq!((stats.queued, stats.dropped_overflow, stats.coalesced), (3, 2, 1));
    // Invalid input is refused up front.
    let bad = snap(users[1], map, f32::NAN, 3);
    assert!(matches!(p.submit(bad), Err(SubmitError::Invalid(_))));

    p.flush().await.unwrap();
    assert_eq!(db.store.get_player_state(users[0], map).await.unwrap().position[0], 2.0);
    assert!(db.store.find_player_state(users[3], map).await.unwrap().is_none());
    // Room again after the flush.
    p.submit(snap(users[3], map, 1.0, 1)).unwrap();
}

async fn drops_rows_the_database_refuses(db: TestDb) {
    let user = db.user("real").await;
    let map = db.map("refuse").await;
    let p = Persister::start(db.store.clone(), manual()).unwrap();
    p.submit(snap(user, map, 3.0, 1)).unwrap();
    // No such user: the foreign key refuses this row, which must not block the other.
    p.submit(snap(UserId(987_654), map, 3.0, 1)).unwrap();
    let report = p.flush().await.unwrap();
    assert_eq!(report.rows_written, 1);
    let stats = p.stats();
    assert_eq!((stats.rejected_rows, stats.queued), (1, 0));
    assert!(stats.failures >= 1);
    assert_eq!(db.store.get_player_state(user, map).await.unwrap().position[0], 3.0);
}

async fn shutdown_flushes_and_closes(db: TestDb) {
    let user = db.user("leaver").await;
    let map = db.map("shutdown").await;
    let p = Persister::start(db.store.clone(), manual()).unwrap();
    p.submit(snap(user, map, 6.0, 1)).unwrap();
    let report = p.shutdown(Duration::from_secs(5)).await.unwrap();
    assert_eq!(report.rows_written, 1);
    assert_eq!(db.store.get_player_state(user, map).await.unwrap().position[0], 6.0);
    assert_eq!(p.submit(snap(user, map, 7.0, 2)), Err(SubmitError::Closed));
    assert!(p.flush().await.is_err());
}

async fn survives_a_database_outage(db: TestDb) {
    let map = db.map("outage").await;
    db.store.seed_users(50).await.unwrap();
    let mut users = Vec::new();
    for i in 0..50 {
        users.push(db.store.find_user(&format!("user{i}")).await.unwrap().unwrap().id);
    }
    let (store, mut outage) = db.store_with_outage().await;
    let p = Persister::start(
        store,
        PersisterConfig {
            interval: Duration::from_millis(50),
            batch_size: 20,
            retry_min: Duration::from_millis(50),
            retry_max: Duration::from_millis(200),
            ..PersisterConfig::default()
        },
    )
    .unwrap();

    // Healthy: a first round lands.
    for &u in &users {
        p.submit(snap(u, map, 1.0, 1)).unwrap();
    }
    assert!(wait_for(Duration::from_secs(10), || p.stats().rows_written == 50).await);

    outage.cut().await;
    for &u in &users {
        p.submit(snap(u, map, 2.0, 2)).unwrap();
    }
    assert!(
        wait_for(Duration::from_secs(15), || p.stats().failures >= 2).await,
        "writes during the outage must fail and be counted: {:?}",
        p.stats()
    );
    // The world keeps submitting while the database is down; newer states coalesce.
    for &u in &users {
        p.submit(snap(u, map, 3.0, 3)).unwrap();
    }
    let stats = p.stats();
    assert_eq!(stats.queued, 50, "{stats:?}");
    assert_eq!(stats.rows_written, 50, "{stats:?}");
    assert_eq!(stats.dropped_overflow, 0);
    let err = p.flush().await.unwrap_err();
    assert!(matches!(err, StoreError::Unavailable(_)), "{err:?}");

    outage.restore().await;
    assert!(
        wait_for(Duration::from_secs(20), || p.stats().queued == 0).await,
        "queued writes must land once the database is back: {:?}",
        p.stats()
    );
    assert_eq!(p.stats().rows_written, 100);
    let stored = db.store.list_player_states(map).await.unwrap();
    assert_eq!(stored.len(), 50);
    assert!(stored.iter().all(|s| s.position[0] == 3.0 && s.updated_at_ms == 3));
}

/// Dropping every handle makes the task write what is queued before it exits.
async fn dropping_the_last_handle_writes_the_queue(db: TestDb) {
    let user = db.user("dropper").await;
    let map = db.map("dropped").await;
    let p = Persister::start(db.store.clone(), manual()).unwrap();
    let p2 = p.clone();
    p.submit(snap(user, map, 5.0, 1)).unwrap();
    drop(p);
    p2.submit(snap(user, map, 6.0, 2)).unwrap();
    drop(p2);
    let mut found = None;
    for _ in 0..250 {
        found = db.store.find_player_state(user, map).await.unwrap();
        if found.is_some() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(found.map(|s| s.position[0]), Some(6.0));
}

#[tokio::test]
async fn start_rejects_zero_sizes() {
    let db = TestDb::sqlite().await;
    for config in [
        PersisterConfig { batch_size: 0, ..PersisterConfig::default() },
        PersisterConfig { max_pending: 0, ..PersisterConfig::default() },
    ] {
        let err = Persister::start(db.store.clone(), config).unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{err:?}");
    }
    // Absurd durations saturate instead of overflowing.
    let p = Persister::start(
        db.store.clone(),
        PersisterConfig { interval: Duration::MAX, retry_max: Duration::MAX, ..PersisterConfig::default() },
    )
    .unwrap();
    assert_eq!(p.flush().await.unwrap().rows_written, 0);
    p.shutdown(Duration::MAX).await.unwrap();
}

/// Issue 15: a checkpoint is written right away, whatever the writer's own interval, so
/// the caller's clock alone sets the loss bound.
async fn checkpoint_writes_at_once(db: TestDb) {
    let user = db.user("checkpointed").await;
    let map = db.map("checkpoint").await;
    let p = Persister::start(db.store.clone(), manual()).unwrap();
    let started = std::time::Instant::now();
    p.checkpoint(&[snap(user, map, 4.0, 4)]).unwrap();
    assert!(wait_for(Duration::from_secs(5), || p.stats().rows_written == 1).await, "{:?}", p.stats());
    assert!(started.elapsed() < Duration::from_secs(2), "written at once, not after the hour-long interval");
    assert!(p.stats().healthy);
    p.shutdown(Duration::from_secs(5)).await.unwrap();
}

/// Issue 15: shutdown while the database is down gives up at its deadline (not at the
/// deadline plus a pool timeout) and says how many positions were lost; the writer
/// reports the database unhealthy meanwhile.
async fn shutdown_on_a_dead_database_keeps_its_deadline_and_counts_the_loss(db: TestDb) {
    let map = db.map("dead-shutdown").await;
    db.store.seed_users(10).await.unwrap();
    let mut users = Vec::new();
    for i in 0..10 {
        users.push(db.store.find_user(&format!("user{i}")).await.unwrap().unwrap().id);
    }
    let (store, mut outage) = db.store_with_outage().await;
    let config = PersisterConfig { retry_min: Duration::from_millis(20), ..manual() };
    let p = Persister::start(store, config).unwrap();
    outage.cut().await;
    let states: Vec<_> = users.iter().map(|&u| snap(u, map, 5.0, 5)).collect();
    p.checkpoint(&states).unwrap();
    assert!(wait_for(Duration::from_secs(15), || !p.stats().healthy).await, "{:?}", p.stats());
    let deadline = Duration::from_millis(400);
    let started = std::time::Instant::now();
    let loss = p.shutdown(deadline).await.unwrap_err();
    let took = started.elapsed();
    assert_eq!(loss.lost, 10, "{loss}");
    assert!(loss.to_string().contains("10 player positions were not saved"), "{loss}");
    assert!(took < deadline + Duration::from_millis(300), "shutdown took {took:?} for a {deadline:?} deadline");
    assert_eq!(p.stats().lost_at_shutdown, 10);
    assert_eq!(p.stats().dropped_total(), 10);
    outage.restore().await;
}
