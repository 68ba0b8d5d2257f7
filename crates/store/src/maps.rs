//! Maps and their static objects: the reference's `NewMap`, `GetMapInfo`,
//! `NewStatic{Sphere,Box,Capsule}Object` and `GetMapStaticObjects`.

use sqlx::any::AnyRow;
use sqlx::{Any, QueryBuilder, Row};

use crate::error::{Result, StoreError, is_unique_violation};
use crate::model::{Heightmap, MapId, MapInfo, MapSummary, NewMap, StaticObject, StoredShape, WorldBounds, now_ms};
use crate::store::Store;

/// Longest accepted map name in bytes.
pub const MAX_MAP_NAME_LEN: usize = 64;
/// Longest accepted heightmap path in bytes.
pub const MAX_HEIGHTMAP_PATH_LEN: usize = 1024;
/// Most samples in an inline heightmap (4096 x 4096, 32 MiB as a BLOB). MariaDB must be
/// configured with `max_allowed_packet` above the blob size for the largest maps.
pub const MAX_HEIGHTMAP_SAMPLES: usize = 4096 * 4096;

/// Rows per multi-row insert of static objects (10 binds per row).
const STATIC_CHUNK: usize = 250;

fn validate_map(map: &NewMap) -> Result<()> {
    let bad = |msg: String| Err(StoreError::InvalidInput(msg));
    if map.name.trim().is_empty() || map.name.len() > MAX_MAP_NAME_LEN {
        return bad(format!("map name must be 1 to {MAX_MAP_NAME_LEN} bytes, not blank"));
    }
    if !(map.max_height.is_finite() && map.max_height >= 0.0) {
        return bad(format!("max_height {} must be finite and >= 0", map.max_height));
    }
    let b = map.bounds;
    let finite = b.min.iter().chain(&b.max).all(|c| c.is_finite());
    if !finite || (0..3).any(|i| b.min[i] >= b.max[i]) {
        return bad(format!("world bounds {b:?} must be finite with min < max"));
    }
    match &map.heightmap {
        Heightmap::None => {}
        Heightmap::Inline { width, height, samples } => {
            let expected = (*width as usize).checked_mul(*height as usize);
            if *width == 0 || *height == 0 || expected != Some(samples.len()) {
                return bad(format!(
                    "heightmap of {width}x{height} needs width*height > 0 samples, got {}",
                    samples.len()
                ));
            }
            if samples.len() > MAX_HEIGHTMAP_SAMPLES {
                return bad(format!("heightmap larger than {MAX_HEIGHTMAP_SAMPLES} samples"));
            }
        }
        Heightmap::Path(path) => {
            if path.is_empty() || path.len() > MAX_HEIGHTMAP_PATH_LEN {
                return bad(format!("heightmap path must be 1 to {MAX_HEIGHTMAP_PATH_LEN} bytes"));
            }
        }
    }
    Ok(())
}

fn validate_object(object: &StaticObject) -> Result<()> {
    object.shape.validate()?;
    if object.position.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(StoreError::InvalidInput(format!("static object {} has a non-finite position", object.object_id)))
    }
}

fn f32_of(row: &AnyRow, column: &str) -> Result<f32> {
    // Written from f32, so the narrowing is exact.
    Ok(row.try_get::<f64, _>(column)? as f32)
}

fn summary_from_row(row: &AnyRow) -> Result<MapSummary> {
    Ok(MapSummary {
        id: MapId(row.try_get("id")?),
        name: row.try_get("name")?,
        max_height: f32_of(row, "max_height")?,
        bounds: WorldBounds {
            min: [f32_of(row, "min_x")?, f32_of(row, "min_y")?, f32_of(row, "min_z")?],
            max: [f32_of(row, "max_x")?, f32_of(row, "max_y")?, f32_of(row, "max_z")?],
        },
    })
}

