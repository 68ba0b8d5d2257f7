//! Issue 29: disabled and banned accounts are refused at login with their own reasons
//! (told only after a correct password), a timed ban ends by itself, and an older client
//! gets a reason it understands. Through the real TLS login path.

use std::time::Duration;

use myriad_client::{ClientConfig, ClientError, Connection, Credentials, Trust};
use myriad_protocol::login::RefusalReason;
use myriad_server::{ServerConfig, ServerHandle};
use myriad_store::{Store, now_ms};

mod common;

fn refusal(result: Result<Connection, ClientError>) -> (RefusalReason, u32) {
    match result {
        Err(ClientError::Refused { reason, retry_after_ms }) => (reason, retry_after_ms),
        Err(e) => panic!("expected a refusal, got {e:?}"),
        Ok(_) => panic!("expected a refusal, the login was accepted"),
    }
}

#[test]
fn disabled_and_banned_accounts_are_refused_with_their_reasons() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig { persist_interval_ms: 100, ..common::small_server(dir.path(), 50) };
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    // Set up offline, as `myriad user ban/disable` does on a stopped server.
    let ban_ends = now_ms() + 3000;
    rt.block_on(async {
        let store = Store::open(&myriad_server::store_config(&cfg)).await.unwrap();
        store.seed_users(4).await.unwrap();
        store.set_disabled("user1", true).await.unwrap();
        store.ban("user2", "cheating", None).await.unwrap();
        store.ban("user3", "cool down", Some(ban_ends)).await.unwrap();
        store.close().await;
    });
    let server = ServerHandle::start(cfg).unwrap();
    let trust = Trust::pin_file(server.certificate_path()).unwrap();
    let mut cc = ClientConfig::new(server.login_addr(), &trust).unwrap();
    cc.login_timeout = Duration::from_secs(20);
    rt.block_on(async {
        let ok = Connection::connect(cc.clone(), Credentials::test_user(0)).await.expect("user0 logs in");
        drop(ok);
        assert_eq!(
            refusal(Connection::connect(cc.clone(), Credentials::test_user(1)).await).0,
            RefusalReason::Disabled
        );
        assert_eq!(
            refusal(Connection::connect(cc.clone(), Credentials::test_user(2)).await),
            (RefusalReason::Banned, 0),
            "a ban without end has no retry hint"
        );
        let (reason, left) = refusal(Connection::connect(cc.clone(), Credentials::test_user(3)).await);
        assert_eq!(reason, RefusalReason::Banned);
        assert!(left > 0 && left <= 3000, "the time left of the ban: {left} ms");
        // A wrong password on a banned account is a wrong password: nothing is revealed.
        let guess = Credentials { username: "user2".into(), password: "guess".into() };
        assert_eq!(refusal(Connection::connect(cc.clone(), guess).await).0, RefusalReason::WrongCredentials);
        // A client before login version 5 speaks an older datagram protocol: it is
        // refused before its credentials are judged (right ones included), with the
        // nearest reason it knows.
        for (version, told) in
            [(2, RefusalReason::BadRequest), (3, RefusalReason::BadRequest), (4, RefusalReason::OutdatedClient)]
        {
            let old = ClientConfig { login_version: version, ..cc.clone() };
            assert_eq!(
                refusal(Connection::connect(old.clone(), Credentials::test_user(0)).await).0,
                told,
                "login version {version}"
            );
        }
        // The timed ban ends by itself; changes made in the database while the server
        // runs count at the next login.
        tokio::time::sleep(Duration::from_millis(u64::from(left) + 100)).await;
        let back = Connection::connect(cc.clone(), Credentials::test_user(3)).await.expect("the ban ended");
        drop(back);
        server.store().set_disabled("user1", false).await.unwrap();
        let enabled = Connection::connect(cc.clone(), Credentials::test_user(1)).await.expect("enabled again");
        drop(enabled);
    });
    server.shutdown().unwrap();
}

#[test]
fn a_second_server_on_the_same_database_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::small_server(dir.path(), 10);
    let first = ServerHandle::start(cfg.clone()).unwrap();
    let second = ServerHandle::start(cfg.clone()).unwrap_err().to_string();
    assert!(second.contains("in use") && second.contains("myriad.db.lock"), "{second}");
    first.shutdown().unwrap();
    // The lock goes with the server.
    ServerHandle::start(cfg).unwrap().shutdown().unwrap();
}
