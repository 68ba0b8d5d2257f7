//! Account control (disable, ban, list) and integrity checks, each run on SQLite and on
//! MySQL/MariaDB (see `common`).

mod common;

use std::time::Duration;

use common::TestDb;
use myriad_store::{CheckDepth, StoreError, UserId, check_database, now_ms};

backend_tests!(
    disabled_accounts_are_refused_only_with_the_right_password,
    bans_refuse_until_their_end,
    accounts_are_listed_by_pages,
    account_commands_on_unknown_users_fail,
    an_intact_database_passes_its_check,
);

async fn disabled_accounts_are_refused_only_with_the_right_password(db: TestDb) {
    let s = &db.store;
    db.user("dora").await;
    s.set_disabled("dora", true).await.unwrap();
    assert!(s.account("dora").await.unwrap().unwrap().disabled);
    assert!(matches!(s.check_credentials("dora", "pw-dora").await, Err(StoreError::AccountDisabled)));
    // A wrong guess learns nothing about the account's state.
    assert!(matches!(s.check_credentials("dora", "nope").await, Err(StoreError::WrongCredentials)));
    // Enabling twice is fine (MariaDB counts matched rows, not changed ones).
    s.set_disabled("DORA", false).await.unwrap();
    s.set_disabled("dora", false).await.unwrap();
    s.check_credentials("dora", "pw-dora").await.expect("enabled again");
}

async fn bans_refuse_until_their_end(db: TestDb) {
    let s = &db.store;
    db.user("bart").await;
    db.user("lisa").await;
    s.ban("bart", "griefing", None).await.unwrap();
    let account = s.account("bart").await.unwrap().unwrap();
    let ban = account.ban.expect("banned");
    assert_eq!((ban.reason.as_str(), ban.until_ms), ("griefing", None));
    assert!(matches!(s.check_credentials("bart", "pw-bart").await, Err(StoreError::AccountBanned { until_ms: None })));
    s.unban("bart").await.unwrap();
    assert_eq!(s.account("bart").await.unwrap().unwrap().ban, None);
    s.check_credentials("bart", "pw-bart").await.expect("unbanned");

    // A timed ban ends by itself.
    let until = now_ms() + 1500;
    s.ban("lisa", "spam", Some(until)).await.unwrap();
    match s.check_credentials("lisa", "pw-lisa").await {
        Err(StoreError::AccountBanned { until_ms }) => assert_eq!(until_ms, Some(until)),
        other => panic!("expected a ban, got {other:?}"),
    }
    tokio::time::sleep(Duration::from_millis(u64::try_from(until - now_ms()).unwrap_or(0) + 50)).await;
    s.check_credentials("lisa", "pw-lisa").await.expect("the ban has ended");
    assert!(!s.account("lisa").await.unwrap().unwrap().ban.unwrap().in_force_at(now_ms()));

    // Bad reasons and ends in the past are refused.
    assert!(matches!(s.ban("bart", "", None).await, Err(StoreError::InvalidInput(_))));
    assert!(matches!(s.ban("bart", "a\x1b[2Jb", None).await, Err(StoreError::InvalidInput(_))));
    assert!(matches!(s.ban("bart", &"x".repeat(256), None).await, Err(StoreError::InvalidInput(_))));
    assert!(matches!(s.ban("bart", "late", Some(now_ms() - 1)).await, Err(StoreError::InvalidInput(_))));
}

async fn accounts_are_listed_by_pages(db: TestDb) {
    let s = &db.store;
    s.seed_users(7).await.unwrap();
    s.ban("user3", "test", None).await.unwrap();
    let mut seen = Vec::new();
    let mut after: Option<UserId> = None;
    loop {
        let page = s.list_accounts(after, 3).await.unwrap();
        if page.is_empty() {
            break;
        }
        assert!(page.len() <= 3);
        after = page.last().map(|a| a.id);
        seen.extend(page);
    }
    assert_eq!(seen.len(), 7);
    assert!(seen.windows(2).all(|w| w[0].id < w[1].id), "by id");
    assert_eq!(seen.iter().filter(|a| a.ban.is_some()).map(|a| a.username.as_str()).collect::<Vec<_>>(), ["user3"]);
}

async fn account_commands_on_unknown_users_fail(db: TestDb) {
    let s = &db.store;
    assert!(matches!(s.set_disabled("ghost", true).await, Err(StoreError::NotFound(_))));
    assert!(matches!(s.ban("ghost", "x", None).await, Err(StoreError::NotFound(_))));
    assert!(matches!(s.unban("ghost").await, Err(StoreError::NotFound(_))));
    assert_eq!(s.account("ghost").await.unwrap(), None);
}

async fn an_intact_database_passes_its_check(db: TestDb) {
    db.user("carl").await;
    for depth in [CheckDepth::Quick, CheckDepth::Full] {
        let report = check_database(&db.config.database, depth).await.expect("check runs");
        assert!(report.is_intact(), "{report:?}");
        assert!(!report.database.contains("myriad:myriad@"), "no password in {}", report.database);
        if db.dialect() == myriad_store::Dialect::MySql {
            assert!(report.tables.iter().any(|t| t == "users"), "{report:?}");
        }
    }
}