fn heightmap_from_row(row: &AnyRow) -> Result<Heightmap> {
    let blob: Option<Vec<u8>> = row.try_get("heightmap")?;
    let path: Option<String> = row.try_get("heightmap_path")?;
    match (blob, path) {
        (Some(bytes), _) => {
            let width: i64 = row.try_get("heightmap_width")?;
            let height: i64 = row.try_get("heightmap_height")?;
            let (Ok(width), Ok(height)) = (u32::try_from(width), u32::try_from(height)) else {
                return Err(corrupt("heightmap dimensions out of range"));
            };
            if bytes.len() != 2 * width as usize * height as usize {
                return Err(corrupt("heightmap blob size does not match its dimensions"));
            }
            let samples = bytes.chunks_exact(2).map(|p| u16::from_le_bytes([p[0], p[1]])).collect();
            Ok(Heightmap::Inline { width, height, samples })
        }
        (None, Some(path)) => Ok(Heightmap::Path(path)),
        (None, None) => Ok(Heightmap::None),
    }
}

fn corrupt(msg: &str) -> StoreError {
    StoreError::Database(sqlx::Error::Decode(msg.to_owned().into()))
}

fn object_from_row(row: &AnyRow) -> Result<StaticObject> {
    Ok(StaticObject {
        object_id: row.try_get("object_id")?,
        shape: StoredShape::from_columns(
            row.try_get("shape_kind")?,
            row.try_get("radius")?,
            [row.try_get("half_x")?, row.try_get("half_y")?, row.try_get("half_z")?],
        )?,
        position: [f32_of(row, "pos_x")?, f32_of(row, "pos_y")?, f32_of(row, "pos_z")?],
    })
}

