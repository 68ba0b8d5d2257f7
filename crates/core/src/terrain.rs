//! The terrain: a heightmap of `u16` samples spanning the world's x–z extent.
//!
//! Sample 0 is the world's floor (`base_y`) and 65535 is `base_y + max_height`. Samples are
//! stored row-major, `depth` rows along z of `width` samples along x; sample `(i, j)` sits at
//! `x = origin_x + i * extent_x / (width - 1)`, `z = origin_z + j * extent_z / (depth - 1)`.
//!
//! [`Terrain::height_at`] is the one bilinear sampler of the project. The GPU backends
//! repeat its arithmetic operation for operation (in `f32`, no fused multiply–add), so the
//! terrain floor is the same bit for bit everywhere. Do not change its expression without
//! changing the kernels.

use std::path::Path;

use crate::error::CoreError;
use crate::rng::{hash3, unit_f32};
use crate::stamp::Stamp;

/// A heightmap over the world's x–z extent.
#[derive(Clone, Debug)]
pub struct Terrain {
    width: u32,
    depth: u32,
    samples: Vec<u16>,
    max_height: f32,
    origin_x: f32,
    origin_z: f32,
    extent_x: f32,
    extent_z: f32,
    base_y: f32,
    /// `(width - 1) / extent_x`, precomputed once so every backend uses the same value.
    inv_cell_x: f32,
    /// `(depth - 1) / extent_z`.
    inv_cell_z: f32,
    /// `max_height / 65535`.
    height_scale: f32,
    /// Which terrain this is, for device copies (a terrain never changes once made).
    stamp: Stamp,
}

impl PartialEq for Terrain {
    /// Equal samples and placement (the stamp says which value, not what it holds).
    fn eq(&self, o: &Terrain) -> bool {
        self.width == o.width
            && self.depth == o.depth
            && self.samples == o.samples
            && self.max_height == o.max_height
            && self.origin_x == o.origin_x
            && self.origin_z == o.origin_z
            && self.extent_x == o.extent_x
            && self.extent_z == o.extent_z
            && self.base_y == o.base_y
            && self.inv_cell_x == o.inv_cell_x
            && self.inv_cell_z == o.inv_cell_z
            && self.height_scale == o.height_scale
    }
}

impl Terrain {
    /// This terrain's process-unique stamp (a clone has its own).
    pub fn stamp(&self) -> u64 {
        self.stamp.get()
    }
}

/// Where a terrain lies in the world: its x–z rectangle and its floor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TerrainPlacement {
    /// World x of the first column.
    pub origin_x: f32,
    /// World z of the first row.
    pub origin_z: f32,
    /// Length covered along x.
    pub extent_x: f32,
    /// Length covered along z.
    pub extent_z: f32,
    /// World y of a zero sample.
    pub base_y: f32,
}

/// Largest heightmap accepted, in samples (4096 × 4096 = 16.8 million, 32 MiB of `u16`):
/// the same cap as the store's (`myriad_store::MAX_HEIGHTMAP_SAMPLES`). Larger grids are
/// refused from the file's header, before anything is allocated; resample the image (a
/// 4096² heightmap over a 10 km map is already one sample per 2.4 m).
pub const MAX_TERRAIN_SAMPLES: u64 = 4096 * 4096;

/// Largest heightmap file read (a 4096² 16-bit PNG, uncompressed, plus room for chunks).
pub const MAX_HEIGHTMAP_FILE_BYTES: u64 = 2 * MAX_TERRAIN_SAMPLES + (1 << 20);

/// Largest extent of a terrain (and so of a served map) along x or z, and largest
/// `max_height`, in world units: beyond 65,536 an `f32` position resolves coarser than
/// 1/256 unit and the physics' contact depths lose their precision.
pub const MAX_WORLD_EXTENT: f32 = 65_536.0;

/// Refuses a grid over [`MAX_TERRAIN_SAMPLES`], naming the limit.
fn check_dimensions(width: u32, depth: u32) -> Result<(), String> {
    let n = u64::from(width) * u64::from(depth);
    if n > MAX_TERRAIN_SAMPLES {
        return Err(format!(
            "{width}x{depth} = {n} samples exceeds the limit of {MAX_TERRAIN_SAMPLES} (4096x4096); \
             resample the heightmap to at most 4096x4096"
        ));
    }
    Ok(())
}

