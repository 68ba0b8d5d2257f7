//! Building the served world: the map (generated from a scenario or loaded from the
//! store), its NPCs, and the map description and data sent at login.

use std::sync::Arc;

use myriad_core::terrain::TerrainPlacement;
use myriad_core::{ObjectKind, Shape, ShapeKind, StaticKind, Terrain, Vec3, World};
use myriad_protocol::ShapeKind as WireKind;
use myriad_protocol::login::{MapData, MapDescription, ShapeDesc, StaticPrimitive};
use myriad_store::{Heightmap, MapId, NewMap, Store, StoreError, WorldBounds};

use crate::config::ServerConfig;
use crate::error::ServerError;

/// The world the server starts with and what clients learn about its map.
pub struct PreparedWorld {
    /// The world, statics and NPCs placed.
    pub world: World,
    /// The store's id of the map (player states are kept per map).
    pub map_id: MapId,
    /// Sent in every accepted login.
    pub description: MapDescription,
    /// The `MapData` frame, encoded once, sent to clients that ask for it.
    pub map_frame: Arc<Vec<u8>>,
}

/// Name under which a generated map is registered in the store.
pub fn generated_map_name(config: &ServerConfig) -> String {
    format!("scenario-{}-seed-{}", config.scenario, config.seed)
}

/// Builds the world of `config` and registers its map in the store if needed.
///
/// A generated map (empty `map` key) is registered without a heightmap: its terrain is a
/// pure function of scenario and seed, so it is regenerated on every start.
pub async fn prepare(config: &ServerConfig, store: &Store) -> Result<PreparedWorld, ServerError> {
    let grid = config.npc_spacing > 0.0;
    let (mut world, map_id, name) = if config.map.is_empty() {
        let mut spec = myriad_core::ScenarioSpec::reference(config.scenario, config.seed)?;
        spec.users = 0;
        spec.dynamic = if grid { 0 } else { config.npc_count };
        let world = spec.build()?;
        let name = generated_map_name(config);
        let map_id = match store.map_id_by_name(&name).await {
            Ok(id) => id,
            Err(StoreError::NotFound(_)) => {
                let b = world.bounds;
                store
                    .create_map(&NewMap {
                        name: name.clone(),
                        heightmap: Heightmap::None,
                        max_height: spec.max_height,
                        bounds: WorldBounds { min: b.min.to_array(), max: b.max.to_array() },
                    })
                    .await?
            }
            Err(e) => return Err(e.into()),
        };
        (world, map_id, name)
    } else {
        let map_id = store.map_id_by_name(&config.map).await?;
        let info = store.get_map(map_id).await?;
        let (min, max) = (Vec3::from_array(info.bounds.min), Vec3::from_array(info.bounds.max));
        let at = TerrainPlacement {
            origin_x: min.x,
            origin_z: min.z,
            extent_x: max.x - min.x,
            extent_z: max.z - min.z,
            base_y: min.y,
        };
        let terrain = match &info.heightmap {
            // Not `Terrain::flat`: the bounds come from the database, and an absurd size
            // must be an error naming the limit, not a panic.
            Heightmap::None => Terrain::new(2, 2, vec![0; 4], 0.0, at)?,
            Heightmap::Inline { width, height, samples } => {
                Terrain::new(*width, *height, samples.clone(), info.max_height, at)?
            }
            Heightmap::Path(p) => Terrain::from_png(std::path::Path::new(p), info.max_height, at)?,
        };
        let mut spec = myriad_core::ScenarioSpec::custom(config.seed);
        spec.name = info.name.clone();
        spec.static_objects = 0;
        spec.users = 0;
        spec.dynamic = if grid { 0 } else { config.npc_count };
        spec.origin = min;
        spec.world_size = (max.x - min.x).min(max.z - min.z);
        spec.max_height = info.max_height;
        let mut world = spec.build_on(terrain)?;
        for object in store.get_static_objects(map_id).await? {
            let shape = core_shape(object.shape);
            world.statics.add(StaticKind::Other, &[(shape, Vec3::from_array(object.position))])?;
        }
        (world, map_id, info.name)
    };
    if grid {
        place_npc_grid(&mut world, config.npc_count, config.npc_spacing)?;
    }
    let b = world.bounds;
    let statics = &world.statics;
    let primitives: Vec<StaticPrimitive> = (0..statics.prim_count())
        .map(|i| StaticPrimitive {
            shape: shape_desc(statics.shape_of(i)),
            position: statics.positions()[i].to_array(),
        })
        .collect();
    let description = MapDescription {
        map_id: map_id.0,
        name,
        bounds_min: b.min.to_array(),
        bounds_max: b.max.to_array(),
        terrain_width: world.terrain.width(),
        terrain_depth: world.terrain.depth(),
        max_height: world.terrain.max_height(),
        static_primitives: primitives.len() as u32,
    };
    let data = MapData {
        terrain_width: world.terrain.width(),
        terrain_depth: world.terrain.depth(),
        samples: world.terrain.samples().to_vec(),
        statics: primitives,
    };
    let mut frame = Vec::new();
    data.encode(&mut frame).map_err(|e| ServerError::Internal(format!("map too large to send: {e}")))?;
    Ok(PreparedWorld { world, map_id, description, map_frame: Arc::new(frame) })
}

