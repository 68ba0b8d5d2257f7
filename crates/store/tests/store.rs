//! Store tests, each run on SQLite and on MySQL/MariaDB (see `common`).

mod common;

use common::TestDb;
use myriad_store::{Heightmap, MapId, NewMap, PlayerState, StaticObject, StoreError, StoredShape, UserId, WorldBounds};

backend_tests!(
    create_user_then_login,
    wrong_password_is_rejected,
    unknown_user_is_rejected_like_a_wrong_password,
    username_taken,
    invalid_input_is_rejected,
    player_state_round_trip,
    batched_save_of_1000_states,
    stale_states_do_not_overwrite_newer_ones,
    maps_and_statics_round_trip,
    static_objects_are_all_or_nothing,
    seed_users_is_idempotent,
    reopening_keeps_data,
    password_change_and_user_deletion,
);

fn sphere(r: f32) -> StoredShape {
    StoredShape::Sphere { radius: r }
}

fn state(user: UserId, map: MapId, pos: [f32; 3], t: i64) -> PlayerState {
    PlayerState {
        user_id: user,
        map_id: map,
        shape: StoredShape::Capsule { radius: 0.5, half_height: 0.9 },
        position: pos,
        updated_at_ms: t,
    }
}

async fn create_user_then_login(db: TestDb) {
    let id = db.user("alice").await;
    let map = db.map("login-map").await;
    let user = db.store.check_credentials("alice", "pw-alice").await.unwrap();
    assert_eq!(user.id, id);
    assert_eq!(user.username, "alice");

    // First visit: no state yet.
    let login = db.store.login("alice", "pw-alice", map).await.unwrap();
    assert_eq!(login.user_id, id);
    assert_eq!(login.state, None);

    // With a state, login returns it.
    let s = state(id, map, [1.5, 2.25, -3.0], 1000);
    db.store.create_player_state(&s).await.unwrap();
    let login = db.store.login("alice", "pw-alice", map).await.unwrap();
    assert_eq!(login.state, Some(s));

    // Usernames are case-insensitive.
    let user = db.store.check_credentials("ALICE", "pw-alice").await.unwrap();
    assert_eq!(user.id, id);
}

async fn wrong_password_is_rejected(db: TestDb) {
    db.user("bob").await;
    let err = db.store.check_credentials("bob", "pw-bobx").await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
    let err = db.store.check_credentials("bob", "PW-BOB").await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
    let map = db.map("m").await;
    let err = db.store.login("bob", "nope", map).await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
}

async fn unknown_user_is_rejected_like_a_wrong_password(db: TestDb) {
    db.user("carol").await;
    let err = db.store.check_credentials("nobody", "pw-carol").await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
    assert_eq!(
        err.to_string(),
        StoreError::WrongCredentials.to_string(),
        "the message must not say which part was wrong"
    );
    assert!(db.store.find_user("nobody").await.unwrap().is_none());
}

async fn username_taken(db: TestDb) {
    db.user("dave").await;
    for name in ["dave", "DAVE", "Dave"] {
        let err = db.store.create_user(name, "other").await.unwrap_err();
        assert!(matches!(err, StoreError::UsernameTaken), "{name}: {err:?}");
    }
    // The original password still works.
    db.store.check_credentials("dave", "pw-dave").await.unwrap();
}