/// Reads a heightmap file whose size is at most `limit` bytes, checked before reading.
fn read_bounded(path: &Path, limit: u64) -> Result<Vec<u8>, CoreError> {
    let io = |source| CoreError::HeightmapIo { path: path.into(), source };
    let len = std::fs::metadata(path).map_err(io)?.len();
    if len > limit {
        return Err(CoreError::invalid(
            "heightmap file",
            format!("{} is {len} bytes, over the limit of {limit} (a 4096x4096 16-bit heightmap)", path.display()),
        ));
    }
    std::fs::read(path).map_err(io)
}

impl Terrain {
    /// A terrain from raw samples. Fails if the sizes do not match or a parameter is not
    /// finite and positive.
    pub fn new(
        width: u32,
        depth: u32,
        samples: Vec<u16>,
        max_height: f32,
        at: TerrainPlacement,
    ) -> Result<Terrain, CoreError> {
        if width < 2 || depth < 2 {
            return Err(CoreError::invalid("heightmap size", format!("{width}x{depth}: need at least 2x2 samples")));
        }
        check_dimensions(width, depth).map_err(|e| CoreError::invalid("heightmap size", e))?;
        if samples.len() as u64 != width as u64 * depth as u64 {
            return Err(CoreError::invalid(
                "heightmap",
                format!("{} samples for a {width}x{depth} grid", samples.len()),
            ));
        }
        if !(max_height.is_finite() && max_height >= 0.0) {
            return Err(CoreError::invalid("max height", format!("{max_height}")));
        }
        let finite_pos = |v: f32| v.is_finite() && v > 0.0;
        if !finite_pos(at.extent_x) || !finite_pos(at.extent_z) {
            return Err(CoreError::invalid("terrain extent", format!("{} x {}", at.extent_x, at.extent_z)));
        }
        if at.extent_x > MAX_WORLD_EXTENT || at.extent_z > MAX_WORLD_EXTENT || max_height > MAX_WORLD_EXTENT {
            return Err(CoreError::invalid(
                "world size",
                format!(
                    "{} x {} units, max height {max_height}: over the limit of {MAX_WORLD_EXTENT} units \
                     (f32 precision); split the world into several maps",
                    at.extent_x, at.extent_z
                ),
            ));
        }
        if !(at.origin_x.is_finite() && at.origin_z.is_finite() && at.base_y.is_finite()) {
            return Err(CoreError::invalid("terrain origin", "not finite"));
        }
        Ok(Terrain {
            width,
            depth,
            samples,
            max_height,
            origin_x: at.origin_x,
            origin_z: at.origin_z,
            extent_x: at.extent_x,
            extent_z: at.extent_z,
            base_y: at.base_y,
            inv_cell_x: (width - 1) as f32 / at.extent_x,
            inv_cell_z: (depth - 1) as f32 / at.extent_z,
            height_scale: max_height / 65535.0,
            stamp: Stamp::new(),
        })
    }

    /// A flat terrain (every sample 0) of 2×2 samples.
    pub fn flat(at: TerrainPlacement) -> Terrain {
        Terrain::new(2, 2, vec![0; 4], 0.0, at).expect("a flat terrain with a valid placement")
    }

