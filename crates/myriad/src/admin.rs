//! `myriad user …` and `myriad map …`: accounts and maps in the store.

use std::io::{BufRead, IsTerminal};
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use myriad_core::Terrain;
use myriad_core::terrain::TerrainPlacement;
use myriad_store::{Heightmap, NewMap, Store, WorldBounds};

use crate::serve::ConfigArgs;

/// Which store to use: the server's configuration (file and overrides).
#[derive(clap::Args, Debug)]
pub struct StoreArgs {
    #[command(flatten)]
    config: ConfigArgs,
}

impl StoreArgs {
    fn open(&self, rt: &tokio::runtime::Runtime) -> Result<Store> {
        let config = self.config.effective()?;
        std::fs::create_dir_all(&config.data_dir)
            .with_context(|| format!("creating data directory {}", config.data_dir.display()))?;
        rt.block_on(Store::open(&myriad_server::store_config(&config))).context("opening the store")
    }
}

/// `myriad user`.
#[derive(clap::Subcommand, Debug)]
pub enum UserCommand {
    /// Create an account; the password is asked for (or read from standard input).
    Add {
        /// Account name (letters, digits, `_`, `-`, `.`; at most 32 bytes).
        name: String,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Create the test accounts `user<i>` / `password<i>` for i in 0..count (existing ones are kept).
    Seed {
        /// How many.
        #[arg(long, default_value_t = 100)]
        count: u32,
        #[command(flatten)]
        store: StoreArgs,
    },
}

/// `myriad map`.
#[derive(clap::Subcommand, Debug)]
pub enum MapCommand {
    /// Import a heightmap (16- or 8-bit grayscale PNG) as a new map.
    Import {
        /// The PNG file.
        file: PathBuf,
        /// Terrain height of the brightest sample.
        #[arg(long)]
        max_height: f32,
        /// Map name (default: the file name without extension).
        #[arg(long)]
        name: Option<String>,
        /// Length of the map along x and z.
        #[arg(long, default_value_t = 1024.0)]
        size: f32,
        #[command(flatten)]
        store: StoreArgs,
    },
    /// List the maps.
    List {
        #[command(flatten)]
        store: StoreArgs,
    },
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?)
}

fn read_password() -> Result<String> {
    let password = if std::io::stdin().is_terminal() {
        let first = rpassword::prompt_password("password: ")?;
        let again = rpassword::prompt_password("again: ")?;
        if first != again {
            bail!("the passwords differ");
        }
        first
    } else {
        let mut line = String::new();
        std::io::stdin().lock().read_line(&mut line)?;
        line.trim_end_matches(['\r', '\n']).to_string()
    };
    if password.is_empty() {
        bail!("empty password");
    }
    Ok(password)
}

/// Runs `myriad user …`.
pub fn user(cmd: UserCommand) -> Result<()> {
    let rt = runtime()?;
    match cmd {
        UserCommand::Add { name, store } => {
            let password = read_password()?;
            let store = store.open(&rt)?;
            let id = rt.block_on(store.create_user(&name, &password)).with_context(|| format!("creating {name}"))?;
            rt.block_on(store.close());
            println!("created user {name} (id {})", id.0);
        }
        UserCommand::Seed { count, store } => {
            let store = store.open(&rt)?;
            let t = std::time::Instant::now();
            let r = rt.block_on(store.seed_users(count)).context("seeding users")?;
            rt.block_on(store.close());
            println!(
                "user0..user{}: {} created, {} already there ({:.1} s)",
                count.saturating_sub(1),
                r.created,
                r.skipped,
                t.elapsed().as_secs_f64()
            );
        }
    }
    Ok(())
}

/// Runs `myriad map …`.
pub fn map(cmd: MapCommand) -> Result<()> {
    let rt = runtime()?;
    match cmd {
        MapCommand::Import { file, max_height, name, size, store } => {
            let at = TerrainPlacement { origin_x: 0.0, origin_z: 0.0, extent_x: size, extent_z: size, base_y: 0.0 };
            let terrain =
                Terrain::from_png(&file, max_height, at).with_context(|| format!("reading {}", file.display()))?;
            let name = match name {
                Some(n) => n,
                None => {
                    file.file_stem().and_then(|s| s.to_str()).context("cannot derive a map name; use --name")?.into()
                }
            };
            let store = store.open(&rt)?;
            let map = NewMap {
                name: name.clone(),
                heightmap: Heightmap::Inline {
                    width: terrain.width(),
                    height: terrain.depth(),
                    samples: terrain.samples().to_vec(),
                },
                max_height,
                bounds: WorldBounds { min: [0.0, 0.0, 0.0], max: [size, max_height + 64.0, size] },
            };
            let id = rt.block_on(store.create_map(&map)).with_context(|| format!("importing map {name}"))?;
            rt.block_on(store.close());
            println!(
                "imported map {name} (id {}): {}x{} samples, {size} units, max height {max_height}; serve it with --map {name}",
                id.0,
                terrain.width(),
                terrain.depth()
            );
        }
        MapCommand::List { store } => {
            let store = store.open(&rt)?;
            let maps = rt.block_on(store.list_maps())?;
            rt.block_on(store.close());
            println!("{:>4}  {:<32} {:>10}  bounds", "id", "name", "max height");
            for m in maps {
                println!(
                    "{:>4}  {:<32} {:>10.1}  {:?} .. {:?}",
                    m.id.0, m.name, m.max_height, m.bounds.min, m.bounds.max
                );
            }
        }
    }
    Ok(())
}