async fn invalid_input_is_rejected(db: TestDb) {
    let long_name = "x".repeat(33);
    let long_pw = "p".repeat(65);
    for (name, pw) in [
        ("", "pw"),
        (long_name.as_str(), "pw"),
        ("has space", "pw"),
        ("émile", "pw"),
        ("semi;colon", "pw"),
        ("ok", ""),
        ("ok", long_pw.as_str()),
    ] {
        let err = db.store.create_user(name, pw).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{name:?}/{pw:?}: {err:?}");
        let err = db.store.check_credentials(name, pw).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{name:?}/{pw:?}: {err:?}");
    }
    // Limits are inclusive.
    db.store.create_user(&"y".repeat(32), &"p".repeat(64)).await.unwrap();

    let user = db.user("erin").await;
    let map = db.map("invalid-map").await;
    for bad in [
        PlayerState { position: [f32::NAN, 0.0, 0.0], ..state(user, map, [0.0; 3], 1) },
        PlayerState { position: [0.0, f32::INFINITY, 0.0], ..state(user, map, [0.0; 3], 1) },
        PlayerState { shape: sphere(0.0), ..state(user, map, [0.0; 3], 1) },
        PlayerState { shape: sphere(-1.0), ..state(user, map, [0.0; 3], 1) },
        PlayerState { shape: StoredShape::Box { half_extents: [1.0, f32::NAN, 1.0] }, ..state(user, map, [0.0; 3], 1) },
    ] {
        let err = db.store.create_player_state(&bad).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{bad:?}: {err:?}");
        let err = db.store.save_player_states(&[bad]).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{bad:?}: {err:?}");
    }
    assert!(db.store.find_player_state(user, map).await.unwrap().is_none());

    let good = NewMap {
        name: "fine".into(),
        heightmap: Heightmap::None,
        max_height: 1.0,
        bounds: WorldBounds { min: [0.0; 3], max: [1.0; 3] },
    };
    let bad_maps = [
        NewMap { name: "".into(), ..good.clone() },
        NewMap { name: "   ".into(), ..good.clone() },
        NewMap { name: "n".repeat(65), ..good.clone() },
        NewMap { max_height: f32::NAN, ..good.clone() },
        NewMap { bounds: WorldBounds { min: [0.0; 3], max: [1.0, 0.0, 1.0] }, ..good.clone() },
        NewMap { heightmap: Heightmap::Inline { width: 3, height: 2, samples: vec![0; 5] }, ..good.clone() },
        NewMap { heightmap: Heightmap::Inline { width: 0, height: 0, samples: vec![] }, ..good.clone() },
        NewMap { heightmap: Heightmap::Path(String::new()), ..good.clone() },
    ];
    for bad in bad_maps {
        let err = db.store.create_map(&bad).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{bad:?}: {err:?}");
    }
    assert!(db.store.list_maps().await.unwrap().iter().all(|m| m.name != "fine"));
}

async fn player_state_round_trip(db: TestDb) {
    let user = db.user("frank").await;
    let map = db.map("round-trip").await;
    let other_map = db.map("round-trip-2").await;

    let err = db.store.get_player_state(user, map).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    let s = state(user, map, [10.0, 0.5, 20.0], 5);
    let err = db.store.update_player_state(&s).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");

    db.store.create_player_state(&s).await.unwrap();
    assert_eq!(db.store.get_player_state(user, map).await.unwrap(), s);
    let err = db.store.create_player_state(&s).await.unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists(_)), "{err:?}");

    // Every shape kind survives the trip, with awkward f32 values.
    for shape in [
        sphere(0.1),
        StoredShape::Box { half_extents: [0.3, 1.0e-3, 7.123_456] },
        StoredShape::Capsule { radius: 0.25, half_height: 0.0 },
    ] {
        let s2 = PlayerState { shape, position: [-0.1, 1.0e7, std::f32::consts::PI], updated_at_ms: 6, ..s };
        db.store.update_player_state(&s2).await.unwrap();
        assert_eq!(db.store.get_player_state(user, map).await.unwrap(), s2);
    }
    // Updating with identical values still finds the row.
    let same = db.store.get_player_state(user, map).await.unwrap();
    db.store.update_player_state(&same).await.unwrap();

    // States are per map.
    assert!(db.store.find_player_state(user, other_map).await.unwrap().is_none());
    let elsewhere = state(user, other_map, [1.0, 2.0, 3.0], 7);
    db.store.create_player_state(&elsewhere).await.unwrap();
    assert_eq!(db.store.list_player_states(other_map).await.unwrap(), vec![elsewhere]);

    // Unknown user or map.
    let ghost = state(UserId(999_999), map, [0.0; 3], 1);
    let err = db.store.create_player_state(&ghost).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    let ghost_map = state(user, MapId(999_999), [0.0; 3], 1);
    let err = db.store.create_player_state(&ghost_map).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
}

