//! Deterministic, shardable, checkpointed execution of a simulation split
//! into fixed chunks.
//!
//! A simulation of N paths is cut into `ceil(N / CHUNK_PATHS)` chunks of
//! consecutive path indices. The chunk size is a constant, never derived from
//! the thread count. Chunks run in parallel (rayon) in batches; each batch's
//! tallies are merged *in chunk order* into the running total. Tallies are
//! integer counts, so the merge is exact and the result is bitwise the same
//! for any thread count, and for shards merged afterwards. A shard `k/N`
//! (0-based k) is the contiguous chunk range `[k·C/N, (k+1)·C/N)`.
//!
//! Between batches the runner may write a checkpoint (the running tally and
//! the next chunk) to a [`CheckpointStore`] (the job layer's is a file,
//! replaced atomically: [`crate::jobs::store::FileCheckpoint`]); a resumed
//! run starts from it and ends with the same tally as an uninterrupted one.

use crate::error::{Error, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Paths per chunk. Changing it changes nothing in the results (every path
/// has its own stream); it sets the granularity of checkpoints and shards.
pub const CHUNK_PATHS: u64 = 1 << 14;
/// Chunks per batch between two checkpoint opportunities.
const BATCH_CHUNKS: u64 = 32;

/// Anything the runner can accumulate.
pub trait Tally: Clone + Send + Serialize + DeserializeOwned {
    fn merge(&mut self, other: &Self);
}

impl Tally for super::tally::ProfileTally {
    fn merge(&mut self, other: &Self) {
        super::tally::ProfileTally::merge(self, other)
    }
}

/// `--shard k/N`: the k-th of N slices (0-based).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    /// Parses `k/N` with 0 ≤ k < N.
    pub fn parse(s: &str) -> Result<Self> {
        const ALLOWED: &str = "k/N with integers 0 <= k < N";
        let (k, n) = s
            .split_once('/')
            .ok_or_else(|| Error::param("shard", s, ALLOWED))?;
        match (k.trim().parse::<u64>(), n.trim().parse::<u64>()) {
            (Ok(index), Ok(count)) if index < count => Ok(Shard { index, count }),
            _ => Err(Error::param("shard", s, ALLOWED)),
        }
    }
}

/// The chunk range `[lo, hi)` of a simulation of `paths` paths, or of one shard of it.
pub fn chunk_range(paths: u64, shard: Option<Shard>) -> (u64, u64) {
    shard_range(paths.div_ceil(CHUNK_PATHS), shard)
}

/// The chunk range `[lo, hi)` of a simulation of `chunks` chunks, or of one
/// shard of it.
pub fn shard_range(chunks: u64, shard: Option<Shard>) -> (u64, u64) {
    match shard {
        None => (0, chunks),
        Some(Shard { index, count }) => {
            let at = |k: u64| ((k as u128 * chunks as u128) / count as u128) as u64;
            (at(index), at(index + 1))
        }
    }
}

/// The path range `[first, first + count)` of chunk `c`.
pub fn chunk_paths(paths: u64, c: u64) -> (u64, u64) {
    let first = c * CHUNK_PATHS;
    (first, CHUNK_PATHS.min(paths.saturating_sub(first)))
}

/// Paths in the chunk ranges `chunks` of a simulation of `paths` paths.
pub fn paths_in(paths: u64, chunks: &[(u64, u64)]) -> u64 {
    let end = |c: u64| c.saturating_mul(CHUNK_PATHS).min(paths);
    chunks
        .iter()
        .map(|&(lo, hi)| end(hi) - end(lo.min(hi)))
        .sum()
}

/// Joins the chunk ranges of documents to be merged: they must be disjoint
/// (the same shard twice is an error naming the file); adjacent ranges are
/// coalesced, sorted.
pub fn join_chunks<'a>(
    inputs: impl IntoIterator<Item = (&'a std::path::Path, &'a [(u64, u64)])>,
) -> Result<Vec<(u64, u64)>> {
    let mut chunks: Vec<(u64, u64)> = Vec::new();
    for (path, ranges) in inputs {
        for &(lo, hi) in ranges {
            if chunks.iter().any(|&(a, b)| lo < b && a < hi) {
                return Err(Error::Merge {
                    path: path.to_path_buf(),
                    msg: format!("chunks {lo}..{hi} overlap another input (the same shard twice?)"),
                });
            }
            chunks.push((lo, hi));
        }
    }
    chunks.sort();
    let mut joined: Vec<(u64, u64)> = Vec::new();
    for (lo, hi) in chunks {
        match joined.last_mut() {
            Some(last) if last.1 == lo => last.1 = hi,
            _ => joined.push((lo, hi)),
        }
    }
    Ok(joined)
}