    /// A hilly terrain from fractal value noise: `octaves` layers of smoothly interpolated
    /// lattice noise, each at twice the frequency and half the amplitude of the last,
    /// normalised to the full `u16` range. The same seed gives the same samples on every
    /// machine (integer hashing and `f64` arithmetic only).
    pub fn generate(
        seed: u64,
        width: u32,
        depth: u32,
        max_height: f32,
        at: TerrainPlacement,
    ) -> Result<Terrain, CoreError> {
        if width < 2 || depth < 2 {
            return Err(CoreError::invalid("heightmap size", format!("{width}x{depth}")));
        }
        check_dimensions(width, depth).map_err(|e| CoreError::invalid("heightmap size", e))?;
        const OCTAVES: u32 = 6;
        const BASE_CELLS: f64 = 4.0; // hills across the whole map at the lowest octave
        let mut raw = vec![0f64; width as usize * depth as usize];
        for j in 0..depth {
            let v = j as f64 / (depth - 1) as f64;
            for i in 0..width {
                let u = i as f64 / (width - 1) as f64;
                let mut amp = 1.0;
                let mut freq = BASE_CELLS;
                let mut h = 0.0;
                for o in 0..OCTAVES {
                    h += amp * value_noise(seed.wrapping_add(o as u64), u * freq, v * freq);
                    amp *= 0.5;
                    freq *= 2.0;
                }
                raw[(j * width + i) as usize] = h;
            }
        }
        let (lo, hi) = raw.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &h| (lo.min(h), hi.max(h)));
        let span = if hi > lo { hi - lo } else { 1.0 };
        let samples = raw.iter().map(|&h| ((h - lo) / span * 65535.0).round() as u16).collect();
        Terrain::new(width, depth, samples, max_height, at)
    }

    /// Loads a 16-bit (or 8-bit, scaled by 257) grayscale PNG. The dimensions are
    /// checked from the header against [`MAX_TERRAIN_SAMPLES`] before any sample buffer
    /// is allocated, and the file size against [`MAX_HEIGHTMAP_FILE_BYTES`] before reading.
    pub fn from_png(path: &Path, max_height: f32, at: TerrainPlacement) -> Result<Terrain, CoreError> {
        let bytes = read_bounded(path, MAX_HEIGHTMAP_FILE_BYTES)?;
        let bad = |reason: String| CoreError::HeightmapPng { path: path.into(), reason };
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().map_err(|e| bad(e.to_string()))?;
        let header = reader.info();
        check_dimensions(header.width, header.height).map_err(bad)?;
        let size = reader.output_buffer_size().ok_or_else(|| bad("image too large".into()))?;
        let mut buf = vec![0u8; size];
        let info = reader.next_frame(&mut buf).map_err(|e| bad(e.to_string()))?;
        if info.color_type != png::ColorType::Grayscale {
            return Err(bad(format!("colour type {:?}, expected grayscale", info.color_type)));
        }
        let samples: Vec<u16> = match info.bit_depth {
            // PNG stores 16-bit samples big-endian.
            png::BitDepth::Sixteen => {
                buf[..info.buffer_size()].chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect()
            }
            png::BitDepth::Eight => buf[..info.buffer_size()].iter().map(|&b| b as u16 * 257).collect(),
            other => return Err(bad(format!("bit depth {other:?}, expected 8 or 16"))),
        };
        Terrain::new(info.width, info.height, samples, max_height, at)
    }

    /// Loads raw little-endian `u16` samples. Without `dims` the grid must be square.
    pub fn from_raw(
        path: &Path,
        dims: Option<(u32, u32)>,
        max_height: f32,
        at: TerrainPlacement,
    ) -> Result<Terrain, CoreError> {
        let bytes = read_bounded(path, 2 * MAX_TERRAIN_SAMPLES)?;
        let n = bytes.len() as u64;
        let (w, d) = match dims {
            Some((w, d)) if n == 2 * w as u64 * d as u64 => (w, d),
            Some((w, d)) => {
                return Err(CoreError::HeightmapRawSize {
                    path: path.into(),
                    bytes: n,
                    expected: format!("{w}x{d}x2"),
                });
            }
            None => {
                let side = ((n / 2) as f64).sqrt().round() as u64;
                if !n.is_multiple_of(2) || side * side * 2 != n {
                    return Err(CoreError::HeightmapRawSize {
                        path: path.into(),
                        bytes: n,
                        expected: "2 bytes per sample of a square grid".into(),
                    });
                }
                (side as u32, side as u32)
            }
        };
        let samples = bytes.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        Terrain::new(w, d, samples, max_height, at)
    }

    /// Writes the samples as a 16-bit grayscale PNG (the format [`Terrain::from_png`] reads).
    pub fn write_png(&self, path: &Path) -> Result<(), CoreError> {
        let io = |e: std::io::Error| CoreError::HeightmapIo { path: path.into(), source: e };
        let file = std::fs::File::create(path).map_err(io)?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), self.width, self.depth);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mut writer = enc.write_header().map_err(|e| io(std::io::Error::other(e)))?;
        let data: Vec<u8> = self.samples.iter().flat_map(|s| s.to_be_bytes()).collect();
        writer.write_image_data(&data).map_err(|e| io(std::io::Error::other(e)))?;
        writer.finish().map_err(|e| io(std::io::Error::other(e)))
    }

    /// The terrain height at world `(x, z)` by bilinear interpolation of the four nearest
    /// samples; positions outside the terrain take the nearest edge.
    ///
    /// The expression is mirrored by the GPU kernels: keep the two in step.
    #[inline]
    pub fn height_at(&self, x: f32, z: f32) -> f32 {
        let max_i = (self.width - 1) as f32;
        let max_j = (self.depth - 1) as f32;
        let fx = ((x - self.origin_x) * self.inv_cell_x).clamp(0.0, max_i);
        let fz = ((z - self.origin_z) * self.inv_cell_z).clamp(0.0, max_j);
        // Clamping the cell index to width - 2 keeps the +1 neighbour inside the grid; on
        // the last column the weight becomes 1 and the result is the edge sample exactly.
        let i = (fx as u32).min(self.width - 2);
        let j = (fz as u32).min(self.depth - 2);
        let tx = fx - i as f32;
        let tz = fz - j as f32;
        let w = self.width as usize;
        let k = j as usize * w + i as usize;
        let h00 = self.samples[k] as f32;
        let h10 = self.samples[k + 1] as f32;
        let h01 = self.samples[k + w] as f32;
        let h11 = self.samples[k + w + 1] as f32;
        let a = h00 + (h10 - h00) * tx;
        let b = h01 + (h11 - h01) * tx;
        let h = a + (b - a) * tz;
        self.base_y + h * self.height_scale
    }

    /// Samples along x.
    pub fn width(&self) -> u32 {
        self.width
    }
    /// Samples along z.
    pub fn depth(&self) -> u32 {
        self.depth
    }
    /// The raw samples, row-major (rows along z).
    pub fn samples(&self) -> &[u16] {
        &self.samples
    }
    /// The height of sample 65535 above `base_y`.
    pub fn max_height(&self) -> f32 {
        self.max_height
    }
    /// Where the terrain lies.
    pub fn placement(&self) -> TerrainPlacement {
        TerrainPlacement {
            origin_x: self.origin_x,
            origin_z: self.origin_z,
            extent_x: self.extent_x,
            extent_z: self.extent_z,
            base_y: self.base_y,
        }
    }
    /// The precomputed sampling constants `(inv_cell_x, inv_cell_z, height_scale)`, for
    /// backends that upload them.
    pub fn sampling_constants(&self) -> (f32, f32, f32) {
        (self.inv_cell_x, self.inv_cell_z, self.height_scale)
    }

    /// A hash of everything [`Terrain::height_at`] reads (what `==` compares), the same
    /// on every machine and in every process: two processes that must compute the same
    /// heights (a zone and a gateway) compare it instead of the samples. Unlike the
    /// [`stamp`](Terrain::stamp), equal terrains hash equal.
    pub fn content_hash(&self) -> u64 {
        let mut h = xxhash_rust::xxh3::Xxh3::new();
        h.update(&self.width.to_le_bytes());
        h.update(&self.depth.to_le_bytes());
        let floats = [
            self.max_height,
            self.origin_x,
            self.origin_z,
            self.extent_x,
            self.extent_z,
            self.base_y,
            self.inv_cell_x,
            self.inv_cell_z,
            self.height_scale,
        ];
        for f in floats {
            h.update(&f.to_bits().to_le_bytes());
        }
        for s in &self.samples {
            h.update(&s.to_le_bytes());
        }
        h.digest()
    }
}