/// Places `count` NPCs on a square grid `spacing` apart, centred on the map, standing on
/// the terrain; shapes cycle through sphere, box and capsule.
fn place_npc_grid(world: &mut World, count: u32, spacing: f32) -> Result<(), ServerError> {
    let b = world.bounds;
    let per_side = (count as f64).sqrt().ceil().max(1.0) as u32;
    let span = spacing * (per_side - 1) as f32;
    let centre = b.center();
    let start_x = (centre.x - span / 2.0).max(b.min.x + 1.0);
    let start_z = (centre.z - span / 2.0).max(b.min.z + 1.0);
    let mut placed = 0;
    'rows: for j in 0..per_side {
        for i in 0..per_side {
            if placed == count {
                break 'rows;
            }
            let (x, z) = (start_x + i as f32 * spacing, start_z + j as f32 * spacing);
            if x > b.max.x - 1.0 || z > b.max.z - 1.0 {
                continue;
            }
            let shape = match placed % 3 {
                0 => Shape::Sphere { radius: 0.5 },
                1 => Shape::Box { half: Vec3::splat(0.5) },
                _ => Shape::Capsule { radius: 0.4, half_height: 0.5 },
            };
            let y = world.terrain.height_at(x, z) + shape.half_extents().y + 0.05;
            world.dynamics.spawn(shape, Vec3::new(x, y, z), ObjectKind::Npc)?;
            placed += 1;
        }
    }
    Ok(())
}

/// The world model's shape of a stored shape.
pub fn core_shape(s: myriad_store::StoredShape) -> Shape {
    match s {
        myriad_store::StoredShape::Sphere { radius } => Shape::Sphere { radius },
        myriad_store::StoredShape::Box { half_extents } => Shape::Box { half: Vec3::from_array(half_extents) },
        myriad_store::StoredShape::Capsule { radius, half_height } => Shape::Capsule { radius, half_height },
    }
}

/// The stored form of a world-model shape.
pub fn store_shape(s: Shape) -> myriad_store::StoredShape {
    match s {
        Shape::Sphere { radius } => myriad_store::StoredShape::Sphere { radius },
        Shape::Box { half } => myriad_store::StoredShape::Box { half_extents: half.to_array() },
        Shape::Capsule { radius, half_height } => myriad_store::StoredShape::Capsule { radius, half_height },
    }
}

/// The wire kind of a shape kind.
pub fn wire_kind(k: ShapeKind) -> WireKind {
    match k {
        ShapeKind::Sphere => WireKind::Sphere,
        ShapeKind::Box => WireKind::Box,
        ShapeKind::Capsule => WireKind::Capsule,
    }
}

/// The login's description of a shape.
pub fn shape_desc(s: Shape) -> ShapeDesc {
    ShapeDesc { kind: wire_kind(s.kind()), half: s.half_extents().to_array(), radius: s.radius() }
}

/// A spawn point for a first visit: spread over the map by user id, on the terrain.
pub fn spawn_point(world: &World, user: myriad_store::UserId, shape: Shape) -> Vec3 {
    let b = world.bounds;
    let h = myriad_core::rng::hash3(world.seed, 0x5e5e, user.0 as u64);
    let fx = (h & 0xffff_ffff) as f32 / u32::MAX as f32;
    let fz = (h >> 32) as f32 / u32::MAX as f32;
    let margin = 4.0f32.min(b.size().x / 4.0);
    let x = b.min.x + margin + fx * (b.size().x - 2.0 * margin);
    let z = b.min.z + margin + fz * (b.size().z - 2.0 * margin);
    Vec3::new(x, world.terrain.height_at(x, z) + shape.half_extents().y + 0.1, z)
}

/// A stored position may come from another map version: keep it inside the bounds and
/// above the terrain.
pub fn clamp_into_world(world: &World, p: Vec3) -> Vec3 {
    let b = world.bounds;
    let p = if p.is_finite() { p } else { b.center() };
    let p = p.clamp(b.min + Vec3::splat(0.5), b.max - Vec3::splat(0.5));
    let floor = world.terrain.height_at(p.x, p.z);
    Vec3::new(p.x, p.y.max(floor + 0.05), p.z)
}
