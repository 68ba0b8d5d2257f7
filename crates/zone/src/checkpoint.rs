//! Checkpoints: each zone's objects at a tick, stored durably, so that the cluster can
//! roll back to the last tick that *every* zone has stored (a consistent cut) when a
//! zone dies or stalls.
//!
//! The store is NATS JetStream's object store: the zones already hold a NATS connection,
//! objects are chunked (a zone of scenario 3 is several megabytes, over NATS' 1 MiB
//! message limit), and the data is replicated with the NATS cluster — no SQL server
//! becomes a dependency of every zone. Each checkpoint is a signed
//! [`Message::Checkpoint`], so a forged or corrupted
//! one is refused, never loaded.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use myriad_core::ObjectState;
use tokio::io::AsyncReadExt;

use crate::error::ZoneError;
use crate::layout::ZoneId;
use crate::rebalance::Cuts;
use crate::wire::{ClusterKey, Message, decode, encode_checkpoint};

/// A zone's checkpoint: its objects at a tick, the cuts they were stepped there with (so
/// a zone restarted after a cut move resumes on the moved cuts) and the epoch that
/// wrote it (checkpoints of one tick from two epochs are not one world).
#[derive(Clone, Debug, PartialEq)]
pub struct Snapshot {
    /// The epoch (run) that wrote it.
    pub run: u64,
    /// The cuts along x and z.
    pub cuts: Cuts,
    /// The objects, by id.
    pub objects: Vec<ObjectState>,
}

/// Where checkpoints live. Names are `z<zone>-t<tick>`, so that nobody needs to list a
/// bucket (listing a bucket that others write to is slow on JetStream).
pub trait CheckpointStore: Send {
    /// Stores zone `zone`'s objects at `tick`, stepped there with `cuts`.
    fn put(&mut self, zone: ZoneId, tick: u64, run: u64, cuts: &Cuts, objects: &[ObjectState])
    -> Result<(), ZoneError>;
    /// Whether zone `zone` has a checkpoint at `tick`.
    fn has(&mut self, zone: ZoneId, tick: u64) -> Result<bool, ZoneError>;
    /// Zone `zone`'s checkpoint of `tick`.
    fn get(&mut self, zone: ZoneId, tick: u64) -> Result<Snapshot, ZoneError>;
    /// Drops zone `zone`'s checkpoint at `tick`, and its intent log segment that starts
    /// there, if there are.
    fn forget(&mut self, zone: ZoneId, tick: u64) -> Result<(), ZoneError>;
    /// Stores zone `zone`'s intent log segment that starts at `tick`
    /// ([`crate::replay`]; signed by the zone, checked by whoever reads it).
    fn put_log(&mut self, zone: ZoneId, tick: u64, bytes: &[u8]) -> Result<(), ZoneError>;
    /// Zone `zone`'s intent log segment that starts at `tick`, as stored.
    fn get_log(&mut self, zone: ZoneId, tick: u64) -> Result<Vec<u8>, ZoneError>;

    /// The first of `candidates` that all `zones` zones have stored, if any.
    fn latest_consistent(&mut self, zones: usize, candidates: &[u64]) -> Result<Option<u64>, ZoneError> {
        for &t in candidates {
            let mut all = true;
            for z in 0..zones {
                if !self.has(ZoneId(z as u16), t)? {
                    all = false;
                    break;
                }
            }
            if all {
                return Ok(Some(t));
            }
        }
        Ok(None)
    }
}

/// The object store bucket of `cluster`'s checkpoints: `myriad-<cluster>`.
pub fn bucket_name(cluster: &str) -> String {
    format!("myriad-{cluster}")
}

fn name(zone: ZoneId, tick: u64) -> String {
    format!("z{}-t{tick}", zone.0)
}

/// The name of a zone's intent log segment that starts at `tick`.
fn log_name(zone: ZoneId, tick: u64) -> String {
    format!("z{}-t{tick}-log", zone.0)
}

fn checked(key: &ClusterKey, bytes: &[u8], zone: ZoneId, tick: u64) -> Result<Snapshot, ZoneError> {
    match decode(key, bytes) {
        Ok(Message::Checkpoint { run, tick: t, zone: z, cuts, objects }) if t == tick && z == zone => {
            Ok(Snapshot { run, cuts, objects })
        }
        Ok(_) => Err(ZoneError::Checkpoint(format!("{} holds another zone's or tick's state", name(zone, tick)))),
        Err(e) => Err(ZoneError::Checkpoint(format!("{} refused: {e}", name(zone, tick)))),
    }
}