/// Smoothly interpolated lattice noise in [0, 1) at `(u, v)` (lattice spacing 1).
fn value_noise(seed: u64, u: f64, v: f64) -> f64 {
    let (iu, iv) = (u.floor(), v.floor());
    let (fu, fv) = (u - iu, v - iv);
    let corner = |di: i64, dj: i64| -> f64 {
        let i = (iu as i64 + di) as u64;
        let j = (iv as i64 + dj) as u64;
        unit_f32(hash3(seed, i, j)) as f64
    };
    // Quintic fade (Perlin 2002): continuous slope and curvature across cells.
    let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (su, sv) = (fade(fu), fade(fv));
    let a = corner(0, 0) + (corner(1, 0) - corner(0, 0)) * su;
    let b = corner(0, 1) + (corner(1, 1) - corner(0, 1)) * su;
    a + (b - a) * sv
}

#[cfg(test)]
mod tests {
    use super::*;

    fn placement() -> TerrainPlacement {
        TerrainPlacement { origin_x: -100.0, origin_z: 50.0, extent_x: 200.0, extent_z: 100.0, base_y: -10.0 }
    }

    #[test]
    fn bilinear_interpolates_between_samples_and_clamps_outside() {
        // 3x2 grid: heights along x 0, 65535, 0 on both rows.
        let t = Terrain::new(3, 2, vec![0, 65535, 0, 0, 65535, 0], 100.0, placement()).unwrap();
        assert_eq!(t.height_at(-100.0, 50.0), -10.0);
        assert_eq!(t.height_at(0.0, 100.0), 90.0);
        assert!((t.height_at(-50.0, 75.0) - 40.0).abs() < 1e-4);
        // Outside: nearest edge.
        assert_eq!(t.height_at(-1e6, 1e6), -10.0);
        assert_eq!(t.height_at(100.0, 150.0), -10.0);
        assert_eq!(t.height_at(1e9, 0.0), -10.0);
    }

