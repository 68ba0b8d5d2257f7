//! Argon2id password hashing, always off the async threads.
//!
//! Hashes are PHC strings (`$argon2id$v=19$m=...,t=...,p=...$salt$hash`): the cost is
//! stored with each hash, so raising [`HashCost`] later only affects new hashes and old
//! ones still verify. Hashing takes tens to hundreds of milliseconds by design, so it
//! never runs on a runtime worker (or the server's tick thread).
//!
//! # The verification pool
//!
//! Verifications ([`verify_password`], so every login) run on one process-wide pool of
//! threads ([`configure_hash_pool`]; by default the cores less one, at least one), not on
//! tokio's blocking pool. Each pool thread keeps its Argon2 working memory (19 MiB at the
//! default cost) and reuses it for the next verification
//! (`Argon2::hash_password_into_with_memory`): the process's memory for hashing is
//! `threads × m_kib`, allocated once, instead of a fresh block per login that the
//! allocator may keep after it is freed. The pool's queue is not bounded here: the
//! caller (the login service) bounds what it submits and how long it waits. Creating
//! hashes (new users, password changes) is rare and stays on the blocking pool.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use argon2::{Algorithm, Argon2, Block, Params, PasswordHash, PasswordHasher, Version};

use crate::error::{Result, StoreError};

/// Longest accepted username in bytes (the login packet's username field is 32 bytes).
pub const MAX_USERNAME_LEN: usize = 32;
/// Longest accepted password in bytes (the login packet's password field is 64 bytes).
pub const MAX_PASSWORD_LEN: usize = 64;

/// Argon2id cost parameters used for new hashes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HashCost {
    /// Memory in KiB (at least `8 * p`).
    pub m_kib: u32,
    /// Number of passes.
    pub t: u32,
    /// Degree of parallelism (lanes).
    pub p: u32,
}

impl HashCost {
    /// The OWASP-recommended Argon2id minimum (19 MiB, 2 passes, 1 lane), also argon2's
    /// default: about 20-40 ms per hash or verification in a release build on one core
    /// (measured: see the crate README).
    pub const DEFAULT: HashCost = HashCost { m_kib: 19 * 1024, t: 2, p: 1 };

    /// A cheap cost for tests and benchmarks of everything but hashing. Never use it for
    /// real accounts: it offers almost no resistance to offline guessing.
    pub const INSECURE_FAST: HashCost = HashCost { m_kib: 64, t: 1, p: 1 };

    fn hasher(self) -> Result<Argon2<'static>> {
        let params = Params::new(self.m_kib, self.t, self.p, None)
            .map_err(|e| StoreError::InvalidInput(format!("argon2 cost {self:?}: {e}")))?;
        Ok(Argon2::new(Algorithm::Argon2id, Version::V0x13, params))
    }

    /// Checks that argon2 accepts these parameters.
    pub fn validate(self) -> Result<()> {
        self.hasher().map(|_| ())
    }
}

impl Default for HashCost {
    fn default() -> Self {
        HashCost::DEFAULT
    }
}

/// Rejects usernames the login packet cannot carry or that would compare differently on
/// the two backends: 1 to 32 bytes of ASCII letters, digits, `_`, `-` and `.`.
///
/// Restricting to ASCII keeps uniqueness identical on SQLite (`COLLATE NOCASE`, ASCII
/// case folding) and MariaDB (`utf8mb4_unicode_ci`, which would also fold accents and
/// ignore trailing spaces).
pub fn validate_username(username: &str) -> Result<()> {
    if username.is_empty() || username.len() > MAX_USERNAME_LEN {
        return Err(StoreError::InvalidInput(format!("username must be 1 to {MAX_USERNAME_LEN} bytes")));
    }
    if !username.bytes().all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-' | b'.')) {
        return Err(StoreError::InvalidInput(
            "username may only contain ASCII letters, digits, '_', '-' and '.'".into(),
        ));
    }
    Ok(())
}

/// Rejects empty passwords and passwords longer than the login packet's 64 bytes.
pub fn validate_password(password: &str) -> Result<()> {
    if password.is_empty() || password.len() > MAX_PASSWORD_LEN {
        return Err(StoreError::InvalidInput(format!("password must be 1 to {MAX_PASSWORD_LEN} bytes")));
    }
    Ok(())
}

/// Hashes synchronously; call only from a blocking context.
pub(crate) fn hash_blocking(cost: HashCost, password: &[u8]) -> Result<String> {
    let hash = cost
        .hasher()?
        .hash_password(password)
        .map_err(|e| StoreError::Internal(format!("argon2 hashing failed: {e}")))?;
    Ok(hash.to_string())
}

