//! What to draw, as plain data: the terrain mesh, and instance transforms and colours of
//! every primitive. No GL here, so all of it runs under unit tests.
//!
//! **Coordinates.** The server's world is the reference's Unity world: y up, forward
//! `+z`, right `+x`, a left-handed frame. three-d (OpenGL) is right-handed, so a camera
//! behind the player looking along `+z` would show `+x` on the *left*. Everything drawn
//! therefore goes through [`to_render`], which negates x: the picture then matches the
//! Unity client (the right arrow moves the player to the right of the screen). Shapes
//! are symmetric in x, so only positions and the terrain change.
//!
//! **Base meshes.** Every primitive is one of three unit meshes (see [`Part`]): a sphere
//! of radius 1, a cube of half extent 1 and an open cylinder of radius 1 from `y = -1` to
//! `y = 1`. A capsule is a cylinder plus two spheres.

use std::collections::HashSet;

use myriad_protocol::ShapeKind;
use myriad_protocol::login::{MapData, MapDescription, ShapeDesc, StaticPrimitive};
use three_d::{CpuMesh, Indices, Mat4, Positions, Srgba, Vec3, vec3};

/// Colours of everything drawn. Dynamic kinds get saturated colours that the terrain
/// never has, so a screenshot can be checked for them.
pub mod palette {
    use three_d::Srgba;

    /// Terrain at the world's floor.
    pub const TERRAIN_LOW: Srgba = Srgba::new_opaque(62, 128, 48);
    /// Terrain at `max_height`.
    pub const TERRAIN_HIGH: Srgba = Srgba::new_opaque(128, 136, 92);
    /// Dynamic spheres.
    pub const SPHERE: Srgba = Srgba::new_opaque(225, 52, 40);
    /// Dynamic boxes.
    pub const BOX: Srgba = Srgba::new_opaque(40, 96, 230);
    /// Dynamic capsules.
    pub const CAPSULE: Srgba = Srgba::new_opaque(240, 196, 32);
    /// The player's own object, whatever its shape.
    pub const OWN: Srgba = Srgba::new_opaque(240, 40, 240);
    /// Static boxes (crates, rocks).
    pub const STATIC_BOX: Srgba = Srgba::new_opaque(150, 140, 128);
    /// Static boxes standing on a capsule: tree crowns.
    pub const CROWN: Srgba = Srgba::new_opaque(30, 92, 36);
    /// Static capsules: tree trunks.
    pub const TRUNK: Srgba = Srgba::new_opaque(110, 72, 40);
    /// Static spheres.
    pub const STATIC_SPHERE: Srgba = Srgba::new_opaque(140, 140, 140);
    /// The sky (clear colour).
    pub const SKY: Srgba = Srgba::new_opaque(150, 190, 230);
}

/// Why the map cannot be turned into a mesh.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// The heightmap's size and samples disagree, or it has fewer than 2×2 samples.
    #[error("heightmap of {width}×{depth} with {samples} samples")]
    BadHeightmap {
        /// Samples along x.
        width: u32,
        /// Samples along z.
        depth: u32,
        /// Samples present.
        samples: usize,
    },
    /// The map's bounds are empty or not finite.
    #[error("map bounds {min:?}..{max:?}")]
    BadBounds {
        /// Minimum corner.
        min: [f32; 3],
        /// Maximum corner.
        max: [f32; 3],
    },
}

/// A world position in render coordinates (x negated; see the module docs).
#[inline]
pub fn to_render(p: [f32; 3]) -> Vec3 {
    vec3(-p[0], p[1], p[2])
}

