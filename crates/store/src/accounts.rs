//! Account control for operators: list, disable and enable, ban and unban (issue 29).
//!
//! The flags live on the `users` row (migration 3) and are read by every password check
//! ([`Store::check_credentials`]), so a change made offline or by another process takes
//! effect at the account's next login without telling the server.

use sqlx::Row;
use sqlx::any::AnyRow;

use crate::error::{Result, StoreError};
use crate::model::{UserId, now_ms};
use crate::names::validate_username;
use crate::store::Store;

/// Longest ban reason in bytes (the MariaDB column is `VARCHAR(255)`).
pub const MAX_BAN_REASON_LEN: usize = 255;

/// A ban on an account.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ban {
    /// Why, as the operator wrote it.
    pub reason: String,
    /// When it was made, milliseconds since the Unix epoch.
    pub since_ms: i64,
    /// When it ends, milliseconds since the Unix epoch; `None`: it does not end.
    pub until_ms: Option<i64>,
}

impl Ban {
    /// Whether the ban is in force at `now_ms` (a timed ban ends by itself).
    pub fn in_force_at(&self, now_ms: i64) -> bool {
        self.until_ms.is_none_or(|until| until > now_ms)
    }
}

/// A user as an operator sees it: the [`User`](crate::User) fields and its controls.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Account {
    /// Database id.
    pub id: UserId,
    /// Username as stored.
    pub username: String,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: i64,
    /// Refused at login while set.
    pub disabled: bool,
    /// The last ban made, if not lifted; it may have ended ([`Ban::in_force_at`]).
    pub ban: Option<Ban>,
}

/// Columns of [`Account`] that [`account_from_row`] reads, as a literal for `concat!`
/// (constant SQL text, nothing formatted in at run time).
macro_rules! account_columns {
    () => {
        "id, username, created_at, disabled, banned_at, ban_until, ban_reason"
    };
}
pub(crate) use account_columns;

/// Reads an [`Account`] from a row selected with `account_columns!()`.
pub(crate) fn account_from_row(row: &AnyRow) -> Result<Account> {
    let banned_at: Option<i64> = row.try_get("banned_at")?;
    let ban = match banned_at {
        Some(since_ms) => Some(Ban {
            reason: row.try_get::<Option<String>, _>("ban_reason")?.unwrap_or_default(),
            since_ms,
            until_ms: row.try_get("ban_until")?,
        }),
        None => None,
    };
    Ok(Account {
        id: UserId(row.try_get("id")?),
        username: row.try_get("username")?,
        created_at_ms: row.try_get("created_at")?,
        disabled: row.try_get::<i64, _>("disabled")? != 0,
        ban,
    })
}

impl Account {
    /// Why this account may not log in at `now_ms`, if it may not: disabled first (it
    /// lasts until an operator enables it), then a ban in force.
    pub fn refusal_at(&self, now_ms: i64) -> Option<StoreError> {
        if self.disabled {
            return Some(StoreError::AccountDisabled);
        }
        match &self.ban {
            Some(ban) if ban.in_force_at(now_ms) => Some(StoreError::AccountBanned { until_ms: ban.until_ms }),
            _ => None,
        }
    }
}

/// Checks a ban reason: 1 to [`MAX_BAN_REASON_LEN`] bytes, no control characters (it is
/// printed on operators' terminals, where escape sequences would be obeyed).
pub fn validate_ban_reason(reason: &str) -> Result<()> {
    if reason.trim().is_empty() || reason.len() > MAX_BAN_REASON_LEN {
        return Err(StoreError::InvalidInput(format!("a ban reason is 1 to {MAX_BAN_REASON_LEN} bytes")));
    }
    if reason.chars().any(char::is_control) {
        return Err(StoreError::InvalidInput("a ban reason may not contain control characters".into()));
    }
    Ok(())
}

impl Store {
    /// Up to `limit` accounts with an id above `after` (all from the start when `None`),
    /// by id: page through every account without holding them all.
    pub async fn list_accounts(&self, after: Option<UserId>, limit: u32) -> Result<Vec<Account>> {
        let rows = sqlx::query(concat!("SELECT ", account_columns!(), " FROM users WHERE id > ? ORDER BY id LIMIT ?"))
            .bind(after.map_or(i64::MIN, |id| id.0))
            .bind(i64::from(limit))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(account_from_row).collect()
    }

    /// Up to `limit` accounts by id, skipping the first `offset` (the admin API's pages).
    pub async fn accounts_page(&self, offset: u32, limit: u32) -> Result<Vec<Account>> {
        let rows = sqlx::query(concat!("SELECT ", account_columns!(), " FROM users ORDER BY id LIMIT ? OFFSET ?"))
            .bind(i64::from(limit))
            .bind(i64::from(offset))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(account_from_row).collect()
    }

    /// One account by name (case-insensitively); `None` if there is none.
    pub async fn account(&self, username: &str) -> Result<Option<Account>> {
        let sql = concat!("SELECT ", account_columns!(), " FROM users WHERE username = ?");
        let row = sqlx::query(sql).bind(username).fetch_optional(&self.pool).await?;
        row.as_ref().map(account_from_row).transpose()
    }

    /// Disables (`true`) or enables (`false`) an account: a disabled account is refused
    /// at login with [`StoreError::AccountDisabled`]. Fails with [`StoreError::NotFound`]
    /// for an unknown user.
    pub async fn set_disabled(&self, username: &str, disabled: bool) -> Result<()> {
        validate_username(username)?;
        let done = sqlx::query("UPDATE users SET disabled = ? WHERE username = ?")
            .bind(i64::from(disabled))
            .bind(username)
            .execute(&self.pool)
            .await?;
        expect_one(done.rows_affected(), username)
    }

    /// Bans an account (replacing any earlier ban) until `until_ms` (milliseconds since
    /// the Unix epoch, which must be in the future) or, with `None`, without end. A banned
    /// account is refused at login with [`StoreError::AccountBanned`].
    pub async fn ban(&self, username: &str, reason: &str, until_ms: Option<i64>) -> Result<()> {
        validate_username(username)?;
        validate_ban_reason(reason)?;
        let now = now_ms();
        if until_ms.is_some_and(|until| until <= now) {
            return Err(StoreError::InvalidInput("the ban's end is not in the future".into()));
        }
        let done = sqlx::query("UPDATE users SET banned_at = ?, ban_until = ?, ban_reason = ? WHERE username = ?")
            .bind(now)
            .bind(until_ms)
            .bind(reason)
            .bind(username)
            .execute(&self.pool)
            .await?;
        expect_one(done.rows_affected(), username)
    }

    /// Lifts an account's ban (a no-op on an account without one). Fails with
    /// [`StoreError::NotFound`] for an unknown user.
    pub async fn unban(&self, username: &str) -> Result<()> {
        validate_username(username)?;
        let done =
            sqlx::query("UPDATE users SET banned_at = NULL, ban_until = NULL, ban_reason = NULL WHERE username = ?")
                .bind(username)
                .execute(&self.pool)
                .await?;
        expect_one(done.rows_affected(), username)
    }
}

/// `NotFound` unless an update matched the user's row. (sqlx asks MariaDB for matched
/// rather than changed rows, `CLIENT_FOUND_ROWS`, so enabling an enabled account counts 1
/// on both backends.)
fn expect_one(rows: u64, username: &str) -> Result<()> {
    if rows == 0 { Err(StoreError::NotFound(format!("user {username:?}"))) } else { Ok(()) }
}