async fn batched_save_of_1000_states(db: TestDb) {
    let map = db.map("crowd").await;
    let report = db.store.seed_users(1000).await.unwrap();
    assert_eq!(report.created, 1000);
    let mut users = Vec::new();
    for i in 0..1000 {
        users.push(db.store.find_user(&format!("user{i}")).await.unwrap().unwrap().id);
    }
    let states: Vec<PlayerState> =
        users.iter().enumerate().map(|(i, &u)| state(u, map, [i as f32, 1.0, -(i as f32) * 0.5], 100)).collect();
    assert_eq!(db.store.save_player_states(&states).await.unwrap(), 1000);
    let mut stored = db.store.list_player_states(map).await.unwrap();
    stored.sort_by_key(|s| s.user_id);
    let mut expected = states.clone();
    expected.sort_by_key(|s| s.user_id);
    assert_eq!(stored, expected);

    // Second round: updates of existing rows, with a duplicate in the same call (the
    // newer one must win whatever its position in the slice).
    let mut moved: Vec<PlayerState> =
        states.iter().map(|s| PlayerState { position: [s.position[0], 2.0, 0.0], updated_at_ms: 200, ..*s }).collect();
    moved.insert(0, PlayerState { position: [0.0, 9.0, 9.0], updated_at_ms: 300, ..states[0] });
    moved.push(PlayerState { position: [0.0, 8.0, 8.0], updated_at_ms: 150, ..states[0] });
    assert_eq!(db.store.save_player_states(&moved).await.unwrap(), 1000);
    let first = db.store.get_player_state(states[0].user_id, map).await.unwrap();
    assert_eq!(first.position, [0.0, 9.0, 9.0]);
    assert_eq!(first.updated_at_ms, 300);
    let last = db.store.get_player_state(states[999].user_id, map).await.unwrap();
    assert_eq!(last.position, [999.0, 2.0, 0.0]);

    assert_eq!(db.store.save_player_states(&[]).await.unwrap(), 0);
}

async fn stale_states_do_not_overwrite_newer_ones(db: TestDb) {
    let user = db.user("gina").await;
    let map = db.map("stale").await;
    let newer = state(user, map, [5.0, 5.0, 5.0], 2000);
    db.store.save_player_states(&[newer]).await.unwrap();
    let older = state(user, map, [1.0, 1.0, 1.0], 1000);
    db.store.save_player_states(&[older]).await.unwrap();
    assert_eq!(db.store.get_player_state(user, map).await.unwrap(), newer);
    let newest = PlayerState { shape: sphere(2.0), ..state(user, map, [6.0, 6.0, 6.0], 3000) };
    db.store.save_player_states(&[newest]).await.unwrap();
    assert_eq!(db.store.get_player_state(user, map).await.unwrap(), newest);
}

fn objects(n: i64) -> Vec<StaticObject> {
    (0..n)
        .map(|i| StaticObject {
            object_id: i,
            shape: match i % 3 {
                0 => sphere(1.0 + i as f32 * 0.01),
                1 => StoredShape::Box { half_extents: [1.0, 2.0, 0.5 + i as f32] },
                _ => StoredShape::Capsule { radius: 0.3, half_height: i as f32 },
            },
            position: [i as f32, -1.5, 0.125 * i as f32],
        })
        .collect()
}