impl Store {
    /// Creates a map (the reference's `NewMap`). Names are unique:
    /// [`StoreError::AlreadyExists`] otherwise.
    pub async fn create_map(&self, map: &NewMap) -> Result<MapId> {
        validate_map(map)?;
        let (blob, width, height, path) = match &map.heightmap {
            Heightmap::None => (None, 0i64, 0i64, None),
            Heightmap::Inline { width, height, samples } => {
                let bytes: Vec<u8> = samples.iter().flat_map(|s| s.to_le_bytes()).collect();
                (Some(bytes), i64::from(*width), i64::from(*height), None)
            }
            Heightmap::Path(p) => (None, 0, 0, Some(p.clone())),
        };
        let b = map.bounds;
        // The id is read back by the unique name (see `create_user` for why).
        let mut tx = self.pool.begin().await?;
        let inserted = sqlx::query(
            "INSERT INTO maps (name, heightmap, heightmap_width, heightmap_height, \
             heightmap_path, max_height, min_x, min_y, min_z, max_x, max_y, max_z, created_at) \
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(map.name.as_str())
        .bind(blob)
        .bind(width)
        .bind(height)
        .bind(path)
        .bind(f64::from(map.max_height))
        .bind(f64::from(b.min[0]))
        .bind(f64::from(b.min[1]))
        .bind(f64::from(b.min[2]))
        .bind(f64::from(b.max[0]))
        .bind(f64::from(b.max[1]))
        .bind(f64::from(b.max[2]))
        .bind(now_ms())
        .execute(&mut *tx)
        .await;
        match inserted {
            Ok(_) => {}
            Err(e) if is_unique_violation(&e) => {
                return Err(StoreError::AlreadyExists(format!("map named {:?}", map.name)));
            }
            Err(e) => return Err(e.into()),
        }
        let id: i64 = sqlx::query_scalar("SELECT id FROM maps WHERE name = ?")
            .bind(map.name.as_str())
            .fetch_one(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(MapId(id))
    }

    /// A map with its heightmap (the reference's `GetMapInfo`), or
    /// [`StoreError::NotFound`].
    pub async fn get_map(&self, id: MapId) -> Result<MapInfo> {
        let row = sqlx::query(
            "SELECT id, name, heightmap, heightmap_width, heightmap_height, heightmap_path, \
             max_height, min_x, min_y, min_z, max_x, max_y, max_z, created_at \
             FROM maps WHERE id = ?",
        )
        .bind(id.0)
        .fetch_optional(&self.pool)
        .await?
        .ok_or_else(|| StoreError::NotFound(format!("map {}", id.0)))?;
        let summary = summary_from_row(&row)?;
        Ok(MapInfo {
            id: summary.id,
            name: summary.name,
            heightmap: heightmap_from_row(&row)?,
            max_height: summary.max_height,
            bounds: summary.bounds,
            created_at_ms: row.try_get("created_at")?,
        })
    }

    /// The id of the map with this name, or [`StoreError::NotFound`].
    pub async fn map_id_by_name(&self, name: &str) -> Result<MapId> {
        let id: Option<i64> =
            sqlx::query_scalar("SELECT id FROM maps WHERE name = ?").bind(name).fetch_optional(&self.pool).await?;
        id.map(MapId).ok_or_else(|| StoreError::NotFound(format!("map named {name:?}")))
    }

    /// Every map without its heightmap samples, ordered by id.
    pub async fn list_maps(&self) -> Result<Vec<MapSummary>> {
        let rows = sqlx::query(
            "SELECT id, name, max_height, min_x, min_y, min_z, max_x, max_y, max_z \
             FROM maps ORDER BY id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(summary_from_row).collect()
    }

    /// Adds static objects to a map in one transaction (the reference's
    /// `NewStatic*Object`, in bulk). All or nothing: an invalid object rejects the call
    /// with [`StoreError::InvalidInput`], an object id already on the map with
    /// [`StoreError::AlreadyExists`], an unknown map with [`StoreError::NotFound`].
    pub async fn add_static_objects(&self, map: MapId, objects: &[StaticObject]) -> Result<u64> {
        for object in objects {
            validate_object(object)?;
        }
        let mut tx = self.pool.begin().await?;
        let exists: Option<i64> =
            sqlx::query_scalar("SELECT id FROM maps WHERE id = ?").bind(map.0).fetch_optional(&mut *tx).await?;
        if exists.is_none() {
            return Err(StoreError::NotFound(format!("map {}", map.0)));
        }
        for chunk in objects.chunks(STATIC_CHUNK) {
            let mut qb: QueryBuilder<Any> = QueryBuilder::new(
                "INSERT INTO static_objects (map_id, object_id, shape_kind, radius, \
                 half_x, half_y, half_z, pos_x, pos_y, pos_z) ",
            );
            qb.push_values(chunk, |mut b, o| {
                let c = o.shape.to_columns();
                b.push_bind(map.0)
                    .push_bind(o.object_id)
                    .push_bind(c.kind)
                    .push_bind(c.radius)
                    .push_bind(c.half[0])
                    .push_bind(c.half[1])
                    .push_bind(c.half[2])
                    .push_bind(f64::from(o.position[0]))
                    .push_bind(f64::from(o.position[1]))
                    .push_bind(f64::from(o.position[2]));
            });
            match qb.build().persistent(false).execute(&mut *tx).await {
                Ok(_) => {}
                Err(e) if is_unique_violation(&e) => {
                    return Err(StoreError::AlreadyExists(format!(
                        "a static object id given is already on map {}",
                        map.0
                    )));
                }
                Err(e) => return Err(e.into()),
            }
        }
        tx.commit().await?;
        Ok(objects.len() as u64)
    }

    /// The static objects of a map ordered by object id (the reference's
    /// `GetMapStaticObjects`), or [`StoreError::NotFound`] if the map does not exist.
    pub async fn get_static_objects(&self, map: MapId) -> Result<Vec<StaticObject>> {
        let exists: Option<i64> =
            sqlx::query_scalar("SELECT id FROM maps WHERE id = ?").bind(map.0).fetch_optional(&self.pool).await?;
        if exists.is_none() {
            return Err(StoreError::NotFound(format!("map {}", map.0)));
        }
        let rows = sqlx::query(
            "SELECT object_id, shape_kind, radius, half_x, half_y, half_z, pos_x, pos_y, pos_z \
             FROM static_objects WHERE map_id = ? ORDER BY object_id",
        )
        .bind(map.0)
        .fetch_all(&self.pool)
        .await?;
        rows.iter().map(object_from_row).collect()
    }
}