/// Checkpoint of a running simulation. `key` identifies the configuration
/// and `range` the chunks the run covers: a resumed run must be the same
/// simulation *and* the same shard, or its tally would claim chunks it does
/// not hold (a shard 1/3 checkpoint resumed as shard 1/2 counts the overlap
/// twice once merged).
#[derive(Serialize, Deserialize)]
struct Checkpoint<T> {
    format: String,
    key: serde_json::Value,
    range: (u64, u64),
    next_chunk: u64,
    wall_s: f64,
    tally: T,
}

/// Where a run keeps its checkpoint: serialised bytes, written whole or not
/// at all. The runner never opens files itself.
pub trait CheckpointStore: Send + Sync + std::fmt::Debug {
    /// What errors name (a file path).
    fn origin(&self) -> &Path;
    /// The stored checkpoint, if there is one.
    fn load(&self) -> Result<Option<Vec<u8>>>;
    /// Replaces the stored checkpoint.
    fn save(&self, bytes: &[u8]) -> Result<()>;
    /// Removes the stored checkpoint (the run finished).
    fn clear(&self) -> Result<()>;
}

/// How to run: where to checkpoint, how often, whether to resume, progress.
#[derive(Clone, Debug, Default)]
pub struct RunOptions {
    /// Checkpoint store; `None` disables checkpoints.
    pub checkpoint: Option<Arc<dyn CheckpointStore>>,
    /// Minimum time between two checkpoints (a checkpoint is written after
    /// the first batch that ends past it).
    pub checkpoint_every: Duration,
    /// Continue from the checkpoint if one exists.
    pub resume: bool,
    /// Report progress on stderr ([`crate::progress`]: a bar on a terminal,
    /// log lines otherwise).
    pub progress: bool,
}

/// Result of [`run`]: the tally and the wall time spent on it, including
/// time spent before a resume.
pub struct RunOutcome<T> {
    pub tally: T,
    pub wall_s: f64,
}