async fn maps_and_statics_round_trip(db: TestDb) {
    let samples: Vec<u16> = (0..(64 * 32)).map(|i| (i * 31 % 65_536) as u16).collect();
    let inline = NewMap {
        name: "hills".into(),
        heightmap: Heightmap::Inline { width: 64, height: 32, samples },
        max_height: 42.5,
        bounds: WorldBounds { min: [-10.0, 0.0, -20.0], max: [1000.0, 64.0, 500.5] },
    };
    let by_path =
        NewMap { name: "desert".into(), heightmap: Heightmap::Path("maps/desert.png".into()), ..inline.clone() };
    let flat = NewMap { name: "flat".into(), heightmap: Heightmap::None, ..inline.clone() };
    let mut ids = Vec::new();
    for map in [&inline, &by_path, &flat] {
        let id = db.store.create_map(map).await.unwrap();
        let got = db.store.get_map(id).await.unwrap();
        assert_eq!(got.id, id);
        assert_eq!(got.name, map.name);
        assert_eq!(got.heightmap, map.heightmap);
        assert_eq!(got.max_height, map.max_height);
        assert_eq!(got.bounds, map.bounds);
        assert!(got.created_at_ms > 0);
        assert_eq!(db.store.map_id_by_name(&map.name).await.unwrap(), id);
        ids.push(id);
    }
    let listed = db.store.list_maps().await.unwrap();
    assert_eq!(listed.iter().map(|m| m.id).collect::<Vec<_>>(), ids);
    assert_eq!(listed[1].name, "desert");
    assert_eq!(listed[1].bounds, inline.bounds);

    let err = db.store.create_map(&flat).await.unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists(_)), "{err:?}");
    let err = db.store.get_map(MapId(424_242)).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    let err = db.store.map_id_by_name("atlantis").await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");

    // Statics: more than one insert chunk, all shapes; per map.
    let objs = objects(600);
    assert_eq!(db.store.add_static_objects(ids[0], &objs).await.unwrap(), 600);
    assert_eq!(db.store.get_static_objects(ids[0]).await.unwrap(), objs);
    assert!(db.store.get_static_objects(ids[1]).await.unwrap().is_empty());
    // The same object ids on another map are fine.
    db.store.add_static_objects(ids[1], &objs[..3]).await.unwrap();
    assert_eq!(db.store.get_static_objects(ids[1]).await.unwrap(), objs[..3].to_vec());
    let err = db.store.get_static_objects(MapId(424_242)).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    let err = db.store.add_static_objects(MapId(424_242), &objs[..1]).await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
}

async fn static_objects_are_all_or_nothing(db: TestDb) {
    let map = db.map("atomic").await;
    db.store.add_static_objects(map, &objects(10)).await.unwrap();
    // 300 new objects, then one clashing with an existing id: nothing is added.
    let mut batch: Vec<StaticObject> = objects(310)[10..].to_vec();
    batch.push(objects(10)[5]);
    let err = db.store.add_static_objects(map, &batch).await.unwrap_err();
    assert!(matches!(err, StoreError::AlreadyExists(_)), "{err:?}");
    assert_eq!(db.store.get_static_objects(map).await.unwrap().len(), 10);
    // An invalid object rejects the call before it reaches the database.
    let mut bad = objects(20)[10..].to_vec();
    bad[3].shape = sphere(f32::NAN);
    let err = db.store.add_static_objects(map, &bad).await.unwrap_err();
    assert!(matches!(err, StoreError::InvalidInput(_)), "{err:?}");
    assert_eq!(db.store.get_static_objects(map).await.unwrap().len(), 10);
}

async fn seed_users_is_idempotent(db: TestDb) {
    let report = db.store.seed_users(20).await.unwrap();
    assert_eq!((report.created, report.skipped), (20, 0));
    let first = db.store.find_user("user7").await.unwrap().unwrap();
    let report = db.store.seed_users(25).await.unwrap();
    assert_eq!((report.created, report.skipped), (5, 20));
    let report = db.store.seed_users(25).await.unwrap();
    assert_eq!((report.created, report.skipped), (0, 25));
    // Existing users were left alone, new ones work.
    assert_eq!(db.store.find_user("user7").await.unwrap().unwrap(), first);
    db.store.check_credentials("user7", "password7").await.unwrap();
    db.store.check_credentials("user24", "password24").await.unwrap();
    assert!(db.store.find_user("user25").await.unwrap().is_none());
    let err = db.store.check_credentials("user3", "password4").await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
    assert_eq!(db.store.seed_users(0).await.unwrap().created, 0);
}

