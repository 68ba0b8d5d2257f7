//! Per-map player state: the reference's `NewUserGameInfo`, `UpdateUserGameInfo` and
//! `GetUserGameInfo`, plus the batched upsert behind the write-behind persister.

use std::collections::HashMap;

use sqlx::any::AnyRow;
use sqlx::{Any, QueryBuilder, Row};

use crate::error::{Result, StoreError, is_unique_violation};
use crate::model::{MapId, PlayerState, StoredShape, UserId};
use crate::store::{Dialect, Store};

/// Rows per multi-row upsert statement (11 binds per row, far below SQLite's 32766 and
/// MySQL's 65535 placeholder limits). A fixed size keeps the prepared statements reused.
pub(crate) const UPSERT_CHUNK: usize = 250;

const COLUMNS: &str = "user_id, map_id, shape_kind, radius, half_x, half_y, half_z, \
                       pos_x, pos_y, pos_z, updated_at";

/// Upsert tails. A row is only overwritten by a state at least as new as the stored one,
/// so a late write-behind batch can never roll back a newer direct update.
const SQLITE_UPSERT: &str = " ON CONFLICT (user_id, map_id) DO UPDATE SET \
    shape_kind = excluded.shape_kind, radius = excluded.radius, \
    half_x = excluded.half_x, half_y = excluded.half_y, half_z = excluded.half_z, \
    pos_x = excluded.pos_x, pos_y = excluded.pos_y, pos_z = excluded.pos_z, \
    updated_at = excluded.updated_at \
    WHERE excluded.updated_at >= player_state.updated_at";

/// MySQL evaluates the assignments left to right, so `updated_at` must come last: every
/// condition before it still sees the stored time.
const MYSQL_UPSERT: &str = " ON DUPLICATE KEY UPDATE \
    shape_kind = IF(VALUES(updated_at) >= updated_at, VALUES(shape_kind), shape_kind), \
    radius = IF(VALUES(updated_at) >= updated_at, VALUES(radius), radius), \
    half_x = IF(VALUES(updated_at) >= updated_at, VALUES(half_x), half_x), \
    half_y = IF(VALUES(updated_at) >= updated_at, VALUES(half_y), half_y), \
    half_z = IF(VALUES(updated_at) >= updated_at, VALUES(half_z), half_z), \
    pos_x = IF(VALUES(updated_at) >= updated_at, VALUES(pos_x), pos_x), \
    pos_y = IF(VALUES(updated_at) >= updated_at, VALUES(pos_y), pos_y), \
    pos_z = IF(VALUES(updated_at) >= updated_at, VALUES(pos_z), pos_z), \
    updated_at = GREATEST(updated_at, VALUES(updated_at))";

fn state_from_row(row: &AnyRow) -> Result<PlayerState> {
    let shape = StoredShape::from_columns(
        row.try_get("shape_kind")?,
        row.try_get("radius")?,
        [row.try_get("half_x")?, row.try_get("half_y")?, row.try_get("half_z")?],
    )?;
    let pos: [f64; 3] = [row.try_get("pos_x")?, row.try_get("pos_y")?, row.try_get("pos_z")?];
    Ok(PlayerState {
        user_id: UserId(row.try_get("user_id")?),
        map_id: MapId(row.try_get("map_id")?),
        shape,
        // Written from f32, so exact.
        position: pos.map(|c| c as f32),
        updated_at_ms: row.try_get("updated_at")?,
    })
}

/// Whether a database error is a foreign-key violation (unknown user or map).
fn is_foreign_key_violation(err: &sqlx::Error) -> bool {
    err.as_database_error().is_some_and(|db| db.is_foreign_key_violation())
}