/// The terrain's height at world `(x, z)`: bilinear interpolation of the four nearest
/// samples, clamped at the edges — the same expression as `myriad_core::Terrain::height_at`.
pub fn terrain_height(desc: &MapDescription, map: &MapData, x: f32, z: f32) -> f32 {
    let (w, d) = (map.terrain_width, map.terrain_depth);
    if w < 2 || d < 2 || map.samples.len() != w as usize * d as usize {
        return desc.bounds_min[1];
    }
    let inv_cell_x = (w - 1) as f32 / (desc.bounds_max[0] - desc.bounds_min[0]);
    let inv_cell_z = (d - 1) as f32 / (desc.bounds_max[2] - desc.bounds_min[2]);
    let fx = ((x - desc.bounds_min[0]) * inv_cell_x).clamp(0.0, (w - 1) as f32);
    let fz = ((z - desc.bounds_min[2]) * inv_cell_z).clamp(0.0, (d - 1) as f32);
    let i = (fx as u32).min(w - 2);
    let j = (fz as u32).min(d - 2);
    let (tx, tz) = (fx - i as f32, fz - j as f32);
    let w = w as usize;
    let k = j as usize * w + i as usize;
    let s = &map.samples;
    let (h00, h10, h01, h11) = (s[k] as f32, s[k + 1] as f32, s[k + w] as f32, s[k + w + 1] as f32);
    let a = h00 + (h10 - h00) * tx;
    let b = h01 + (h11 - h01) * tx;
    desc.bounds_min[1] + (a + (b - a) * tz) * (desc.max_height / 65535.0)
}

/// Which samples of a row of `n` become vertices when at most `max` may: all of them if
/// they fit, else `max` evenly spread ones, always including the first and the last so the
/// mesh spans the whole map.
pub fn decimate(n: u32, max: u32) -> Vec<u32> {
    let max = max.max(2);
    if n <= max {
        return (0..n).collect();
    }
    let step = (n - 1) as f64 / (max - 1) as f64;
    (0..max).map(|k| ((k as f64 * step).round() as u32).min(n - 1)).collect()
}

fn lerp_color(a: Srgba, b: Srgba, t: f32) -> Srgba {
    let t = t.clamp(0.0, 1.0);
    let mix = |x: u8, y: u8| (x as f32 + (y as f32 - x as f32) * t).round() as u8;
    Srgba::new(mix(a.r, b.r), mix(a.g, b.g), mix(a.b, b.b), 255)
}

/// The terrain as one mesh, in render coordinates: a vertex per kept sample (at most
/// `max_side` per side, see [`decimate`]) at exactly the sample's height
/// (`bounds_min.y + sample × max_height / 65535`), unit normals from central differences,
/// colours by height, two upward-facing triangles per cell.
pub fn terrain_mesh(desc: &MapDescription, map: &MapData, max_side: u32) -> Result<CpuMesh, SceneError> {
    let (w, d) = (map.terrain_width, map.terrain_depth);
    if w < 2 || d < 2 || map.samples.len() != w as usize * d as usize {
        return Err(SceneError::BadHeightmap { width: w, depth: d, samples: map.samples.len() });
    }
    let (min, max) = (desc.bounds_min, desc.bounds_max);
    let finite = min.iter().chain(max.iter()).all(|c| c.is_finite());
    if !finite || max[0] <= min[0] || max[2] <= min[2] || !desc.max_height.is_finite() {
        return Err(SceneError::BadBounds { min, max });
    }
    let cols = decimate(w, max_side);
    let rows = decimate(d, max_side);
    let (nx, nz) = (cols.len(), rows.len());
    let cell_x = (max[0] - min[0]) / (w - 1) as f32;
    let cell_z = (max[2] - min[2]) / (d - 1) as f32;
    let scale = desc.max_height / 65535.0;
    let xs: Vec<f32> = cols.iter().map(|&i| min[0] + i as f32 * cell_x).collect();
    let zs: Vec<f32> = rows.iter().map(|&j| min[2] + j as f32 * cell_z).collect();
    let sample = |c: usize, r: usize| map.samples[rows[r] as usize * w as usize + cols[c] as usize];
    let height = |c: usize, r: usize| min[1] + sample(c, r) as f32 * scale;

    let mut positions = Vec::with_capacity(nx * nz);
    let mut normals = Vec::with_capacity(nx * nz);
    let mut colors = Vec::with_capacity(nx * nz);
    for r in 0..nz {
        for c in 0..nx {
            let h = height(c, r);
            positions.push(to_render([xs[c], h, zs[r]]));
            // Central differences on the mesh's own grid (one-sided at the edges), so the
            // shading matches the triangles drawn.
            let (c0, c1) = (c.saturating_sub(1), (c + 1).min(nx - 1));
            let (r0, r1) = (r.saturating_sub(1), (r + 1).min(nz - 1));
            let dhdx = (height(c1, r) - height(c0, r)) / (xs[c1] - xs[c0]);
            let dhdz = (height(c, r1) - height(c, r0)) / (zs[r1] - zs[r0]);
            // World normal (-dh/dx, 1, -dh/dz); x negated for render coordinates.
            let n = vec3(dhdx, 1.0, -dhdz);
            normals.push(n / (n.x * n.x + n.y * n.y + n.z * n.z).sqrt());
            colors.push(lerp_color(palette::TERRAIN_LOW, palette::TERRAIN_HIGH, sample(c, r) as f32 / 65535.0));
        }
    }
    let mut indices = Vec::with_capacity((nx - 1) * (nz - 1) * 6);
    for r in 0..nz - 1 {
        for c in 0..nx - 1 {
            let a = (r * nx + c) as u32;
            let b = a + nx as u32; // next row (+z)
            // With x negated, (a, a+1, b) turns counter-clockwise seen from above.
            indices.extend_from_slice(&[a, a + 1, b, a + 1, b + 1, b]);
        }
    }
    Ok(CpuMesh {
        positions: Positions::F32(positions),
        indices: Indices::U32(indices),
        normals: Some(normals),
        colors: Some(colors),
        ..Default::default()
    })
}