async fn reopening_keeps_data(db: TestDb) {
    let user = db.user("hank").await;
    let map = db.map("persist").await;
    let s = state(user, map, [3.0, 2.0, 1.0], 77);
    db.store.create_player_state(&s).await.unwrap();
    let again = db.reopen().await;
    again.check_credentials("hank", "pw-hank").await.unwrap();
    assert_eq!(again.get_player_state(user, map).await.unwrap(), s);
    again.close().await;
    let err = again.find_user("hank").await.unwrap_err();
    assert!(err.is_transient(), "closed pool is reported as unavailable: {err:?}");
}

#[tokio::test]
async fn bad_urls_and_costs_are_invalid_input() {
    use myriad_store::{HashCost, Store, StoreConfig};
    for url in ["postgres://localhost/db", "nonsense", "mysql://[::1"] {
        let err = Store::open(&StoreConfig::url(url)).await.unwrap_err();
        assert!(matches!(err, StoreError::InvalidInput(_)), "{url}: {err:?}");
    }
    let dir = tempfile::tempdir().unwrap();
    let config = StoreConfig::sqlite(dir.path()).hash_cost(HashCost { m_kib: 1, t: 1, p: 1 });
    let err = Store::open(&config).await.unwrap_err();
    assert!(matches!(err, StoreError::InvalidInput(_)), "{err:?}");
}

#[tokio::test]
async fn unreachable_server_is_unavailable() {
    use myriad_store::{Store, StoreConfig};
    // Nothing listens on port 1: connection refused.
    let mut config = StoreConfig::url("mysql://myriad:myriad@127.0.0.1:1/none");
    config.acquire_timeout = std::time::Duration::from_millis(300);
    let err = Store::open(&config).await.unwrap_err();
    assert!(matches!(err, StoreError::Unavailable(_)), "{err:?}");
    assert!(err.is_transient());
}

#[tokio::test]
async fn seed_users_refuses_absurd_counts() {
    let db = TestDb::sqlite().await;
    let err = db.store.seed_users(u32::MAX).await.unwrap_err();
    assert!(matches!(err, StoreError::InvalidInput(_)), "{err:?}");
}

#[tokio::test]
async fn sqlite_data_dir_is_created_with_wal() {
    use myriad_store::{SQLITE_FILE_NAME, Store, StoreConfig};
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("nested dir #1").join("data?");
    let store = Store::open(&StoreConfig::sqlite(&data).hash_cost(common::TEST_COST)).await.unwrap();
    store.create_user("walter", "pw").await.unwrap();
    assert!(data.join(SQLITE_FILE_NAME).is_file());
    // WAL mode leaves a -wal file next to the database while connections are open.
    assert!(data.join(format!("{SQLITE_FILE_NAME}-wal")).exists());
    store.close().await;
}

async fn password_change_and_user_deletion(db: TestDb) {
    let user = db.user("ivy").await;
    let map = db.map("admin").await;
    db.store.create_player_state(&state(user, map, [1.0, 2.0, 3.0], 1)).await.unwrap();

    db.store.set_password("IVY", "new-secret").await.unwrap();
    let err = db.store.check_credentials("ivy", "pw-ivy").await.unwrap_err();
    assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
    assert_eq!(db.store.check_credentials("ivy", "new-secret").await.unwrap().id, user);
    let err = db.store.set_password("nobody", "x").await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    let err = db.store.set_password("ivy", "").await.unwrap_err();
    assert!(matches!(err, StoreError::InvalidInput(_)), "{err:?}");

    db.store.delete_user("ivy").await.unwrap();
    assert!(db.store.find_user("ivy").await.unwrap().is_none());
    // The player's state went with the user (foreign key cascade).
    assert!(db.store.find_player_state(user, map).await.unwrap().is_none());
    let err = db.store.delete_user("ivy").await.unwrap_err();
    assert!(matches!(err, StoreError::NotFound(_)), "{err:?}");
    // The name is free again.
    db.store.create_user("ivy", "again").await.unwrap();
}