/// Verifies synchronously; call only from a blocking context. A malformed stored hash
/// counts as a mismatch (and is logged without its content).
#[cfg(test)]
pub(crate) fn verify_blocking(password: &[u8], phc: &str) -> bool {
    verify_with_memory(password, phc, &mut Vec::new())
}

/// Verifies `password` against a PHC string with `memory` as Argon2's working memory,
/// grown when the hash's cost needs more and otherwise reused as is. The comparison of
/// the outputs is constant-time.
fn verify_with_memory(password: &[u8], phc: &str, memory: &mut Vec<Block>) -> bool {
    match try_verify(password, phc, memory) {
        Ok(matches) => matches,
        Err(e) => {
            tracing::warn!(error = %e, "stored password hash could not be verified");
            false
        }
    }
}

fn try_verify(password: &[u8], phc: &str, memory: &mut Vec<Block>) -> std::result::Result<bool, String> {
    // The parameters come from the PHC string itself, not from the configured cost.
    let parsed = PasswordHash::new(phc).map_err(|e| e.to_string())?;
    let (Some(salt), Some(expected)) = (&parsed.salt, &parsed.hash) else {
        return Err("the stored hash has no salt or no output".into());
    };
    let algorithm = Algorithm::new(parsed.algorithm.as_str()).map_err(|e| e.to_string())?;
    let version = match parsed.version {
        Some(v) => Version::try_from(v).map_err(|e| e.to_string())?,
        None => Version::default(),
    };
    let params = Params::try_from(&parsed).map_err(|e| e.to_string())?;
    let blocks = params.block_count();
    if memory.len() < blocks {
        memory.resize(blocks, Block::default());
    }
    let mut out = vec![0u8; expected.len()];
    Argon2::new(algorithm, version, params)
        .hash_password_into_with_memory(password, salt, &mut out, &mut memory[..blocks])
        .map_err(|e| e.to_string())?;
    // `Output`'s equality is constant-time.
    let computed = argon2::password_hash::phc::Output::new(&out).map_err(|e| e.to_string())?;
    Ok(computed == *expected)
}

type Job = Box<dyn FnOnce(&mut Vec<Block>) + Send>;

/// The process-wide verification pool; see the module docs.
struct HashPool {
    jobs: Mutex<mpsc::Sender<Job>>,
    threads: usize,
}

static POOL: OnceLock<HashPool> = OnceLock::new();
/// Threads the pool will start with (0: the cores less one).
static POOL_THREADS: AtomicUsize = AtomicUsize::new(0);
/// Bytes of Argon2 working memory held by the pool's threads, together.
static POOL_MEMORY: AtomicU64 = AtomicU64::new(0);
/// Verifications the pool has run.
static POOL_VERIFIED: AtomicU64 = AtomicU64::new(0);

/// How long a hashing thread keeps its working memory without a job. A burst of logins
/// reuses it (no allocation per check, which glibc would keep); a server with no logins
/// gives it back: an Argon2 buffer (19 MiB at the default cost) is one mapping of its
/// own, so freeing it returns it to the system at once.
const IDLE_RELEASE: Duration = Duration::from_secs(10);

/// One hashing thread: runs jobs with its working memory, and frees that memory after
/// `idle` without a job (subtracting it from `held`, where the jobs added it).
fn hashing_thread(jobs: &Mutex<mpsc::Receiver<Job>>, idle: Duration, held: &AtomicU64) {
    let mut memory: Vec<Block> = Vec::new();
    loop {
        // Hold the lock only to take a job, never while hashing.
        let job = jobs.lock().unwrap_or_else(|p| p.into_inner()).recv_timeout(idle);
        match job {
            Ok(job) => job(&mut memory),
            Err(RecvTimeoutError::Timeout) if !memory.is_empty() => {
                held.fetch_sub((memory.len() * Block::SIZE) as u64, Ordering::Relaxed);
                memory = Vec::new();
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return,
        }
    }
}

/// Runs first on every thread of the pool (the server lowers their priority there).
static POOL_THREAD_START: OnceLock<fn()> = OnceLock::new();

/// Sets the number of threads of the verification pool and a function each of them runs
/// first (say, to lower its priority below the tick's). Takes effect only before the
/// pool's first use (it starts on the first verification); returns whether it did.
pub fn configure_hash_pool(threads: usize, on_thread_start: fn()) -> bool {
    POOL_THREADS.store(threads.max(1), Ordering::Relaxed);
    let _ = POOL_THREAD_START.set(on_thread_start);
    POOL.get().is_none()
}

/// What the verification pool holds: its threads, the bytes of Argon2 working memory
/// they keep (together), and verifications run so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HashPoolStats {
    /// Threads of the pool (0 before its first use).
    pub threads: usize,
    /// Bytes of working memory held, over all threads.
    pub memory_bytes: u64,
    /// Verifications run.
    pub verified: u64,
}