/// The three unit meshes every primitive is drawn with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Part {
    /// Sphere of radius 1 around the origin.
    Sphere,
    /// Cube from -1 to 1 on every axis.
    Cube,
    /// Open cylinder of radius 1 around the y axis, from y = -1 to 1.
    Cylinder,
}

/// The instance transforms placing `shape` centred at world `centre`: a sphere scaled by
/// its radius, a box by its half extents, a capsule as a cylinder (radius, segment half
/// length `half[1] - radius`) and two spheres at the segment's ends.
pub fn for_each_part(shape: &ShapeDesc, centre: [f32; 3], mut f: impl FnMut(Part, Mat4)) {
    let c = to_render(centre);
    match shape.kind {
        ShapeKind::Sphere => f(Part::Sphere, Mat4::from_translation(c) * Mat4::from_scale(shape.radius)),
        ShapeKind::Box => f(
            Part::Cube,
            Mat4::from_translation(c) * Mat4::from_nonuniform_scale(shape.half[0], shape.half[1], shape.half[2]),
        ),
        ShapeKind::Capsule => {
            let r = shape.radius;
            let seg = (shape.half[1] - r).max(0.0);
            if seg > 0.0 {
                f(Part::Cylinder, Mat4::from_translation(c) * Mat4::from_nonuniform_scale(r, seg, r));
            }
            for end in [seg, -seg] {
                f(Part::Sphere, Mat4::from_translation(c + vec3(0.0, end, 0.0)) * Mat4::from_scale(r));
            }
        }
    }
}

/// Instances of one [`Part`]: a transform and a colour each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Batch {
    /// Instance transforms.
    pub transforms: Vec<Mat4>,
    /// Instance colours, one per transform.
    pub colors: Vec<Srgba>,
}

impl Batch {
    /// Number of instances.
    pub fn len(&self) -> usize {
        self.transforms.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.transforms.is_empty()
    }
}

/// The instances of every part: what one set of three instanced meshes draws.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Batches {
    /// Spheres (and capsule caps).
    pub spheres: Batch,
    /// Boxes.
    pub cubes: Batch,
    /// Capsule bodies.
    pub cylinders: Batch,
}

impl Batches {
    /// Empties every batch, keeping the allocations.
    pub fn clear(&mut self) {
        for b in [&mut self.spheres, &mut self.cubes, &mut self.cylinders] {
            b.transforms.clear();
            b.colors.clear();
        }
    }

    /// The batch of one part.
    pub fn part(&self, part: Part) -> &Batch {
        match part {
            Part::Sphere => &self.spheres,
            Part::Cube => &self.cubes,
            Part::Cylinder => &self.cylinders,
        }
    }

    /// Adds the parts of one shape, all in one colour.
    pub fn push_shape(&mut self, shape: &ShapeDesc, centre: [f32; 3], color: Srgba) {
        for_each_part(shape, centre, |part, m| {
            let b = match part {
                Part::Sphere => &mut self.spheres,
                Part::Cube => &mut self.cubes,
                Part::Cylinder => &mut self.cylinders,
            };
            b.transforms.push(m);
            b.colors.push(color);
        });
    }