impl Store {
    /// Creates a player's state on a map (the reference's `NewUserGameInfo`). Fails with
    /// [`StoreError::AlreadyExists`] if there is one, [`StoreError::NotFound`] if the user
    /// or the map does not exist.
    pub async fn create_player_state(&self, state: &PlayerState) -> Result<()> {
        state.validate()?;
        let c = state.shape.to_columns();
        let result = sqlx::query(
            "INSERT INTO player_state (user_id, map_id, shape_kind, radius, half_x, half_y, \
             half_z, pos_x, pos_y, pos_z, updated_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(state.user_id.0)
        .bind(state.map_id.0)
        .bind(c.kind)
        .bind(c.radius)
        .bind(c.half[0])
        .bind(c.half[1])
        .bind(c.half[2])
        .bind(f64::from(state.position[0]))
        .bind(f64::from(state.position[1]))
        .bind(f64::from(state.position[2]))
        .bind(state.updated_at_ms)
        .execute(&self.pool)
        .await;
        match result {
            Ok(_) => Ok(()),
            Err(e) if is_unique_violation(&e) => Err(StoreError::AlreadyExists(format!(
                "player state of user {} on map {}",
                state.user_id.0, state.map_id.0
            ))),
            Err(e) if is_foreign_key_violation(&e) => {
                Err(StoreError::NotFound(format!("user {} or map {}", state.user_id.0, state.map_id.0)))
            }
            Err(e) => Err(e.into()),
        }
    }

    /// Overwrites a player's shape, position and time on a map (the reference's
    /// `UpdateUserGameInfo`). Fails with [`StoreError::NotFound`] if there is no state.
    pub async fn update_player_state(&self, state: &PlayerState) -> Result<()> {
        state.validate()?;
        let c = state.shape.to_columns();
        let done = sqlx::query(
            "UPDATE player_state SET shape_kind = ?, radius = ?, half_x = ?, half_y = ?, \
             half_z = ?, pos_x = ?, pos_y = ?, pos_z = ?, updated_at = ? \
             WHERE user_id = ? AND map_id = ?",
        )
        .bind(c.kind)
        .bind(c.radius)
        .bind(c.half[0])
        .bind(c.half[1])
        .bind(c.half[2])
        .bind(f64::from(state.position[0]))
        .bind(f64::from(state.position[1]))
        .bind(f64::from(state.position[2]))
        .bind(state.updated_at_ms)
        .bind(state.user_id.0)
        .bind(state.map_id.0)
        .execute(&self.pool)
        .await?;
        // MySQL counts matched rows here, not changed ones: sqlx sets CLIENT_FOUND_ROWS.
        if done.rows_affected() == 0 {
            return Err(StoreError::NotFound(format!(
                "player state of user {} on map {}",
                state.user_id.0, state.map_id.0
            )));
        }
        Ok(())
    }

    /// A player's state on a map (the reference's `GetUserGameInfo`), or
    /// [`StoreError::NotFound`].
    pub async fn get_player_state(&self, user: UserId, map: MapId) -> Result<PlayerState> {
        self.find_player_state(user, map)
            .await?
            .ok_or_else(|| StoreError::NotFound(format!("player state of user {} on map {}", user.0, map.0)))
    }

    /// A player's state on a map, or `None`.
    pub async fn find_player_state(&self, user: UserId, map: MapId) -> Result<Option<PlayerState>> {
        let row = sqlx::query(
            "SELECT user_id, map_id, shape_kind, radius, half_x, half_y, half_z, \
             pos_x, pos_y, pos_z, updated_at FROM player_state WHERE user_id = ? AND map_id = ?",
        )
        .bind(user.0)
        .bind(map.0)
        .fetch_optional(&self.pool)
        .await?;
        row.as_ref().map(state_from_row).transpose()
    }

    /// Inserts or updates many player states in one transaction, with multi-row upserts
    /// of 250 rows. Returns the number of distinct (user, map) states written.
    ///
    /// When the slice holds several states of one player on one map, the one with the
    /// newest `updated_at_ms` wins (the later one on ties). A stored state newer than the
    /// given one is kept. Every state is validated first; one invalid state rejects the
    /// whole call with [`StoreError::InvalidInput`] and writes nothing. An unknown user or
    /// map fails the whole transaction with [`StoreError::Database`].
    pub async fn save_player_states(&self, states: &[PlayerState]) -> Result<u64> {
        for state in states {
            state.validate()?;
        }
        // Deduplicate: SQLite and MySQL would apply duplicates in order, but the order of
        // rows inside one statement is not something to rely on.
        let mut newest: HashMap<(i64, i64), usize> = HashMap::with_capacity(states.len());
        for (i, s) in states.iter().enumerate() {
            newest
                .entry((s.user_id.0, s.map_id.0))
                .and_modify(|j| {
                    if s.updated_at_ms >= states[*j].updated_at_ms {
                        *j = i;
                    }
                })
                .or_insert(i);
        }
        let mut rows: Vec<&PlayerState> = newest.into_values().map(|i| &states[i]).collect();
        if rows.is_empty() {
            return Ok(0);
        }
        // A stable order makes concurrent batches lock rows in the same order (no
        // deadlocks on MySQL) and keeps the index insertions sequential.
        rows.sort_unstable_by_key(|s| (s.user_id.0, s.map_id.0));

        let tail = match self.dialect {
            Dialect::Sqlite => SQLITE_UPSERT,
            Dialect::MySql => MYSQL_UPSERT,
        };
        let mut tx = self.pool.begin().await?;
        for chunk in rows.chunks(UPSERT_CHUNK) {
            let mut qb: QueryBuilder<Any> = QueryBuilder::new(format!("INSERT INTO player_state ({COLUMNS}) "));
            qb.push_values(chunk, |mut b, s| {
                let c = s.shape.to_columns();
                b.push_bind(s.user_id.0)
                    .push_bind(s.map_id.0)
                    .push_bind(c.kind)
                    .push_bind(c.radius)
                    .push_bind(c.half[0])
                    .push_bind(c.half[1])
                    .push_bind(c.half[2])
                    .push_bind(f64::from(s.position[0]))
                    .push_bind(f64::from(s.position[1]))
                    .push_bind(f64::from(s.position[2]))
                    .push_bind(s.updated_at_ms);
            });
            qb.push(tail);
            // Not cached: each batch size is another statement, and SQLite keeps a cached
            // one's whole compiled program (measured: ~10 MiB after 300 players' batches).
            qb.build().persistent(false).execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(rows.len() as u64)
    }

    /// Every player state stored for a map, ordered by user id.
    pub async fn list_player_states(&self, map: MapId) -> Result<Vec<PlayerState>> {
        let rows = sqlx::query(
            "SELECT user_id, map_id, shape_kind, radius, half_x, half_y, half_z, \
             pos_x, pos_y, pos_z, updated_at FROM player_state WHERE map_id = ? ORDER BY user_id",
        )
        .bind(map.0)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(state_from_row).collect()
    }
}
