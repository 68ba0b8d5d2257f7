//! What the server's integration tests share.

use std::path::Path;

use myriad_server::ServerConfig;
use myriad_store::HashCost;

/// A small, fast server for tests: loopback on free ports, scenario 1's map with `npcs`
/// NPCs, cheap password hashes, no stage log, data in `dir`.
pub fn small_server(dir: &Path, npcs: u32) -> ServerConfig {
    let fast = HashCost::INSECURE_FAST;
    ServerConfig {
        udp_addr: "127.0.0.1:0".parse().unwrap(),
        login_addr: "127.0.0.1:0".parse().unwrap(),
        npc_count: npcs,
        data_dir: dir.to_path_buf(),
        hash_memory_kib: fast.m_kib,
        hash_passes: fast.t,
        hash_lanes: fast.p,
        log_stages_every_s: 0.0,
        ..ServerConfig::default()
    }
}