/// Runs chunks `range.0..range.1`, computing each with `chunk` and merging in
/// chunk order into `empty`.
pub fn run<T: Tally>(
    key: &serde_json::Value,
    range: (u64, u64),
    empty: T,
    chunk: impl Fn(u64) -> T + Sync,
    opts: &RunOptions,
) -> Result<RunOutcome<T>> {
    let start = Instant::now();
    let (mut next, mut total, mut wall_before) = (range.0, empty, 0.0);
    if let (true, Some(store)) = (opts.resume, &opts.checkpoint)
        && let Some(bytes) = store.load()?
    {
        let path = store.origin();
        let ck: Checkpoint<T> = serde_json::from_slice(&bytes)
            .map_err(|e| Error::format(path, "(json)", e.to_string()))?;
        if &ck.key != key {
            return Err(Error::format(
                path,
                "key",
                "checkpoint belongs to a different simulation (configuration differs)",
            ));
        }
        if ck.range != range {
            return Err(Error::format(
                path,
                "range",
                format!(
                    "checkpoint covers chunks {}..{}, this run {}..{} (another shard layout)",
                    ck.range.0, ck.range.1, range.0, range.1
                ),
            ));
        }
        if !(range.0..=range.1).contains(&ck.next_chunk) {
            return Err(Error::format(
                path,
                "next_chunk",
                "outside this run's chunk range",
            ));
        }
        next = ck.next_chunk;
        total = ck.tally;
        wall_before = ck.wall_s;
    }
    let label = if next > range.0 {
        "simulating (resumed from its checkpoint)"
    } else {
        "simulating"
    };
    let bar = crate::progress::Task::new(opts.progress, label, range.1 - range.0, "chunks");
    bar.set(next - range.0);
    let mut last_checkpoint = Instant::now();
    while next < range.1 {
        let hi = (next + BATCH_CHUNKS).min(range.1);
        let parts: Vec<T> = (next..hi).into_par_iter().map(&chunk).collect();
        for p in &parts {
            total.merge(p);
        }
        next = hi;
        bar.set(next - range.0);
        if let Some(store) = &opts.checkpoint
            && next < range.1
            && last_checkpoint.elapsed() >= opts.checkpoint_every
        {
            let ck = Checkpoint {
                format: "svkernel.checkpoint".into(),
                key: key.clone(),
                range,
                next_chunk: next,
                wall_s: wall_before + start.elapsed().as_secs_f64(),
                tally: total.clone(),
            };
            // Compact: a reference tally at 4096² × 3 is hundreds of MB.
            let bytes = serde_json::to_vec(&ck)
                .map_err(|e| Error::format(store.origin(), "(json)", e.to_string()))?;
            store.save(&bytes)?;
            last_checkpoint = Instant::now();
        }
    }
    bar.finish();
    Ok(RunOutcome {
        tally: total,
        wall_s: wall_before + start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_tile_the_chunks() {
        for paths in [1, CHUNK_PATHS, 10 * CHUNK_PATHS + 3, 1_000_003] {
            for n in 1..7 {
                let mut expect = 0;
                for k in 0..n {
                    let (lo, hi) = chunk_range(paths, Some(Shard { index: k, count: n }));
                    assert_eq!(lo, expect);
                    expect = hi;
                }
                assert_eq!(expect, chunk_range(paths, None).1);
            }
            let total: u64 = (0..chunk_range(paths, None).1)
                .map(|c| chunk_paths(paths, c).1)
                .sum();
            assert_eq!(total, paths);
        }
    }

    /// The chunks a run merged, in order.
    #[derive(Clone, Default, Serialize, Deserialize)]
    struct Seen(Vec<u64>);

    impl Tally for Seen {
        fn merge(&mut self, o: &Self) {
            self.0.extend_from_slice(&o.0);
        }
    }

    /// A checkpoint kept in memory.
    #[derive(Debug, Default)]
    struct Memory(std::sync::Mutex<Option<Vec<u8>>>);

    impl CheckpointStore for Memory {
        fn origin(&self) -> &Path {
            Path::new("run.ckpt")
        }
        fn load(&self) -> Result<Option<Vec<u8>>> {
            Ok(self.0.lock().unwrap().clone())
        }
        fn save(&self, bytes: &[u8]) -> Result<()> {
            *self.0.lock().unwrap() = Some(bytes.to_vec());
            Ok(())
        }
        fn clear(&self) -> Result<()> {
            *self.0.lock().unwrap() = None;
            Ok(())
        }
    }

    #[test]
    fn a_checkpoint_resumes_only_its_own_chunk_range() {
        let opts = RunOptions {
            checkpoint: Some(Arc::new(Memory::default())),
            checkpoint_every: Duration::ZERO,
            resume: true,
            progress: false,
        };
        let key = serde_json::json!({ "sim": 1 });
        let chunk = |c: u64| Seen(vec![c]);
        // Two batches: the checkpoint after the first (next chunk 32) stays.
        let full = run(&key, (0, 64), Seen::default(), chunk, &opts).unwrap();
        assert_eq!(full.tally.0, (0..64).collect::<Vec<_>>());
        // Resumed over the same range: the remaining chunks only, once each
        // (counted: a resume that silently restarted would give the same
        // tally).
        let calls = std::sync::atomic::AtomicU64::new(0);
        let counted = |c: u64| {
            calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            chunk(c)
        };
        let resumed = run(&key, (0, 64), Seen::default(), counted, &opts).unwrap();
        assert_eq!(resumed.tally.0, full.tally.0);
        assert_eq!(calls.into_inner(), 32, "chunks run again on resume");
        // Another shard layout whose range contains the checkpoint's next
        // chunk is refused: it would claim chunks 10..32 that it never ran.
        let err = run(&key, (10, 64), Seen::default(), chunk, &opts)
            .err()
            .expect("a checkpoint of another chunk range must be refused")
            .to_string();
        assert!(err.contains("run.ckpt") && err.contains("range"), "{err}");
    }

    #[test]
    fn shard_parse() {
        assert_eq!(Shard::parse("2/5").unwrap(), Shard { index: 2, count: 5 });
        for bad in ["5/5", "1", "a/b", "-1/3", "1/0"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
    }
}