    /// Instances in all batches.
    pub fn total(&self) -> usize {
        self.spheres.len() + self.cubes.len() + self.cylinders.len()
    }
}

/// Key of a horizontal position on a 1/100-unit grid (trees stack their crowns exactly
/// above the trunk's centre).
fn column_key(p: [f32; 3]) -> (i64, i64) {
    ((p[0] * 100.0).round() as i64, (p[2] * 100.0).round() as i64)
}

/// The static scenery as instances. The map only carries primitives, so kinds are told
/// apart by shape: capsules are trunks, boxes centred above a capsule are crowns, other
/// boxes are crates and rocks.
pub fn static_batches(statics: &[StaticPrimitive]) -> Batches {
    let trunks: HashSet<(i64, i64)> =
        statics.iter().filter(|p| p.shape.kind == ShapeKind::Capsule).map(|p| column_key(p.position)).collect();
    let mut out = Batches::default();
    for p in statics {
        let color = match p.shape.kind {
            ShapeKind::Capsule => palette::TRUNK,
            ShapeKind::Box if trunks.contains(&column_key(p.position)) => palette::CROWN,
            ShapeKind::Box => palette::STATIC_BOX,
            ShapeKind::Sphere => palette::STATIC_SPHERE,
        };
        out.push_shape(&p.shape, p.position, color);
    }
    out
}

/// The shape drawn for a dynamic object of `kind`: updates carry only the kind, so other
/// objects are drawn at the server's NPC sizes (`myriad-server`'s NPC grid and the
/// player capsule: sphere radius 0.5, box half extent 0.5, capsule radius 0.4 with a
/// segment half length of 0.5).
pub fn nominal_shape(kind: ShapeKind) -> ShapeDesc {
    match kind {
        ShapeKind::Sphere => ShapeDesc { kind, half: [0.5; 3], radius: 0.5 },
        ShapeKind::Box => ShapeDesc { kind, half: [0.5; 3], radius: 0.0 },
        ShapeKind::Capsule => ShapeDesc { kind, half: [0.4, 0.9, 0.4], radius: 0.4 },
    }
}

/// The colour of a dynamic object of `kind` that is not the player's.
pub fn kind_color(kind: ShapeKind) -> Srgba {
    match kind {
        ShapeKind::Sphere => palette::SPHERE,
        ShapeKind::Box => palette::BOX,
        ShapeKind::Capsule => palette::CAPSULE,
    }
}

/// One dynamic object as the renderer gets it from the network thread.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewObject {
    /// Object id.
    pub id: u64,
    /// Shape kind.
    pub kind: ShapeKind,
    /// World position of its centre.
    pub position: [f32; 3],
    /// No news for longer than the stale time.
    pub stale: bool,
}

/// What decides which dynamic objects are drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewFilter {
    /// The player's object: always drawn (even stale), in [`palette::OWN`], with its real
    /// shape.
    pub own_id: u64,
    /// The player's shape (from the login).
    pub own_shape: ShapeDesc,
    /// Where distances are measured from (the camera), world coordinates.
    pub eye: [f32; 3],
    /// Objects farther than this from `eye` are not drawn (the far plane).
    pub far: f32,
}

/// Fills `out` with the dynamic objects to draw: not stale, within `far` of the eye, and
/// the player's own object always. Returns how many objects were drawn.
pub fn dynamic_batches(objects: &[ViewObject], filter: &ViewFilter, out: &mut Batches) -> usize {
    out.clear();
    let far2 = filter.far * filter.far;
    let mut drawn = 0;
    for o in objects {
        if o.id == filter.own_id {
            out.push_shape(&filter.own_shape, o.position, palette::OWN);
            drawn += 1;
            continue;
        }
        let d = [o.position[0] - filter.eye[0], o.position[1] - filter.eye[1], o.position[2] - filter.eye[2]];
        if o.stale || d[0] * d[0] + d[1] * d[1] + d[2] * d[2] > far2 {
            continue;
        }
        out.push_shape(&nominal_shape(o.kind), o.position, kind_color(o.kind));
        drawn += 1;
    }
    drawn
}

