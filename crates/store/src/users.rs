//! Users: creation, credential checks, test-user seeding.
//!
//! The reference's `NewUser`, `CheckUser` and `CheckUserAndRetrieveInfo` procedures.

use sqlx::{Any, QueryBuilder, Row};

use crate::accounts::{account_columns, account_from_row};
use crate::error::{Result, StoreError, is_unique_violation};
use crate::model::{LoginInfo, MapId, SeedReport, UserId, now_ms};
use crate::names::validate_username;
use crate::password::{self, validate_password};
use crate::store::{Dialect, Store};

/// Most users one `seed_users` call creates (test worlds; keeps memory bounded).
pub const MAX_SEED_USERS: u32 = 1_000_000;

/// Rows per multi-row statement when seeding users (3 binds per row).
const SEED_CHUNK: usize = 500;

/// A stored user, without its password hash.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct User {
    /// Database id.
    pub id: UserId,
    /// Username as stored.
    pub username: String,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: i64,
}

impl Store {
    /// Creates a user with an Argon2id hash of `password` (the reference's `NewUser`).
    ///
    /// Usernames are 1 to 32 bytes of ASCII letters, digits, `_`, `-`, `.`, unique
    /// case-insensitively; passwords are 1 to 64 bytes. Fails with
    /// [`StoreError::InvalidInput`] or [`StoreError::UsernameTaken`].
    pub async fn create_user(&self, username: &str, password: &str) -> Result<UserId> {
        validate_username(username)?;
        validate_password(password)?;
        // Fail fast before spending a hash on a name that is taken; the unique index still
        // decides when two creations race.
        if self.find_user(username).await?.is_some() {
            return Err(StoreError::UsernameTaken);
        }
        let hash = password::hash_password(self.hash_cost, password).await?;
        // sqlx's Any driver reports no last-insert id for SQLite, and MySQL has no
        // RETURNING, so the id is read back by the unique name in the same transaction.
        let mut tx = self.pool.begin().await?;
        let inserted = sqlx::query("INSERT INTO users (username, password_hash, created_at) VALUES (?, ?, ?)")
            .bind(username)
            .bind(hash)
            .bind(now_ms())
            .execute(&mut *tx)
            .await;
        match inserted {
            Ok(_) => {}
            Err(e) if is_unique_violation(&e) => return Err(StoreError::UsernameTaken),
            Err(e) => return Err(e.into()),
        }
        let id: i64 =
            sqlx::query_scalar("SELECT id FROM users WHERE username = ?").bind(username).fetch_one(&mut *tx).await?;
        tx.commit().await?;
        Ok(UserId(id))
    }

