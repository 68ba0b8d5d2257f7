//! Plain data types stored and returned by the [`Store`](crate::Store).
//!
//! They are deliberately independent of the physics crate's types: the store knows
//! nothing about simulation, and the server converts at its boundary. Positions are
//! `f32` like the world's; the columns are `DOUBLE`, which holds every `f32` exactly.

use std::time::{SystemTime, UNIX_EPOCH};

use crate::error::{Result, StoreError};

/// Database id of a user (`users.id`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct UserId(pub i64);

/// Database id of a map (`maps.id`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MapId(pub i64);

/// The collision shape of a player or static object, with its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StoredShape {
    /// A sphere of the given radius.
    Sphere {
        /// Radius, > 0.
        radius: f32,
    },
    /// An axis-aligned box given by its half extents along x, y and z.
    Box {
        /// Half extents along x, y and z, each > 0.
        half_extents: [f32; 3],
    },
    /// A capsule along the y axis: a cylinder of the given half height capped by two
    /// hemispheres of the given radius.
    Capsule {
        /// Radius of the cylinder and of the caps, > 0.
        radius: f32,
        /// Half the height of the cylindrical part (the caps excluded), >= 0.
        half_height: f32,
    },
}

/// Column encoding of a [`StoredShape`]: `shape_kind`, `radius`, `half_x`, `half_y`, `half_z`.
/// A capsule stores its half height in `half_y`; unused parameters are stored as 0.
pub(crate) struct ShapeColumns {
    pub kind: i64,
    pub radius: f64,
    pub half: [f64; 3],
}

impl StoredShape {
    /// Stored value of `shape_kind` for spheres.
    pub const KIND_SPHERE: i64 = 0;
    /// Stored value of `shape_kind` for boxes.
    pub const KIND_BOX: i64 = 1;
    /// Stored value of `shape_kind` for capsules.
    pub const KIND_CAPSULE: i64 = 2;

    /// Checks that every parameter is finite and in range.
    pub fn validate(&self) -> Result<()> {
        let ok = match *self {
            StoredShape::Sphere { radius } => radius.is_finite() && radius > 0.0,
            StoredShape::Box { half_extents } => half_extents.iter().all(|h| h.is_finite() && *h > 0.0),
            StoredShape::Capsule { radius, half_height } => {
                radius.is_finite() && radius > 0.0 && half_height.is_finite() && half_height >= 0.0
            }
        };
        if ok { Ok(()) } else { Err(StoreError::InvalidInput(format!("shape parameters out of range: {self:?}"))) }
    }

    pub(crate) fn to_columns(self) -> ShapeColumns {
        match self {
            StoredShape::Sphere { radius } => {
                ShapeColumns { kind: Self::KIND_SPHERE, radius: radius.into(), half: [0.0; 3] }
            }
            StoredShape::Box { half_extents } => {
                ShapeColumns { kind: Self::KIND_BOX, radius: 0.0, half: half_extents.map(f64::from) }
            }
            StoredShape::Capsule { radius, half_height } => {
                ShapeColumns { kind: Self::KIND_CAPSULE, radius: radius.into(), half: [0.0, half_height.into(), 0.0] }
            }
        }
    }

    /// Rebuilds a shape from its columns; an unknown kind is reported as a database error
    /// (the row was not written by this crate).
    pub(crate) fn from_columns(kind: i64, radius: f64, half: [f64; 3]) -> Result<StoredShape> {
        // The values were written from f32, so the narrowing casts are exact.
        match kind {
            Self::KIND_SPHERE => Ok(StoredShape::Sphere { radius: radius as f32 }),
            Self::KIND_BOX => Ok(StoredShape::Box { half_extents: half.map(|h| h as f32) }),
            Self::KIND_CAPSULE => Ok(StoredShape::Capsule { radius: radius as f32, half_height: half[1] as f32 }),
            other => Err(StoreError::Database(sqlx::Error::Decode(format!("unknown shape_kind {other}").into()))),
        }
    }
}

/// A player's persistent state on one map (`player_state` row).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlayerState {
    /// The player.
    pub user_id: UserId,
    /// The map this state belongs to.
    pub map_id: MapId,
    /// The player's collision shape.
    pub shape: StoredShape,
    /// World position of the shape's centre.
    pub position: [f32; 3],
    /// When this state was taken, in milliseconds since the Unix epoch.
    pub updated_at_ms: i64,
}