/// Checkpoints in a JetStream object store bucket `myriad-<cluster>`.
pub struct JetStreamCheckpoints {
    rt: Arc<tokio::runtime::Runtime>,
    js: async_nats::jetstream::Context,
    bucket: String,
    store: async_nats::jetstream::object_store::ObjectStore,
    key: ClusterKey,
}

impl JetStreamCheckpoints {
    /// Opens (or creates) the cluster's bucket on `client`'s server.
    pub fn open(
        rt: Arc<tokio::runtime::Runtime>,
        client: async_nats::Client,
        cluster: &str,
        key: ClusterKey,
    ) -> Result<JetStreamCheckpoints, ZoneError> {
        // The context spawns a task: it must be made inside the runtime.
        let js = {
            let _inside = rt.enter();
            async_nats::jetstream::new(client)
        };
        let bucket = bucket_name(cluster);
        let store = rt.block_on(async {
            match js.get_object_store(&bucket).await {
                Ok(s) => Ok(s),
                Err(_) => js
                    .create_object_store(async_nats::jetstream::object_store::Config {
                        bucket: bucket.clone(),
                        description: Some("Myriad zone checkpoints".into()),
                        ..Default::default()
                    })
                    .await
                    .map_err(|e| ZoneError::Checkpoint(format!("creating bucket {bucket}: {e}"))),
            }
        })?;
        Ok(JetStreamCheckpoints { rt, js, bucket, store, key })
    }

    /// Deletes the bucket and every checkpoint in it (a run that cannot be resumed,
    /// such as `myriad cluster` under a name of its own, leaves nothing behind).
    pub fn delete(self) -> Result<(), ZoneError> {
        let (js, bucket) = (self.js, self.bucket);
        self.rt
            .block_on(async { js.delete_object_store(&bucket).await })
            .map(|_| ())
            .map_err(|e| ZoneError::Checkpoint(format!("deleting bucket {bucket}: {e}")))
    }
}

impl JetStreamCheckpoints {
    fn put_bytes(&self, name: &str, bytes: &[u8]) -> Result<(), ZoneError> {
        let store = &self.store;
        self.rt.block_on(async {
            store
                .put(name, &mut &bytes[..])
                .await
                .map(|_| ())
                .map_err(|e| ZoneError::Checkpoint(format!("storing {name}: {e}")))
        })
    }

    fn get_bytes(&self, name: &str) -> Result<Vec<u8>, ZoneError> {
        let store = &self.store;
        self.rt.block_on(async {
            let mut o = store.get(name).await.map_err(|e| ZoneError::Checkpoint(format!("reading {name}: {e}")))?;
            let mut b = Vec::new();
            o.read_to_end(&mut b).await.map_err(|e| ZoneError::Checkpoint(format!("reading {name}: {e}")))?;
            Ok(b)
        })
    }
}

impl CheckpointStore for JetStreamCheckpoints {
    fn put(
        &mut self,
        zone: ZoneId,
        tick: u64,
        run: u64,
        cuts: &Cuts,
        objects: &[ObjectState],
    ) -> Result<(), ZoneError> {
        let bytes = encode_checkpoint(&self.key, run, tick, zone, cuts, objects)?;
        self.put_bytes(&name(zone, tick), &bytes)
    }

    fn has(&mut self, zone: ZoneId, tick: u64) -> Result<bool, ZoneError> {
        let store = &self.store;
        Ok(self.rt.block_on(async { store.info(name(zone, tick)).await }).is_ok_and(|i| !i.deleted))
    }

    fn get(&mut self, zone: ZoneId, tick: u64) -> Result<Snapshot, ZoneError> {
        let bytes = self.get_bytes(&name(zone, tick))?;
        checked(&self.key, &bytes, zone, tick)
    }

    fn forget(&mut self, zone: ZoneId, tick: u64) -> Result<(), ZoneError> {
        let store = &self.store;
        // Deleting what is not there is not an error: an old checkpoint may be gone.
        for n in [name(zone, tick), log_name(zone, tick)] {
            let _ = self.rt.block_on(async { store.delete(n).await });
        }
        Ok(())
    }

    fn put_log(&mut self, zone: ZoneId, tick: u64, bytes: &[u8]) -> Result<(), ZoneError> {
        self.put_bytes(&log_name(zone, tick), bytes)
    }

