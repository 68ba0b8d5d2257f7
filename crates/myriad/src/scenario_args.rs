//! Command-line flags that pick or shape a scenario, shared by `sim` and `bench`.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use myriad_core::{ActionScript, MovingCrowd, Placement, ScenarioSpec, Terrain, Vec3, World};

/// Which scenario to generate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ScenarioName {
    /// Reference scenario 1: 3,000 static objects, 6,000 dynamic (1,000 users).
    #[value(name = "1")]
    One,
    /// Reference scenario 2: 15,000 static, 55,000 dynamic (5,000 users).
    #[value(name = "2")]
    Two,
    /// Reference scenario 3: 99,999 static, 260,000 dynamic (10,000 users).
    #[value(name = "3")]
    Three,
    /// Scenario 3 scaled to 50,000 players at its density: 500,000 static, 1,300,000
    /// dynamic (50,000 users) on a 2,290-unit map.
    #[value(name = "4")]
    Four,
    /// Counts and sizes from the flags (defaults: scenario 1's).
    Custom,
    /// Scenario 2's counts (or the flags') with most objects crowding eight hot spots.
    Clustered,
    /// A crowd of users walking toward +x across a 512-unit map of 1,500 NPCs and 750
    /// static objects (`myriad sim` only: the crowd walks by its script). `--users` is
    /// the crowd (default 3,000), `--dynamic` the NPCs around it.
    MovingCrowd,
}

/// Flags that adjust the generated world.
#[derive(Args, Clone, Debug)]
pub struct WorldArgs {
    /// Seed of the generator (same seed, same world, on every machine).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of dynamic objects (custom and clustered scenarios).
    #[arg(long)]
    pub dynamic: Option<u32>,
    /// Number of static objects: trees, crates and rocks in equal thirds.
    #[arg(long = "static")]
    pub static_objects: Option<u32>,
    /// How many dynamic objects are users.
    #[arg(long)]
    pub users: Option<u32>,
    /// Length of the map along x and z.
    #[arg(long)]
    pub world_size: Option<f32>,
    /// The world's minimum corner, "x,y,z" (worlds need not start at the origin).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub origin: Option<Vec3>,
    /// Heightmap samples per side when generating terrain.
    #[arg(long)]
    pub terrain_samples: Option<u32>,
    /// Height of the highest terrain sample.
    #[arg(long)]
    pub max_height: Option<f32>,
    /// Load the terrain from a 16-bit grayscale PNG (or a raw little-endian u16 file of a
    /// square grid) instead of generating it; it is stretched over the map.
    #[arg(long)]
    pub heightmap: Option<PathBuf>,
}

fn parse_vec3(s: &str) -> Result<Vec3, String> {
    let parts: Vec<f32> =
        s.split(',').map(|p| p.trim().parse::<f32>().map_err(|e| format!("{p:?}: {e}"))).collect::<Result<_, _>>()?;
    match parts[..] {
        [x, y, z] if x.is_finite() && y.is_finite() && z.is_finite() => Ok(Vec3::new(x, y, z)),
        _ => Err(format!("expected three finite numbers \"x,y,z\", got {s:?}")),
    }
}

impl WorldArgs {
    /// The spec for `name` with these flags applied.
    pub fn spec(&self, name: ScenarioName) -> Result<ScenarioSpec> {
        let mut spec = match name {
            ScenarioName::One => ScenarioSpec::reference(1, self.seed)?,
            ScenarioName::Two => ScenarioSpec::reference(2, self.seed)?,
            ScenarioName::Three => ScenarioSpec::reference(3, self.seed)?,
            ScenarioName::Four => ScenarioSpec::reference(4, self.seed)?,
            ScenarioName::Custom => ScenarioSpec::custom(self.seed),
            ScenarioName::Clustered => ScenarioSpec::clustered(self.seed),
            ScenarioName::MovingCrowd => MovingCrowd::new(self.seed).base,
        };
        let reference =
            matches!(name, ScenarioName::One | ScenarioName::Two | ScenarioName::Three | ScenarioName::Four);
        if reference && (self.dynamic.is_some() || self.static_objects.is_some() || self.users.is_some()) {
            bail!("--dynamic, --static and --users change the counts: use --scenario custom or clustered");
        }
        if let Some(n) = self.dynamic {
            spec.dynamic = n;
            spec.users = spec.users.min(n);
        }
        // The moving crowd's users are its crowd ([`WorldArgs::crowd`]): the objects
        // around it are NPCs.
        let users = if name == ScenarioName::MovingCrowd { None } else { self.users };
        if let Some(n) = self.static_objects {
            spec.static_objects = n;
        }
        if let Some(n) = users {
            spec.users = n;
        }
        if let Some(s) = self.world_size {
            spec.world_size = s;
            // Hot spots keep their size relative to the map.
            if let Placement::Clustered { spread, .. } = &mut spec.placement {
                *spread = s / 64.0;
            }
        }
        if let Some(o) = self.origin {
            spec.origin = o;
        }
        if let Some(t) = self.terrain_samples {
            spec.terrain_samples = t;
        }
        if let Some(h) = self.max_height {
            spec.max_height = h;
        }
        Ok(spec)
    }

    /// The moving crowd these flags describe (`--users` is its size).
    pub fn crowd(&self) -> Result<MovingCrowd> {
        let mut crowd = MovingCrowd::new(self.seed);
        crowd.base = self.spec(ScenarioName::MovingCrowd)?;
        // The crowd keeps its size relative to the map.
        crowd.spread = crowd.base.world_size / 24.0;
        if let Some(n) = self.users {
            crowd.crowd = n;
        }
        if self.heightmap.is_some() {
            bail!("the moving crowd walks on generated terrain: drop --heightmap");
        }
        Ok(crowd)
    }

    /// The world for `name` and the actions that drive it for `ticks` ticks: the moving
    /// crowd's walk, none for the other scenarios.
    pub fn build_with_script(&self, name: ScenarioName, ticks: u64) -> Result<(ScenarioSpec, World, ActionScript)> {
        if name == ScenarioName::MovingCrowd {
            let crowd = self.crowd()?;
            let (world, script) = crowd.build_with_script(ticks).context("generating the moving crowd")?;
            return Ok((crowd.base, world, script));
        }
        let (spec, world) = self.build(name)?;
        Ok((spec, world, ActionScript::default()))
    }

    /// Builds the world for `name`, on the given heightmap if there is one. The moving
    /// crowd is refused: without its script it is a crowd standing still
    /// ([`WorldArgs::build_with_script`]).
    pub fn build(&self, name: ScenarioName) -> Result<(ScenarioSpec, World)> {
        if name == ScenarioName::MovingCrowd {
            bail!("the moving crowd walks by its script: run it with `myriad sim --scenario moving-crowd`");
        }
        let spec = self.spec(name)?;
        let world = match &self.heightmap {
            None => spec.build().with_context(|| format!("generating scenario {}", spec.name))?,
            Some(path) => {
                let at = spec.terrain_placement();
                let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
                let terrain = if is_png {
                    Terrain::from_png(path, spec.max_height, at)
                } else {
                    Terrain::from_raw(path, None, spec.max_height, at)
                }
                .with_context(|| format!("loading heightmap {}", path.display()))?;
                spec.build_on(terrain).with_context(|| format!("placing scenario {} on the heightmap", spec.name))?
            }
        };
        Ok((spec, world))
    }
}
