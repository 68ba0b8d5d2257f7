//! The admin API's audit trail (migration 4), on SQLite and on MySQL/MariaDB (see
//! `common`): appended entries come back newest first, long text is cut to the
//! columns' sizes (never refused), and accounts are paged by offset.

mod common;

use common::TestDb;
use myriad_store::{AuditEntry, MAX_AUDIT_LIST};

backend_tests!(entries_come_back_newest_first_and_long_text_is_cut, accounts_are_paged_by_offset);

fn entry(n: i64, action: &str, ok: bool) -> AuditEntry {
    AuditEntry {
        at_ms: 1_000 + n,
        actor: "token:alice".into(),
        action: action.into(),
        target: format!("user{n}"),
        detail: format!("reason {n}"),
        from: "127.0.0.1:40000".into(),
        ok,
    }
}

async fn entries_come_back_newest_first_and_long_text_is_cut(db: TestDb) {
    let s = &db.store;
    assert!(s.list_audit(10).await.unwrap().is_empty());
    for n in 0..5 {
        s.append_audit(&entry(n, if n % 2 == 0 { "kick" } else { "ban" }, n != 3)).await.unwrap();
    }
    let all = s.list_audit(10).await.unwrap();
    assert_eq!(all.len(), 5);
    assert_eq!(all[0], entry(4, "kick", true), "newest first, every field kept");
    assert_eq!(all[1], entry(3, "ban", false));
    assert_eq!(s.list_audit(2).await.unwrap(), all[..2]);
    // A junk path of a refused request is longer than any column: cut, still written.
    let long = AuditEntry {
        target: "/api/".to_string() + &"é".repeat(400),
        detail: "d".repeat(5000),
        ..entry(9, "refused", false)
    };
    s.append_audit(&long).await.unwrap();
    let newest = &s.list_audit(1).await.unwrap()[0];
    assert!(newest.target.len() <= 255 && newest.target.starts_with("/api/éé"), "{}", newest.target.len());
    assert_eq!(newest.detail.len(), 1024);
    assert_eq!(s.list_audit(MAX_AUDIT_LIST + 5).await.unwrap().len(), 6, "the limit is capped, not refused");
}

async fn accounts_are_paged_by_offset(db: TestDb) {
    for name in ["a1", "a2", "a3", "a4"] {
        db.user(name).await;
    }
    let s = &db.store;
    let names = |page: Vec<myriad_store::Account>| page.into_iter().map(|a| a.username).collect::<Vec<_>>();
    assert_eq!(names(s.accounts_page(0, 2).await.unwrap()), ["a1", "a2"]);
    assert_eq!(names(s.accounts_page(2, 10).await.unwrap()), ["a3", "a4"]);
    assert!(s.accounts_page(10, 10).await.unwrap().is_empty());
}