    fn get_log(&mut self, zone: ZoneId, tick: u64) -> Result<Vec<u8>, ZoneError> {
        self.get_bytes(&log_name(zone, tick))
    }
}

/// Signed checkpoints and intent logs by (zone, tick, whether a log).
type Blobs = BTreeMap<(ZoneId, u64, bool), Vec<u8>>;

/// Checkpoints in memory, shared by clones (tests, and zones of one process).
#[derive(Clone, Default)]
pub struct MemoryCheckpoints {
    blobs: Arc<Mutex<Blobs>>,
    key: Option<ClusterKey>,
}

impl MemoryCheckpoints {
    /// An empty store signing with `key`.
    pub fn new(key: ClusterKey) -> MemoryCheckpoints {
        MemoryCheckpoints { blobs: Arc::default(), key: Some(key) }
    }
}

impl CheckpointStore for MemoryCheckpoints {
    fn put(
        &mut self,
        zone: ZoneId,
        tick: u64,
        run: u64,
        cuts: &Cuts,
        objects: &[ObjectState],
    ) -> Result<(), ZoneError> {
        let key = self.key.as_ref().ok_or_else(|| ZoneError::Checkpoint("no key".into()))?;
        let bytes = encode_checkpoint(key, run, tick, zone, cuts, objects)?;
        self.blobs.lock().expect("not poisoned").insert((zone, tick, false), bytes);
        Ok(())
    }

    fn has(&mut self, zone: ZoneId, tick: u64) -> Result<bool, ZoneError> {
        Ok(self.blobs.lock().expect("not poisoned").contains_key(&(zone, tick, false)))
    }

    fn get(&mut self, zone: ZoneId, tick: u64) -> Result<Snapshot, ZoneError> {
        let key = self.key.as_ref().ok_or_else(|| ZoneError::Checkpoint("no key".into()))?;
        let blobs = self.blobs.lock().expect("not poisoned");
        let bytes =
            blobs.get(&(zone, tick, false)).ok_or_else(|| ZoneError::Checkpoint(format!("no {}", name(zone, tick))))?;
        checked(key, bytes, zone, tick)
    }

    fn forget(&mut self, zone: ZoneId, tick: u64) -> Result<(), ZoneError> {
        let mut blobs = self.blobs.lock().expect("not poisoned");
        blobs.remove(&(zone, tick, false));
        blobs.remove(&(zone, tick, true));
        Ok(())
    }

    fn put_log(&mut self, zone: ZoneId, tick: u64, bytes: &[u8]) -> Result<(), ZoneError> {
        self.blobs.lock().expect("not poisoned").insert((zone, tick, true), bytes.to_vec());
        Ok(())
    }

    fn get_log(&mut self, zone: ZoneId, tick: u64) -> Result<Vec<u8>, ZoneError> {
        let blobs = self.blobs.lock().expect("not poisoned");
        blobs
            .get(&(zone, tick, true))
            .cloned()
            .ok_or_else(|| ZoneError::Checkpoint(format!("no {}", log_name(zone, tick))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::Vec3;

    #[test]
    fn the_latest_consistent_tick_is_common_to_all_zones() {
        let mut s = MemoryCheckpoints::new(ClusterKey::random());
        let o = crate::test_objects::npc_at(1, Vec3::ONE);
        let candidates = [60, 30, 0];
        assert_eq!(s.latest_consistent(2, &candidates).unwrap(), None);
        let cuts = (vec![0.0, 5.0, 10.0], vec![0.0, 10.0]);
        for (z, t) in [(0, 0), (1, 0), (0, 30), (1, 30), (0, 60)] {
            s.put(ZoneId(z), t, 1, &cuts, &[o]).unwrap();
        }
        assert_eq!(s.latest_consistent(2, &candidates).unwrap(), Some(30));
        assert_eq!(s.latest_consistent(3, &candidates).unwrap(), None);
        s.forget(ZoneId(1), 30).unwrap();
        assert_eq!(s.latest_consistent(2, &candidates).unwrap(), Some(0));
        assert_eq!(s.get(ZoneId(0), 60).unwrap(), Snapshot { run: 1, cuts, objects: vec![o] });
        assert!(s.get(ZoneId(1), 60).is_err());
        // A blob signed with another key is refused.
        let mut other = MemoryCheckpoints { blobs: s.blobs.clone(), key: Some(ClusterKey::random()) };
        assert!(matches!(other.get(ZoneId(0), 60), Err(ZoneError::Checkpoint(_))));
    }
}