    /// Looks a user up by name (case-insensitively); `None` if there is none.
    pub async fn find_user(&self, username: &str) -> Result<Option<User>> {
        let row = sqlx::query("SELECT id, username, created_at FROM users WHERE username = ?")
            .bind(username)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|row| {
            Ok(User {
                id: UserId(row.try_get("id")?),
                username: row.try_get("username")?,
                created_at_ms: row.try_get("created_at")?,
            })
        })
        .transpose()
    }

    /// Checks a username and password (the reference's `CheckUser`).
    ///
    /// Returns the user on success and [`StoreError::WrongCredentials`] both when the
    /// password is wrong and when the user does not exist. In the second case a dummy hash
    /// of the same cost is verified anyway, so the answer takes as long either way and its
    /// timing does not reveal which usernames exist. Malformed input (wrong length, bad
    /// characters) is [`StoreError::InvalidInput`]: those limits are public.
    ///
    /// With the right password, a disabled account fails with
    /// [`StoreError::AccountDisabled`] and a banned one with
    /// [`StoreError::AccountBanned`] (only then: a wrong guess learns nothing about them).
    pub async fn check_credentials(&self, username: &str, password: &str) -> Result<User> {
        validate_username(username)?;
        validate_password(password)?;
        let sql = concat!("SELECT ", account_columns!(), ", password_hash FROM users WHERE username = ?");
        let row = sqlx::query(sql).bind(username).fetch_optional(&self.pool).await?;
        let (account, hash) = match row {
            Some(row) => (Some(account_from_row(&row)?), row.try_get::<String, _>("password_hash")?),
            None => (None, self.dummy_hash.to_string()),
        };
        let matches = password::verify_password(password, hash).await?;
        match account {
            Some(account) if matches => match account.refusal_at(now_ms()) {
                Some(refusal) => Err(refusal),
                None => Ok(User { id: account.id, username: account.username, created_at_ms: account.created_at_ms }),
            },
            _ => Err(StoreError::WrongCredentials),
        }
    }

    /// Checks credentials and fetches the player's state on `map` (the reference's
    /// `CheckUserAndRetrieveInfo`). The state is `None` when the user has never been on
    /// that map.
    pub async fn login(&self, username: &str, password: &str, map: MapId) -> Result<LoginInfo> {
        let user = self.check_credentials(username, password).await?;
        let state = self.find_player_state(user.id, map).await?;
        Ok(LoginInfo { user_id: user.id, username: user.username, state })
    }

    /// Replaces a user's password (for an admin command; the caller has authorised it).
    /// Fails with [`StoreError::NotFound`] for an unknown user.
    pub async fn set_password(&self, username: &str, new_password: &str) -> Result<()> {
        validate_username(username)?;
        validate_password(new_password)?;
        let hash = password::hash_password(self.hash_cost, new_password).await?;
        let done = sqlx::query("UPDATE users SET password_hash = ? WHERE username = ?")
            .bind(hash)
            .bind(username)
            .execute(&self.pool)
            .await?;
        if done.rows_affected() == 0 {
            return Err(StoreError::NotFound(format!("user {username:?}")));
        }
        Ok(())
    }

    /// Deletes a user and, by cascade, their player states. Fails with
    /// [`StoreError::NotFound`] for an unknown user.
    pub async fn delete_user(&self, username: &str) -> Result<()> {
        let done = sqlx::query("DELETE FROM users WHERE username = ?").bind(username).execute(&self.pool).await?;
        if done.rows_affected() == 0 {
            return Err(StoreError::NotFound(format!("user {username:?}")));
        }
        Ok(())
    }

    /// Creates the reference's test users `user<i>` with password `password<i>` for
    /// `i` in `0..count`. Existing users are skipped (their passwords are not reset), so
    /// calling it again is harmless.
    ///
    /// Missing users are hashed in parallel on the blocking pool (one task per CPU) and
    /// inserted in transactions of 500 rows. At most [`MAX_SEED_USERS`].
    pub async fn seed_users(&self, count: u32) -> Result<SeedReport> {
        if count > MAX_SEED_USERS {
            return Err(StoreError::InvalidInput(format!("seed_users is limited to {MAX_SEED_USERS} users")));
        }
        let names: Vec<u32> = (0..count).collect();
        let mut missing = Vec::new();
        for chunk in names.chunks(SEED_CHUNK) {
            let mut qb: QueryBuilder<Any> = QueryBuilder::new("SELECT username FROM users WHERE username IN (");
            let mut list = qb.separated(", ");
            for i in chunk {
                list.push_bind(format!("user{i}"));
            }
            qb.push(")");
            let rows = qb.build().persistent(false).fetch_all(&self.pool).await?;
            let existing: std::collections::HashSet<String> = rows
                .iter()
                .map(|r| r.try_get::<String, _>(0).map(|s| s.to_ascii_lowercase()))
                .collect::<Result<_, _>>()?;
            missing.extend(chunk.iter().copied().filter(|i| !existing.contains(&format!("user{i}"))));
        }
        let skipped = count - u32::try_from(missing.len()).unwrap_or(count);
        if missing.is_empty() {
            return Ok(SeedReport { created: 0, skipped });
        }

        let hashed = self.hash_seed_passwords(&missing).await?;
        let created_at = now_ms();
        let mut created = 0u64;
        for chunk in hashed.chunks(SEED_CHUNK) {
            // Insert-or-ignore: a user created concurrently since the check is skipped
            // rather than failing the whole batch.
            let head = match self.dialect {
                Dialect::Sqlite => "INSERT OR IGNORE INTO users (username, password_hash, created_at) ",
                Dialect::MySql => "INSERT IGNORE INTO users (username, password_hash, created_at) ",
            };
            let mut qb: QueryBuilder<Any> = QueryBuilder::new(head);
            qb.push_values(chunk, |mut row, (name, hash)| {
                row.push_bind(name.clone()).push_bind(hash.clone()).push_bind(created_at);
            });
            let mut tx = self.pool.begin().await?;
            // One-off statements: not kept in the statement cache.
            created += qb.build().persistent(false).execute(&mut *tx).await?.rows_affected();
            tx.commit().await?;
        }
        let created = u32::try_from(created).unwrap_or(u32::MAX);
        Ok(SeedReport { created, skipped: count - created })
    }

    /// Hashes `password<i>` for every index, spread over one blocking task per CPU.
    async fn hash_seed_passwords(&self, indices: &[u32]) -> Result<Vec<(String, String)>> {
        let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
        let per_worker = indices.len().div_ceil(workers);
        let cost = self.hash_cost;
        let mut tasks = Vec::new();
        for part in indices.chunks(per_worker.max(1)) {
            let part = part.to_vec();
            tasks.push(tokio::task::spawn_blocking(move || {
                part.into_iter()
                    .map(|i| {
                        let hash = password::hash_blocking(cost, format!("password{i}").as_bytes())?;
                        Ok((format!("user{i}"), hash))
                    })
                    .collect::<Result<Vec<_>>>()
            }));
        }
        let mut out = Vec::with_capacity(indices.len());
        for task in tasks {
            let part = task.await.map_err(|e| StoreError::Internal(format!("hashing task failed: {e}")))??;
            out.extend(part);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use crate::password::VERIFIED_HASHES;
    use crate::{HashCost, Store, StoreConfig, StoreError};

    /// A PHC string's algorithm, version and cost (`$argon2id$v=19$m=…,t=…,p=…`), without
    /// its salt and output.
    fn cost_part(phc: &str) -> String {
        phc.split('$').take(4).collect::<Vec<_>>().join("$")
    }

    /// An unknown username must cost a verification of the same cost as a wrong password,
    /// or login timing tells which usernames exist. Checked by the work each login asked
    /// for rather than by a clock: timings on a shared machine decide nothing.
    #[tokio::test]
    async fn an_unknown_user_costs_the_same_verification_as_a_wrong_password() {
        let dir = tempfile::tempdir().unwrap();
        let cost = HashCost { m_kib: 512, t: 2, p: 1 };
        let store = Store::open(&StoreConfig::sqlite(dir.path()).hash_cost(cost)).await.unwrap();
        store.create_user("known", "right-password").await.unwrap();
        let stored: String = sqlx::query_scalar("SELECT password_hash FROM users WHERE username = ?")
            .bind("known")
            .fetch_one(&store.pool)
            .await
            .unwrap();
        let asked = |phc: &str| VERIFIED_HASHES.lock().unwrap_or_else(|p| p.into_inner()).iter().any(|h| h == phc);
        assert!(!asked(&stored) && !asked(&store.dummy_hash), "nothing checked yet");

        let err = store.check_credentials("known", "wrong").await.unwrap_err();
        assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
        assert!(asked(&stored), "a wrong password is checked against the user's hash");
        assert!(!asked(&store.dummy_hash));

        let err = store.check_credentials("ghost", "wrong").await.unwrap_err();
        assert!(matches!(err, StoreError::WrongCredentials), "{err:?}");
        assert!(asked(&store.dummy_hash), "an unknown user is checked against the dummy hash");
        assert_eq!(cost_part(&store.dummy_hash), cost_part(&stored), "the same algorithm and cost");
        assert_eq!(cost_part(&stored), "$argon2id$v=19$m=512,t=2,p=1");
        store.close().await;
    }
}