/// An open cylinder of radius 1 around the y axis from `y = -1` to `y = 1` (the
/// capsule body; the caps are spheres), with outward unit normals.
pub fn unit_cylinder(segments: u32) -> CpuMesh {
    let segments = segments.max(3);
    let mut positions = Vec::with_capacity(2 * segments as usize);
    let mut normals = Vec::with_capacity(2 * segments as usize);
    for k in 0..segments {
        let a = std::f32::consts::TAU * k as f32 / segments as f32;
        let (s, c) = a.sin_cos();
        for y in [-1.0, 1.0] {
            positions.push(vec3(c, y, s));
            normals.push(vec3(c, 0.0, s));
        }
    }
    let mut indices = Vec::with_capacity(6 * segments as usize);
    for k in 0..segments {
        let (a, b) = (2 * k, 2 * ((k + 1) % segments));
        // a, b: bottom vertices; a + 1, b + 1 above them. Counter-clockwise seen from outside.
        indices.extend_from_slice(&[a, a + 1, b, b, a + 1, b + 1]);
    }
    CpuMesh {
        positions: Positions::F32(positions),
        indices: Indices::U32(indices),
        normals: Some(normals),
        ..Default::default()
    }
}

/// `n` made-up objects for measuring: a square grid `spacing` apart starting 3 units in
/// front of `centre` (+z) and centred on it in x, shapes cycling sphere, box, capsule,
/// standing on `ground`. Their ids (from 2⁶²) cannot clash with the server's.
pub fn synthetic_objects(
    n: usize,
    centre: [f32; 3],
    spacing: f32,
    ground: impl Fn(f32, f32) -> f32,
) -> Vec<ViewObject> {
    let side = (n as f64).sqrt().ceil() as usize;
    let x0 = centre[0] - spacing * (side.saturating_sub(1)) as f32 / 2.0;
    let z0 = centre[2] + 3.0;
    (0..n)
        .map(|k| {
            let kind = [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule][k % 3];
            let (x, z) = (x0 + (k % side) as f32 * spacing, z0 + (k / side) as f32 * spacing);
            let y = ground(x, z) + nominal_shape(kind).half[1];
            ViewObject { id: (1 << 62) + k as u64, kind, position: [x, y, z], stale: false }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use three_d::{InnerSpace, SquareMatrix, Vec4};

    fn desc(w: u32, d: u32) -> MapDescription {
        MapDescription {
            map_id: 1,
            name: "t".into(),
            bounds_min: [10.0, -5.0, 20.0],
            bounds_max: [10.0 + 64.0, 100.0, 20.0 + 32.0],
            terrain_width: w,
            terrain_depth: d,
            max_height: 50.0,
            static_primitives: 0,
        }
    }

    fn map(w: u32, d: u32) -> MapData {
        let samples = (0..w * d).map(|k| ((k * 7919) % 65536) as u16).collect();
        MapData { terrain_width: w, terrain_depth: d, samples, statics: Vec::new() }
    }

    fn positions(m: &CpuMesh) -> &[Vec3] {
        match &m.positions {
            Positions::F32(p) => p,
            Positions::F64(_) => panic!("f32 positions expected"),
        }
    }

    fn indices(m: &CpuMesh) -> &[u32] {
        match &m.indices {
            Indices::U32(i) => i,
            _ => panic!("u32 indices expected"),
        }
    }

    fn origin(m: Mat4) -> Vec3 {
        (m * Vec4::new(0.0, 0.0, 0.0, 1.0)).truncate()
    }

    fn apply(m: Mat4, p: Vec3) -> Vec3 {
        (m * p.extend(1.0)).truncate()
    }

    #[test]
    fn terrain_vertices_sit_on_the_samples() {
        let (d, m) = (desc(5, 3), map(5, 3));
        let mesh = terrain_mesh(&d, &m, 512).unwrap();
        let p = positions(&mesh);
        assert_eq!(p.len(), 15);
        assert_eq!(indices(&mesh).len(), 4 * 2 * 6);
        let h = |k: usize| -5.0 + m.samples[k] as f32 * 50.0 / 65535.0;
        // Corners: (x, z) = bounds corners, x negated, heights = samples.
        assert_eq!(p[0], vec3(-10.0, h(0), 20.0));
        assert_eq!(p[4], vec3(-74.0, h(4), 20.0));
        assert_eq!(p[10], vec3(-10.0, h(10), 52.0));
        assert_eq!(p[14], vec3(-74.0, h(14), 52.0));
        // Every vertex agrees with the bilinear sampler at its own position.
        for v in p {
            assert!((terrain_height(&d, &m, -v.x, v.z) - v.y).abs() < 1e-3, "{v:?}");
        }
    }

    #[test]
    fn terrain_normals_are_unit_and_triangles_face_up() {
        let mesh = terrain_mesh(&desc(9, 7), &map(9, 7), 512).unwrap();
        for n in mesh.normals.as_ref().unwrap() {
            assert!((n.magnitude() - 1.0).abs() < 1e-5, "{n:?}");
            assert!(n.y > 0.0);
        }
        let p = positions(&mesh);
        for t in indices(&mesh).chunks(3) {
            let (a, b, c) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
            assert!((b - a).cross(c - a).y > 0.0, "triangle {t:?} faces down");
        }
    }

    #[test]
    fn terrain_normal_of_a_slope() {
        // Height rises 1 unit per unit of world x: world normal (-1, 1, 0)/√2, render (1, 1, 0)/√2.
        let d = MapDescription { bounds_max: [10.0 + 4.0, 100.0, 20.0 + 4.0], max_height: 65535.0, ..desc(5, 5) };
        let samples = (0..25).map(|k| (k % 5) as u16).collect();
        let m = MapData { terrain_width: 5, terrain_depth: 5, samples, statics: Vec::new() };
        let mesh = terrain_mesh(&d, &m, 512).unwrap();
        let s = std::f32::consts::FRAC_1_SQRT_2;
        for n in mesh.normals.as_ref().unwrap() {
            assert!((n - vec3(s, s, 0.0)).magnitude() < 1e-5, "{n:?}");
        }
    }

    #[test]
    fn decimation_keeps_the_edges_and_the_cap() {
        assert_eq!(decimate(5, 512), vec![0, 1, 2, 3, 4]);
        let d = decimate(1025, 512);
        assert_eq!(d.len(), 512);
        assert_eq!((d[0], d[511]), (0, 1024));
        assert!(d.windows(2).all(|w| w[1] > w[0] && w[1] - w[0] <= 3));
        let (dd, m) = (desc(1025, 9), map(1025, 9));
        let mesh = terrain_mesh(&dd, &m, 256).unwrap();
        let p = positions(&mesh);
        assert_eq!(p.len(), 256 * 9);
        // The far corner is still the last sample, exactly.
        let last = m.samples[1025 * 9 - 1] as f32 * 50.0 / 65535.0 - 5.0;
        assert_eq!(p[p.len() - 1], vec3(-74.0, last, 52.0));
    }

    #[test]
    fn bad_heightmaps_are_errors() {
        let mut m = map(4, 4);
        m.samples.pop();
        assert!(matches!(terrain_mesh(&desc(4, 4), &m, 64), Err(SceneError::BadHeightmap { .. })));
        assert!(terrain_mesh(&desc(1, 4), &map(1, 4), 64).is_err());
        let flat = MapDescription { bounds_max: [10.0, 1.0, 52.0], ..desc(4, 4) };
        assert!(matches!(terrain_mesh(&flat, &map(4, 4), 64), Err(SceneError::BadBounds { .. })));
    }

    #[test]
    fn terrain_height_interpolates_between_samples() {
        let d =
            MapDescription { bounds_min: [0.0; 3], bounds_max: [2.0, 10.0, 2.0], max_height: 65535.0, ..desc(3, 3) };
        let m = MapData {
            terrain_width: 3,
            terrain_depth: 3,
            samples: vec![0, 2, 4, 0, 2, 4, 10, 12, 14],
            statics: vec![],
        };
        assert_eq!(terrain_height(&d, &m, 0.5, 0.0), 1.0);
        assert_eq!(terrain_height(&d, &m, 2.0, 2.0), 14.0);
        assert_eq!(terrain_height(&d, &m, 1.0, 1.5), 7.0);
        assert_eq!(terrain_height(&d, &m, -9.0, 99.0), 10.0, "outside: nearest edge");
    }

    #[test]
    fn box_and_sphere_instances() {
        let mut b = Batches::default();
        let boxy = ShapeDesc { kind: ShapeKind::Box, half: [1.0, 2.0, 3.0], radius: 0.0 };
        b.push_shape(&boxy, [5.0, 6.0, 7.0], palette::BOX);
        assert_eq!((b.cubes.len(), b.spheres.len(), b.cylinders.len()), (1, 0, 0));
        let m = b.cubes.transforms[0];
        assert_eq!(origin(m), vec3(-5.0, 6.0, 7.0));
        // The unit cube's corner lands on the box's corner.
        assert_eq!(apply(m, vec3(1.0, 1.0, 1.0)), vec3(-4.0, 8.0, 10.0));
        let ball = ShapeDesc { kind: ShapeKind::Sphere, half: [0.7; 3], radius: 0.7 };
        b.push_shape(&ball, [0.0, 1.0, 0.0], palette::SPHERE);
        let top = apply(b.spheres.transforms[0], vec3(0.0, 1.0, 0.0));
        assert!((top - vec3(0.0, 1.7, 0.0)).magnitude() < 1e-6);
        assert_eq!(b.spheres.colors, vec![palette::SPHERE]);
    }

    #[test]
    fn capsule_is_a_cylinder_and_two_spheres() {
        let cap = ShapeDesc { kind: ShapeKind::Capsule, half: [0.4, 0.9, 0.4], radius: 0.4 };
        let mut b = Batches::default();
        b.push_shape(&cap, [1.0, 10.0, 2.0], palette::CAPSULE);
        assert_eq!((b.cylinders.len(), b.spheres.len(), b.cubes.len()), (1, 2, 0));
        let cyl = b.cylinders.transforms[0];
        // The cylinder's ends sit at ± the segment half length (0.9 - 0.4 = 0.5).
        assert!((apply(cyl, vec3(0.0, 1.0, 0.0)) - vec3(-1.0, 10.5, 2.0)).magnitude() < 1e-6);
        assert!((apply(cyl, vec3(1.0, -1.0, 0.0)) - vec3(-0.6, 9.5, 2.0)).magnitude() < 1e-6);
        let caps: Vec<Vec3> = b.spheres.transforms.iter().map(|m| origin(*m)).collect();
        assert!(caps.contains(&vec3(-1.0, 10.5, 2.0)) && caps.contains(&vec3(-1.0, 9.5, 2.0)), "{caps:?}");
        // The top cap reaches the capsule's top: centre + half[1].
        let top = b.spheres.transforms.iter().map(|m| apply(*m, vec3(0.0, 1.0, 0.0)).y).fold(f32::MIN, f32::max);
        assert!((top - 10.9).abs() < 1e-5);
        // A capsule with no segment is a sphere.
        let mut s = Batches::default();
        s.push_shape(&ShapeDesc { half: [0.4; 3], ..cap }, [0.0; 3], palette::CAPSULE);
        assert_eq!((s.cylinders.len(), s.spheres.len()), (0, 2));
        assert!(s.spheres.transforms.iter().all(|m| m.determinant() > 0.0));
    }

    #[test]
    fn statics_are_coloured_by_role() {
        let trunk = ShapeDesc { kind: ShapeKind::Capsule, half: [0.3, 1.8, 0.3], radius: 0.3 };
        let crown = ShapeDesc { kind: ShapeKind::Box, half: [1.2, 0.6, 1.2], radius: 0.0 };
        let statics = [
            StaticPrimitive { shape: trunk, position: [100.0, 5.0, 200.0] },
            StaticPrimitive { shape: crown, position: [100.0, 8.0, 200.0] },
            StaticPrimitive { shape: crown, position: [300.0, 1.0, 200.0] },
        ];
        let b = static_batches(&statics);
        assert_eq!((b.cylinders.len(), b.spheres.len(), b.cubes.len()), (1, 2, 2));
        assert_eq!(b.cylinders.colors, vec![palette::TRUNK]);
        assert_eq!(b.cubes.colors, vec![palette::CROWN, palette::STATIC_BOX]);
        assert_eq!(origin(b.cubes.transforms[1]), vec3(-300.0, 1.0, 200.0));
        assert_eq!(b.total(), 5);
    }

    fn obj(id: u64, kind: ShapeKind, x: f32, stale: bool) -> ViewObject {
        ViewObject { id, kind, position: [x, 0.0, 0.0], stale }
    }

    #[test]
    fn dynamic_filter_hides_stale_and_far_objects_and_keeps_the_player() {
        let own_shape = ShapeDesc { kind: ShapeKind::Capsule, half: [0.5, 1.0, 0.5], radius: 0.5 };
        let filter = ViewFilter { own_id: 7, own_shape, eye: [0.0; 3], far: 100.0 };
        let objects = [
            obj(1, ShapeKind::Sphere, 10.0, false),
            obj(2, ShapeKind::Box, 20.0, true),   // stale
            obj(3, ShapeKind::Box, 150.0, false), // beyond the far plane
            obj(4, ShapeKind::Capsule, -99.0, false),
            obj(7, ShapeKind::Capsule, 500.0, true), // own: always, even stale and far
        ];
        let mut out = Batches::default();
        assert_eq!(dynamic_batches(&objects, &filter, &mut out), 3);
        assert_eq!(out.cubes.len(), 0);
        assert_eq!(out.cylinders.len(), 2);
        assert_eq!(out.cylinders.colors, vec![palette::CAPSULE, palette::OWN]);
        assert_eq!(out.spheres.len(), 1 + 2 + 2);
        assert_eq!(out.spheres.colors[0], palette::SPHERE);
        // The player is drawn with its own shape: segment half length 0.5, radius 0.5.
        let own_cyl = out.cylinders.transforms[1];
        assert!((apply(own_cyl, vec3(1.0, 1.0, 0.0)) - vec3(-499.5, 0.5, 0.0)).magnitude() < 1e-5);
        // Reusing the batches starts from empty.
        let none = ViewFilter { own_id: 99, far: 1.0, ..filter };
        assert_eq!(dynamic_batches(&objects, &none, &mut out), 0);
        assert_eq!(out.total(), 0);
    }

    #[test]
    fn dynamic_colours_are_distinct_from_the_terrain() {
        let colors = [palette::SPHERE, palette::BOX, palette::CAPSULE, palette::OWN];
        for (i, a) in colors.iter().enumerate() {
            // Far from both ends of the terrain ramp.
            for t in [palette::TERRAIN_LOW, palette::TERRAIN_HIGH] {
                let d =
                    (a.r as i32 - t.r as i32).abs() + (a.g as i32 - t.g as i32).abs() + (a.b as i32 - t.b as i32).abs();
                assert!(d > 150, "{a:?} vs {t:?}");
            }
            assert!(colors[i + 1..].iter().all(|b| b != a));
        }
    }

    #[test]
    fn cylinder_is_unit_and_faces_out() {
        let m = unit_cylinder(12);
        let p = positions(&m);
        assert_eq!(p.len(), 24);
        assert!(p.iter().all(|v| (v.x * v.x + v.z * v.z - 1.0).abs() < 1e-5 && v.y.abs() == 1.0));
        for t in indices(&m).chunks(3) {
            let (a, b, c) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
            let n = (b - a).cross(c - a);
            let mid = (a + b + c) / 3.0;
            assert!(n.x * mid.x + n.z * mid.z > 0.0, "triangle {t:?} faces in");
        }
        assert!(m.normals.as_ref().unwrap().iter().all(|n| (n.magnitude() - 1.0).abs() < 1e-5));
    }

    #[test]
    fn synthetic_objects_stand_on_the_ground_in_front() {
        let objs = synthetic_objects(10, [100.0, 0.0, 50.0], 2.0, |_, _| 7.0);
        assert_eq!(objs.len(), 10);
        // 4 per side, centred on x = 100.
        assert_eq!(objs[0].position, [97.0, 7.5, 53.0]);
        assert_eq!(objs[5].position, [99.0, 7.9, 55.0]);
        assert_eq!(objs[2].kind, ShapeKind::Capsule);
        assert_eq!(objs[2].position[1], 7.9);
        assert!(objs.iter().all(|o| o.id >= 1 << 62 && !o.stale));
    }
}