impl PlayerState {
    /// A state stamped with the current time.
    pub fn new(user_id: UserId, map_id: MapId, shape: StoredShape, position: [f32; 3]) -> Self {
        PlayerState { user_id, map_id, shape, position, updated_at_ms: now_ms() }
    }

    /// Checks the shape and that the position is finite.
    pub fn validate(&self) -> Result<()> {
        self.shape.validate()?;
        if self.position.iter().all(|c| c.is_finite()) {
            Ok(())
        } else {
            Err(StoreError::InvalidInput(format!("non-finite position {:?}", self.position)))
        }
    }
}

/// Axis-aligned world bounds of a map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldBounds {
    /// Minimum corner (x, y, z).
    pub min: [f32; 3],
    /// Maximum corner (x, y, z).
    pub max: [f32; 3],
}

/// Where a map's terrain heights come from.
#[derive(Debug, Clone, PartialEq)]
pub enum Heightmap {
    /// No terrain (a flat floor at the bottom of the world bounds, as the server decides).
    None,
    /// Samples stored in the database, row-major, `width * height` of them. Stored as a
    /// BLOB of little-endian `u16`s.
    Inline {
        /// Samples per row.
        width: u32,
        /// Number of rows.
        height: u32,
        /// `width * height` samples, row-major; 0 is the lowest terrain, `u16::MAX` is the
        /// map's `max_height`.
        samples: Vec<u16>,
    },
    /// A path to a heightmap file (e.g. a 16-bit PNG), read by the server.
    Path(String),
}

/// A map to create with [`Store::create_map`](crate::Store::create_map).
#[derive(Debug, Clone, PartialEq)]
pub struct NewMap {
    /// Unique, non-empty name (at most 64 bytes).
    pub name: String,
    /// Terrain heights.
    pub heightmap: Heightmap,
    /// Height of the terrain at sample value `u16::MAX`.
    pub max_height: f32,
    /// World bounds.
    pub bounds: WorldBounds,
}

/// A stored map (`maps` row), heightmap included.
#[derive(Debug, Clone, PartialEq)]
pub struct MapInfo {
    /// Database id.
    pub id: MapId,
    /// Unique name.
    pub name: String,
    /// Terrain heights.
    pub heightmap: Heightmap,
    /// Height of the terrain at sample value `u16::MAX`.
    pub max_height: f32,
    /// World bounds.
    pub bounds: WorldBounds,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: i64,
}

/// A map as listed by [`Store::list_maps`](crate::Store::list_maps): everything but the
/// heightmap samples, which may be megabytes.
#[derive(Debug, Clone, PartialEq)]
pub struct MapSummary {
    /// Database id.
    pub id: MapId,
    /// Unique name.
    pub name: String,
    /// Height of the terrain at sample value `u16::MAX`.
    pub max_height: f32,
    /// World bounds.
    pub bounds: WorldBounds,
}

/// A static (immovable) object of a map (`static_objects` row).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticObject {
    /// Id of the object, unique within its map (chosen by the caller).
    pub object_id: i64,
    /// Collision shape.
    pub shape: StoredShape,
    /// World position of the shape's centre.
    pub position: [f32; 3],
}

/// What a successful login returns (the reference's `CheckUserAndRetrieveInfo`).
#[derive(Debug, Clone, PartialEq)]
pub struct LoginInfo {
    /// The authenticated user.
    pub user_id: UserId,
    /// The username as stored (its case may differ from what was typed).
    pub username: String,
    /// The player's state on the requested map, or `None` on a first visit (the server
    /// then spawns the player and creates the state).
    pub state: Option<PlayerState>,
}

/// Outcome of [`Store::seed_users`](crate::Store::seed_users).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SeedReport {
    /// Users created by this call.
    pub created: u32,
    /// Users that already existed and were left untouched.
    pub skipped: u32,
}

/// Milliseconds since the Unix epoch, the store's time unit (stored as `BIGINT`).
pub fn now_ms() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX)).unwrap_or(0)
}