/// The verification pool's figures now.
pub fn hash_pool_stats() -> HashPoolStats {
    HashPoolStats {
        threads: POOL.get().map_or(0, |p| p.threads),
        memory_bytes: POOL_MEMORY.load(Ordering::Relaxed),
        verified: POOL_VERIFIED.load(Ordering::Relaxed),
    }
}

fn pool() -> &'static HashPool {
    POOL.get_or_init(|| {
        let threads = match POOL_THREADS.load(Ordering::Relaxed) {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1)).max(1),
            n => n,
        };
        let (jobs, receiver) = mpsc::channel::<Job>();
        let receiver = Arc::new(Mutex::new(receiver));
        for i in 0..threads {
            let receiver = receiver.clone();
            let spawned = std::thread::Builder::new().name(format!("myriad-hash-{i}")).spawn(move || {
                if let Some(start) = POOL_THREAD_START.get() {
                    start();
                }
                hashing_thread(&receiver, IDLE_RELEASE, &POOL_MEMORY)
            });
            if let Err(e) = spawned {
                tracing::error!(error = %e, "cannot start a password-hashing thread");
            }
        }
        HashPool { jobs: Mutex::new(jobs), threads }
    })
}

/// Runs `f` on the verification pool with the thread's reusable working memory.
async fn on_pool<T: Send + 'static>(f: impl FnOnce(&mut Vec<Block>) -> T + Send + 'static) -> Result<T> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job: Job = Box::new(move |memory| {
        let before = memory.len();
        let out = f(memory);
        // Counted before the answer goes back, so a caller that reads the figures after
        // its answer sees its own verification in them.
        if memory.len() > before {
            let grown = (memory.len() - before) * Block::SIZE;
            POOL_MEMORY.fetch_add(grown as u64, Ordering::Relaxed);
        }
        POOL_VERIFIED.fetch_add(1, Ordering::Relaxed);
        let _ = tx.send(out);
    });
    pool()
        .jobs
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .send(job)
        .map_err(|_| StoreError::Internal("the password-hashing pool has stopped".into()))?;
    rx.await.map_err(|_| StoreError::Internal("a password-hashing thread failed".into()))
}

/// Hashes `password` with `cost` on the blocking pool.
pub async fn hash_password(cost: HashCost, password: &str) -> Result<String> {
    let password = password.as_bytes().to_vec();
    spawn_blocking(move || hash_blocking(cost, &password)).await?
}

/// Verifies `password` against a PHC string on the verification pool (module docs).
pub async fn verify_password(password: &str, phc: String) -> Result<bool> {
    #[cfg(test)]
    VERIFIED_HASHES.lock().unwrap_or_else(|p| p.into_inner()).push(phc.clone());
    let password = password.as_bytes().to_vec();
    on_pool(move |memory| verify_with_memory(&password, &phc, memory)).await
}