    #[test]
    fn generated_terrain_is_seeded_and_hilly() {
        let a = Terrain::generate(7, 257, 257, 128.0, placement()).unwrap();
        let b = Terrain::generate(7, 257, 257, 128.0, placement()).unwrap();
        let c = Terrain::generate(8, 257, 257, 128.0, placement()).unwrap();
        assert_eq!(a, b);
        assert_ne!(a.samples(), c.samples());
        assert_eq!(a.content_hash(), b.content_hash(), "equal terrains hash equal (their stamps differ)");
        assert_ne!(a.stamp(), b.stamp());
        assert_ne!(a.content_hash(), c.content_hash());
        let moved = TerrainPlacement { base_y: -9.0, ..placement() };
        assert_ne!(a.content_hash(), Terrain::generate(7, 257, 257, 128.0, moved).unwrap().content_hash());
        let (lo, hi) = (a.samples().iter().min().unwrap(), a.samples().iter().max().unwrap());
        assert_eq!((*lo, *hi), (0, 65535), "normalised to the full range");
        // Hills, not noise: neighbouring samples differ far less than the full range.
        let max_step = a
            .samples()
            .chunks(257)
            .flat_map(|row| row.windows(2).map(|w| (w[0] as i32 - w[1] as i32).abs()))
            .max()
            .unwrap();
        assert!(max_step < 16_000, "step {max_step}");
    }

    #[test]
    fn png_and_raw_round_trip() {
        let dir = std::env::temp_dir().join(format!("myriad-terrain-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let t = Terrain::generate(3, 33, 17, 64.0, placement()).unwrap();
        let png_path = dir.join("h.png");
        t.write_png(&png_path).unwrap();
        assert_eq!(Terrain::from_png(&png_path, 64.0, placement()).unwrap(), t);

        let raw_path = dir.join("h.raw");
        let bytes: Vec<u8> = t.samples().iter().flat_map(|s| s.to_le_bytes()).collect();
        std::fs::write(&raw_path, &bytes).unwrap();
        assert_eq!(Terrain::from_raw(&raw_path, Some((33, 17)), 64.0, placement()).unwrap(), t);
        assert!(matches!(
            Terrain::from_raw(&raw_path, None, 64.0, placement()),
            Err(CoreError::HeightmapRawSize { .. })
        ));
        std::fs::write(&png_path, b"not a png").unwrap();
        assert!(matches!(Terrain::from_png(&png_path, 64.0, placement()), Err(CoreError::HeightmapPng { .. })));
        assert!(matches!(
            Terrain::from_png(&dir.join("missing.png"), 64.0, placement()),
            Err(CoreError::HeightmapIo { .. })
        ));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn huge_png_header_is_refused_before_allocating() {
        // A valid PNG whose header claims 60000x60000 16-bit samples (7.2 GB decoded);
        // the file itself is tiny. Refused from the header, naming the limit.
        let dir = std::env::temp_dir().join(format!("myriad-terrain-huge-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("huge.png");
        let mut file = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut file, 60_000, 60_000);
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Sixteen);
            let mut writer = enc.write_header().unwrap();
            // A few bytes of image data (a 1 KB file, as in the drill): the decoder reads
            // the header up to the first data chunk.
            writer.write_chunk(png::chunk::IDAT, &[0x78, 0x9c, 0x03, 0x00]).unwrap();
            drop(writer);
        }
        std::fs::write(&path, &file).unwrap();
        let err = Terrain::from_png(&path, 10.0, placement()).unwrap_err().to_string();
        assert!(err.contains("60000x60000") && err.contains("limit"), "{err}");
        let err = Terrain::generate(1, 5000, 5000, 10.0, placement()).unwrap_err().to_string();
        assert!(err.contains("limit"), "{err}");
        let huge = TerrainPlacement { extent_x: 1e9, ..placement() };
        let err = Terrain::new(2, 2, vec![0; 4], 10.0, huge).unwrap_err().to_string();
        assert!(err.contains("world size") && err.contains("limit"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn rejects_bad_parameters() {
        assert!(Terrain::new(1, 5, vec![0; 5], 1.0, placement()).is_err());
        assert!(Terrain::new(2, 2, vec![0; 3], 1.0, placement()).is_err());
        assert!(Terrain::new(2, 2, vec![0; 4], f32::NAN, placement()).is_err());
        let mut p = placement();
        p.extent_x = 0.0;
        assert!(Terrain::new(2, 2, vec![0; 4], 1.0, p).is_err());
    }
}
