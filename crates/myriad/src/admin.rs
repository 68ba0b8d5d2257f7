//! `myriad map …`, and what the store commands share (`user`, `map`, `db`): which store,
//! a runtime, reading a password.

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
    /// The store's configuration (the server's configuration file and overrides).
    pub fn store_config(&self) -> Result<myriad_store::StoreConfig> {
        Ok(myriad_server::store_config(&self.config.effective()?))
    }

    /// Opens the store, after its integrity check on SQLite (a damaged database is
    /// refused before anything writes to it).
    pub fn open(&self, rt: &tokio::runtime::Runtime) -> Result<Store> {
        let config = self.config.effective()?;
        std::fs::create_dir_all(&config.data_dir)
            .with_context(|| format!("creating data directory {}", config.data_dir.display()))?;
        rt.block_on(Store::open(&myriad_server::store_config(&config))).context("opening the store")
    }
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

/// A small runtime for one store command.
pub fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?)
}

/// Reads a password: prompted twice on a terminal, else one line of standard input (never
/// an argument, which other users could read in the process list).
pub fn read_password() -> Result<String> {
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