/// Every hash [`verify_password`] was asked to check, in this test binary: lets a test see
/// which work a login did instead of timing it (timings on shared machines decide nothing).
#[cfg(test)]
pub(crate) static VERIFIED_HASHES: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Runs `f` on the blocking pool and turns a panic or cancellation into an error.
pub(crate) async fn spawn_blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T> {
    tokio::task::spawn_blocking(f).await.map_err(|e| StoreError::Internal(format!("blocking task failed: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_idle_hashing_thread_gives_its_memory_back() {
        let (jobs, receiver) = mpsc::channel::<Job>();
        let held = Arc::new(AtomicU64::new(0));
        let thread = {
            let held = held.clone();
            std::thread::spawn(move || hashing_thread(&Mutex::new(receiver), Duration::from_millis(50), &held))
        };
        type Probe = Box<dyn FnOnce(&mut Vec<Block>) -> usize + Send>;
        let ask = |job: Probe| {
            let (tx, rx) = mpsc::channel();
            let held = held.clone();
            jobs.send(Box::new(move |memory: &mut Vec<Block>| {
                let before = memory.len();
                let seen = job(memory);
                held.fetch_add(((memory.len() - before) * Block::SIZE) as u64, Ordering::Relaxed);
                tx.send(seen).unwrap();
            }))
            .unwrap();
            rx.recv().unwrap()
        };
        // Two jobs in a row: the second finds the first one's memory.
        assert_eq!(ask(Box::new(|m| std::mem::replace(m, vec![Block::default(); 64]).len())), 0);
        assert_eq!(ask(Box::new(|m| m.len())), 64, "kept between jobs");
        assert_eq!(held.load(Ordering::Relaxed), 64 * Block::SIZE as u64);
        std::thread::sleep(Duration::from_millis(300));
        assert_eq!(held.load(Ordering::Relaxed), 0, "freed after the idle time");
        assert_eq!(ask(Box::new(|m| m.len())), 0, "the next job starts with none");
        drop(jobs);
        thread.join().unwrap();
    }

    #[test]
    fn usernames_are_checked() {
        for ok in ["a", "user0", "A.b-c_d", &"x".repeat(MAX_USERNAME_LEN)] {
            assert!(validate_username(ok).is_ok(), "{ok:?}");
        }
        for bad in ["", " ", "a b", "é", "a\0", "a'b", &"x".repeat(MAX_USERNAME_LEN + 1)] {
            assert!(matches!(validate_username(bad), Err(StoreError::InvalidInput(_))), "{bad:?}");
        }
    }

    #[test]
    fn passwords_are_checked_by_bytes() {
        assert!(validate_password("x").is_ok());
        assert!(validate_password(&"p".repeat(MAX_PASSWORD_LEN)).is_ok());
        assert!(validate_password("").is_err());
        // 33 two-byte characters are 66 bytes: over the packet's 64.
        assert!(validate_password(&"é".repeat(33)).is_err());
    }

    #[test]
    fn hashes_are_argon2id_phc_strings_that_verify() {
        let hash = hash_blocking(HashCost::INSECURE_FAST, "pässword".as_bytes()).unwrap();
        assert!(hash.starts_with("$argon2id$v=19$m=64,t=1,p=1$"), "{hash}");
        assert!(verify_blocking("pässword".as_bytes(), &hash));
        assert!(!verify_blocking(b"password", &hash));
        // Salted: the same password hashes differently.
        let again = hash_blocking(HashCost::INSECURE_FAST, "pässword".as_bytes()).unwrap();
        assert_ne!(hash, again);
        // A malformed stored hash is a mismatch, not a panic.
        assert!(!verify_blocking(b"x", "not a hash"));
        assert!(!verify_blocking(b"x", ""));
    }

    #[tokio::test]
    async fn the_pool_verifies_and_reuses_its_memory() {
        let cost = HashCost { m_kib: 256, t: 1, p: 1 };
        let hash = hash_blocking(cost, b"secret").unwrap();
        assert!(verify_password("secret", hash.clone()).await.unwrap());
        assert!(!verify_password("secret!", hash.clone()).await.unwrap());
        let held = hash_pool_stats().memory_bytes;
        assert!(held >= 256 * 1024, "the working memory is kept: {held}");
        for _ in 0..8 {
            assert!(verify_password("secret", hash.clone()).await.unwrap());
        }
        let stats = hash_pool_stats();
        // Every thread grows its memory to the largest cost it has seen, once: no
        // verification of the same cost allocates again.
        assert!(stats.memory_bytes <= stats.threads as u64 * 256 * 1024, "{stats:?}");
        assert!(stats.verified >= 10);
        // A hash made by argon2's own API verifies with the reused memory, and a
        // malformed one is a mismatch.
        let other = cost.hasher().unwrap().hash_password(b"x").unwrap().to_string();
        assert!(verify_password("x", other).await.unwrap());
        assert!(!verify_password("x", "$argon2id$garbage".into()).await.unwrap());
    }

    #[test]
    fn bad_costs_are_rejected() {
        assert!(HashCost::DEFAULT.validate().is_ok());
        assert!(HashCost::INSECURE_FAST.validate().is_ok());
        let too_little_memory = HashCost { m_kib: 1, t: 1, p: 1 };
        assert!(matches!(too_little_memory.validate(), Err(StoreError::InvalidInput(_))));
        assert!(HashCost { m_kib: 64, t: 0, p: 1 }.validate().is_err());
        assert!(HashCost { m_kib: 64, t: 1, p: 0 }.validate().is_err());
    }
}
