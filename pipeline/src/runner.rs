//! Make-style stage runner. Each stage declares its input files, its parameters (any serialisable value) and its
//! output files. A lock file records, per stage, the code version, a blake3 of the canonical parameters, and the
//! blake3 of every input and output. A stage is stale when any of those changed or an output is missing; `run`
//! executes only stale (or forced) stages, in order.
//!
//! Outputs are written under temporary names (`NAME.tmp`) that the runner renames only after the stage function
//! returns successfully, and the lock is updated after each stage. A run killed mid-stage therefore leaves no
//! finished-looking output and an unchanged lock entry: rerunning redoes exactly that stage.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dataset::files::{files_under, hash_file, tmp_path, write_json_atomic};
use serde::{Deserialize, Serialize};

/// What a stage function receives: where to write each declared output (temporary names).
pub struct StageOutputs {
    pub paths: Vec<PathBuf>,
}

type StageFn<'a> = Box<dyn Fn(&StageOutputs) -> anyhow::Result<()> + 'a>;
/// Extra staleness check for outputs the stage can't declare up front (e.g. shards listed by a manifest):
/// `Some(reason)` when they no longer match what the stage wrote.
type CheckFn<'a> = Box<dyn Fn() -> Option<String> + 'a>;

/// One stage: name, code version (bump when its logic changes), inputs, params and outputs.
pub struct Stage<'a> {
    pub name: &'static str,
    pub code_version: &'static str,
    pub inputs: Vec<PathBuf>,
    pub params: serde_json::Value,
    pub outputs: Vec<PathBuf>,
    pub run: StageFn<'a>,
    pub check: Option<CheckFn<'a>>,
}

/// What the lock remembers about a stage's last successful run.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LockEntry {
    pub code_version: String,
    pub params_blake3: String,
    pub inputs: BTreeMap<String, String>,
    pub outputs: BTreeMap<String, String>,
}

#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Lock {
    pub stages: BTreeMap<String, LockEntry>,
}

/// Why a stage must run (or that it need not).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Staleness {
    UpToDate,
    NeverRun,
    CodeChanged { was: String, now: String },
    ParamsChanged,
    InputChanged(String),
    OutputMissing(String),
    OutputChanged(String),
    UpstreamStale(&'static str),
}

impl std::fmt::Display for Staleness {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Staleness::UpToDate => write!(f, "up to date"),
            Staleness::NeverRun => write!(f, "stale: never run"),
            Staleness::CodeChanged { was, now } => write!(f, "stale: code version {was} → {now}"),
            Staleness::ParamsChanged => write!(f, "stale: parameters changed"),
            Staleness::InputChanged(p) => write!(f, "stale: input changed: {p}"),
            Staleness::OutputMissing(p) => write!(f, "stale: output missing: {p}"),
            Staleness::OutputChanged(p) => {
                write!(f, "stale: output modified since it was written: {p}")
            }
            Staleness::UpstreamStale(s) => write!(f, "stale: upstream stage '{s}' is stale"),
        }
    }
}

/// blake3 of the canonical JSON of a parameter value (serde_json maps are ordered, so this is stable).
pub fn params_hash(params: &serde_json::Value) -> String {
    blake3::hash(
        serde_json::to_string(params)
            .expect("JSON values serialise")
            .as_bytes(),
    )
    .to_hex()
    .to_string()
}

pub struct Runner<'a> {
    /// Lock keys are paths relative to this directory (the manifest's), so the lock is portable.
    pub root: PathBuf,
    /// Folders holding copies of inputs fetched from object storage, with the URL prefix each copies
    /// ([`crate::inputs`]): a file there is keyed by its object's URL, what the build read.
    pub fetched_from: Vec<(PathBuf, String)>,
    pub lock_path: PathBuf,
    pub stages: Vec<Stage<'a>>,
    /// blake3 by path, with the size and modification time it was taken at: within one run a stage's outputs are
    /// the next stages' inputs, and re-hashing gigabytes of unchanged files cost seconds each time. Shared (an
    /// `Arc`) so that one command driving several runners (the merge: every partition's, then the whole's) hashes
    /// each file once.
    pub hash_memo: std::sync::Arc<HashMemo>,
}

/// Hashes taken, by path, with what they cost.
#[derive(Default)]
pub struct HashMemo {
    entries: std::sync::Mutex<BTreeMap<PathBuf, (u64, std::time::SystemTime, String)>>,
    /// Keep the entries across `status` / `run` / `adopt` calls ([`HashMemo::for_one_command`]).
    kept: bool,
    files_hashed: std::sync::atomic::AtomicU64,
    bytes_hashed: std::sync::atomic::AtomicU64,
}

/// What a [`HashMemo`] hashed: `files_hashed` counts every file read to hash it and `bytes_hashed` their sizes,
/// `distinct_files` the paths it holds hashes of (equal to `files_hashed` when no file was read twice and none was
/// [`HashMemo::remember`]ed).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct HashStats {
    pub files_hashed: u64,
    pub distinct_files: u64,
    pub bytes_hashed: u64,
}

impl HashMemo {
    /// A memo forgotten at each `status` / `run` / `adopt` call, so that edits between calls on one runner are
    /// always seen (mtime ticks are coarse enough that two writes of equal size can share one).
    pub fn per_call() -> Self {
        Self::default()
    }

    /// A memo kept for the whole of one command, for runners that check the same files in turn while nothing
    /// but the runners themselves writes them (the merge). A file a stage writes is forgotten when the runner
    /// renames it into place, so its next hash is taken from the new bytes.
    pub fn for_one_command() -> Self {
        Self {
            kept: true,
            ..Self::default()
        }
    }

    /// The start of a `status` / `run` / `adopt` call.
    fn begin_call(&self) {
        if !self.kept {
            self.lock().clear();
        }
    }

    fn lock(
        &self,
    ) -> std::sync::MutexGuard<'_, BTreeMap<PathBuf, (u64, std::time::SystemTime, String)>> {
        self.entries.lock().expect("hash memo poisoned")
    }

    /// Drop what is known of `path` (just rewritten).
    fn forget(&self, path: &Path) {
        self.lock().remove(path);
    }

    pub fn hash(&self, path: &Path) -> std::io::Result<String> {
        let meta = std::fs::metadata(path)?;
        let stamp = (meta.len(), meta.modified()?);
        let mut memo = self.lock();
        if let Some((len, modified, hash)) = memo.get(path) {
            if (*len, *modified) == stamp {
                return Ok(hash.clone());
            }
        }
        let hash = hash_file(path)?;
        use std::sync::atomic::Ordering::Relaxed;
        self.files_hashed.fetch_add(1, Relaxed);
        self.bytes_hashed.fetch_add(stamp.0, Relaxed);
        memo.insert(path.to_path_buf(), (stamp.0, stamp.1, hash.clone()));
        Ok(hash)
    }

    /// Record `hash` as `path`'s, taken from the bytes just written there (a download checked on the way), so
    /// the next check does not read the file again.
    pub fn remember(&self, path: &Path, hash: String) -> std::io::Result<()> {
        let meta = std::fs::metadata(path)?;
        self.lock()
            .insert(path.to_path_buf(), (meta.len(), meta.modified()?, hash));
        Ok(())
    }

    /// What was hashed so far. `distinct_files` counts the paths the memo holds, so for a per-call memo it is
    /// the last call's.
    pub fn stats(&self) -> HashStats {
        use std::sync::atomic::Ordering::Relaxed;
        HashStats {
            files_hashed: self.files_hashed.load(Relaxed),
            distinct_files: self.lock().len() as u64,
            bytes_hashed: self.bytes_hashed.load(Relaxed),
        }
    }
}

impl<'a> Runner<'a> {
    fn key(&self, path: &Path) -> String {
        for (dir, url) in &self.fetched_from {
            if let Ok(name) = path.strip_prefix(dir) {
                return format!("{url}/{}", name.display());
            }
        }
        path.strip_prefix(&self.root)
            .unwrap_or(path)
            .display()
            .to_string()
    }

    fn hashes(&self, paths: &[PathBuf]) -> anyhow::Result<BTreeMap<String, String>> {
        paths
            .iter()
            .map(|p| {
                Ok((
                    self.key(p),
                    self.hash_memo
                        .hash(p)
                        .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?,
                ))
            })
            .collect()
    }

    pub fn load_lock(&self) -> anyhow::Result<Lock> {
        if !self.lock_path.exists() {
            return Ok(Lock::default());
        }
        let text = std::fs::read_to_string(&self.lock_path)?;
        serde_json::from_str(&text).map_err(|e| {
            anyhow::anyhow!(
                "{}: unreadable lock ({e}); delete it (or run `g2r-pipeline clean`) to rebuild",
                self.lock_path.display()
            )
        })
    }

    /// Staleness of one stage against the lock, ignoring upstream stages.
    fn own_staleness(&self, stage: &Stage, lock: &Lock) -> anyhow::Result<Staleness> {
        let Some(entry) = lock.stages.get(stage.name) else {
            return Ok(Staleness::NeverRun);
        };
        if entry.code_version != stage.code_version {
            return Ok(Staleness::CodeChanged {
                was: entry.code_version.clone(),
                now: stage.code_version.to_string(),
            });
        }
        if entry.params_blake3 != params_hash(&stage.params) {
            return Ok(Staleness::ParamsChanged);
        }
        for output in &stage.outputs {
            if !output.exists() {
                return Ok(Staleness::OutputMissing(self.key(output)));
            }
        }
        // A declared set that differs from the recorded one (an ortho added or removed) is a change too.
        let declared: Vec<String> = stage.inputs.iter().map(|p| self.key(p)).collect();
        if let Some(gone) = entry.inputs.keys().find(|k| !declared.contains(k)) {
            return Ok(Staleness::InputChanged(format!(
                "{gone} (no longer an input)"
            )));
        }
        for input in &stage.inputs {
            let key = self.key(input);
            if !input.exists() {
                return Ok(Staleness::InputChanged(format!("{key} (missing)")));
            }
            let now = self
                .hash_memo
                .hash(input)
                .map_err(|e| anyhow::anyhow!("{key}: {e}"))?;
            if entry.inputs.get(&key) != Some(&now) {
                return Ok(Staleness::InputChanged(key));
            }
        }
        for output in &stage.outputs {
            let key = self.key(output);
            if entry.outputs.get(&key) != Some(&self.hash_memo.hash(output)?) {
                return Ok(Staleness::OutputChanged(key));
            }
        }
        if let Some(reason) = stage.check.as_ref().and_then(|check| check()) {
            return Ok(Staleness::OutputChanged(reason));
        }
        Ok(Staleness::UpToDate)
    }

    /// Staleness of every stage in order; a stale stage makes every later one stale too.
    pub fn status(&self) -> anyhow::Result<Vec<(&'static str, Staleness)>> {
        self.hash_memo.begin_call();
        let lock = self.load_lock()?;
        let mut out = Vec::new();
        let mut first_stale: Option<&'static str> = None;
        for stage in &self.stages {
            let own = self.own_staleness(stage, &lock)?;
            let status = match (own, first_stale) {
                (Staleness::UpToDate, Some(upstream)) => Staleness::UpstreamStale(upstream),
                (own, _) => own,
            };
            if status != Staleness::UpToDate && first_stale.is_none() {
                first_stale = Some(stage.name);
            }
            out.push((stage.name, status));
        }
        Ok(out)
    }

    /// Run stale stages (and `force`d ones) in order, stopping after `until` if given. Returns the stages run.
    pub fn run(&self, until: Option<&str>, force: &[&str]) -> anyhow::Result<Vec<&'static str>> {
        Ok(self
            .run_timed(until, force)?
            .into_iter()
            .map(|stage| stage.name)
            .collect())
    }

    /// [`Runner::run`], returning each stage run with its wall time and the process's peak memory after it.
    pub fn run_timed(&self, until: Option<&str>, force: &[&str]) -> anyhow::Result<Vec<StageRun>> {
        self.hash_memo.begin_call();
        for name in until.into_iter().chain(force.iter().copied()) {
            if !self.stages.iter().any(|s| s.name == name) {
                let names: Vec<&str> = self.stages.iter().map(|s| s.name).collect();
                anyhow::bail!("unknown stage '{name}': stages are {}", names.join(", "));
            }
        }
        let mut lock = self.load_lock()?;
        let mut ran = Vec::new();
        let mut upstream_ran = false;
        for stage in &self.stages {
            let stale = upstream_ran
                || force.contains(&stage.name)
                || self.own_staleness(stage, &lock)? != Staleness::UpToDate;
            if stale {
                let tmp: Vec<PathBuf> = stage.outputs.iter().map(|p| tmp_path(p)).collect();
                for (path, t) in stage.outputs.iter().zip(&tmp) {
                    if let Some(dir) = path.parent() {
                        std::fs::create_dir_all(dir)?;
                    }
                    let _ = std::fs::remove_file(t);
                }
                tracing::info!(stage = stage.name, "stage started");
                let started = std::time::Instant::now();
                let inputs = self.hashes(&stage.inputs)?;
                (stage.run)(&StageOutputs { paths: tmp.clone() })
                    .map_err(|e| e.context(format!("stage '{}' failed", stage.name)))?;
                for (t, path) in tmp.iter().zip(&stage.outputs) {
                    if !t.exists() {
                        anyhow::bail!("stage '{}' did not write {}", stage.name, path.display());
                    }
                    std::fs::rename(t, path)?;
                    self.hash_memo.forget(path);
                }
                lock.stages.insert(
                    stage.name.to_string(),
                    LockEntry {
                        code_version: stage.code_version.to_string(),
                        params_blake3: params_hash(&stage.params),
                        inputs,
                        outputs: self.hashes(&stage.outputs)?,
                    },
                );
                write_json_atomic(&self.lock_path, &lock)?;
                // Where time goes, per stage (logs and the run record only: no clock reaches a stage output).
                let timed = StageRun {
                    name: stage.name,
                    seconds: started.elapsed().as_secs_f64(),
                    peak_rss_mib: peak_rss_mib(),
                };
                tracing::info!(
                    stage = stage.name,
                    seconds = format!("{:.1}", timed.seconds),
                    peak_rss_mib = timed.peak_rss_mib,
                    "stage done"
                );
                ran.push(timed);
                upstream_ran = true;
            }
            if until == Some(stage.name) {
                break;
            }
        }
        Ok(ran)
    }

    /// Record `names` in the lock as run, from the files their outputs now hold: for outputs produced by other means
    /// than the stage functions (a partitioned build's merge, [`crate::partition`]). The entries are exactly what
    /// running the stages would record when the files hold the same bytes, so later stages and `status` see no
    /// difference.
    pub fn adopt(&self, names: &[&str]) -> anyhow::Result<()> {
        self.hash_memo.begin_call();
        let mut lock = self.load_lock()?;
        for name in names {
            let stage = self
                .stages
                .iter()
                .find(|s| s.name == *name)
                .ok_or_else(|| anyhow::anyhow!("unknown stage '{name}'"))?;
            lock.stages.insert(
                stage.name.to_string(),
                LockEntry {
                    code_version: stage.code_version.to_string(),
                    params_blake3: params_hash(&stage.params),
                    inputs: self.hashes(&stage.inputs)?,
                    outputs: self.hashes(&stage.outputs)?,
                },
            );
        }
        write_json_atomic(&self.lock_path, &lock)
            .map_err(|e| anyhow::anyhow!("{}: {e}", self.lock_path.display()))
    }

    /// Files under `dir` that no stage declares as an output (nor its temporary), with their sizes, sorted: what an
    /// older version's stages wrote and this one no longer does. Nothing reads them, but they can be large.
    pub fn stray_files(&self, dir: &Path) -> anyhow::Result<Vec<(PathBuf, u64)>> {
        let known: std::collections::BTreeSet<PathBuf> = self
            .stages
            .iter()
            .flat_map(|s| s.outputs.iter())
            .flat_map(|p| [p.clone(), tmp_path(p)])
            .collect();
        Ok(files_under(dir)?
            .into_iter()
            .filter(|(path, _)| !known.contains(path))
            .collect())
    }

    /// Remove every declared output, leftover temporaries and the lock.
    pub fn clean(&self) -> anyhow::Result<usize> {
        let mut removed = 0;
        for path in self.stages.iter().flat_map(|s| s.outputs.iter()) {
            for p in [path.clone(), tmp_path(path)] {
                if p.exists() {
                    std::fs::remove_file(&p)?;
                    removed += 1;
                }
            }
        }
        if self.lock_path.exists() {
            std::fs::remove_file(&self.lock_path)?;
        }
        Ok(removed)
    }
}

/// One stage that ran, as `g2r-pipeline run` records it in `run-record.json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StageRun {
    pub name: &'static str,
    pub seconds: f64,
    /// The process's peak resident set after the stage (VmHWM, so at least every earlier stage's), MiB.
    pub peak_rss_mib: Option<u64>,
}

/// The process's peak resident set so far (VmHWM), in MiB; `None` where /proc is not available.
pub fn peak_rss_mib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024)
}

/// Convenience for stage functions: the single output path.
pub fn only(outputs: &StageOutputs) -> &Path {
    &outputs.paths[0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    /// A two-stage toy pipeline: `double` reads numbers from `in.txt`, `sum` adds them up.
    fn pipeline<'a>(
        dir: &Path,
        factor: i64,
        fail_sum: &'a Cell<bool>,
        calls: &'a Cell<u32>,
    ) -> Runner<'a> {
        let (input, doubled, summed) = (
            dir.join("in.txt"),
            dir.join("out/doubled.txt"),
            dir.join("out/sum.txt"),
        );
        let read_numbers = |p: &Path| -> anyhow::Result<Vec<i64>> {
            Ok(std::fs::read_to_string(p)?
                .split_whitespace()
                .map(|v| v.parse().unwrap())
                .collect())
        };
        let (input2, doubled2) = (input.clone(), doubled.clone());
        Runner {
            root: dir.to_path_buf(),
            fetched_from: Vec::new(),
            lock_path: dir.join("pipeline.lock.json"),
            hash_memo: Default::default(),
            stages: vec![
                Stage {
                    name: "double",
                    code_version: "1",
                    inputs: vec![input.clone()],
                    params: serde_json::json!({ "factor": factor }),
                    outputs: vec![doubled.clone()],
                    run: Box::new(move |out| {
                        calls.set(calls.get() + 1);
                        let v: Vec<String> = read_numbers(&input2)?
                            .iter()
                            .map(|x| (x * factor).to_string())
                            .collect();
                        std::fs::write(only(out), v.join(" "))?;
                        Ok(())
                    }),
                    check: None,
                },
                Stage {
                    name: "sum",
                    code_version: "1",
                    inputs: vec![doubled],
                    params: serde_json::json!({}),
                    outputs: vec![summed],
                    run: Box::new(move |out| {
                        calls.set(calls.get() + 1);
                        let total: i64 = read_numbers(&doubled2)?.iter().sum();
                        // Write part of the output, then die: a killed stage.
                        std::fs::write(only(out), format!("{total}"))?;
                        if fail_sum.get() {
                            anyhow::bail!("killed mid-stage");
                        }
                        Ok(())
                    }),
                    check: None,
                },
            ],
        }
    }

    #[test]
    fn only_stale_stages_run_and_status_says_why() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("in.txt"), "1 2 3").unwrap();
        let (fail, calls) = (Cell::new(false), Cell::new(0));
        let runner = pipeline(dir.path(), 2, &fail, &calls);
        assert_eq!(runner.status().unwrap()[0].1, Staleness::NeverRun);
        assert_eq!(runner.run(None, &[]).unwrap(), vec!["double", "sum"]);
        assert_eq!(
            std::fs::read_to_string(dir.path().join("out/sum.txt")).unwrap(),
            "12"
        );
        assert!(runner
            .status()
            .unwrap()
            .iter()
            .all(|(_, s)| *s == Staleness::UpToDate));
        assert!(
            runner.run(None, &[]).unwrap().is_empty(),
            "nothing stale, nothing runs"
        );
        assert_eq!(
            runner.run(None, &["sum"]).unwrap(),
            vec!["sum"],
            "--force reruns one stage"
        );

        // A parameter change makes that stage stale and everything after it.
        let runner = pipeline(dir.path(), 3, &fail, &calls);
        let status = runner.status().unwrap();
        assert_eq!(status[0].1, Staleness::ParamsChanged);
        assert_eq!(status[1].1, Staleness::UpstreamStale("double"));
        assert_eq!(
            runner.run(Some("double"), &[]).unwrap(),
            vec!["double"],
            "--until stops after a stage"
        );
        assert!(matches!(
            runner.status().unwrap()[1].1,
            Staleness::InputChanged(_)
        ));
        runner.run(None, &[]).unwrap();
        assert_eq!(
            std::fs::read_to_string(dir.path().join("out/sum.txt")).unwrap(),
            "18"
        );
        let lock = runner.load_lock().unwrap();
        assert!(
            lock.stages["sum"].outputs.contains_key("out/sum.txt"),
            "lock keys are relative: {lock:?}"
        );

        // An input change and a deleted output are both noticed.
        std::fs::write(dir.path().join("in.txt"), "1 2 4").unwrap();
        assert!(
            matches!(runner.status().unwrap()[0].1, Staleness::InputChanged(ref p) if p.ends_with("in.txt"))
        );
        runner.run(None, &[]).unwrap();
        std::fs::remove_file(dir.path().join("out/sum.txt")).unwrap();
        assert!(matches!(
            runner.status().unwrap()[1].1,
            Staleness::OutputMissing(_)
        ));
        // A middle output deleted: status explains instead of failing on the missing input of the next stage.
        std::fs::remove_file(dir.path().join("out/doubled.txt")).unwrap();
        let st = runner.status().unwrap();
        assert!(
            matches!(st[0].1, Staleness::OutputMissing(_)) && st[1].1 != Staleness::UpToDate,
            "{st:?}"
        );
        runner.run(None, &[]).unwrap();
        // An input no longer declared (an ortho removed from the directory) makes the stage stale.
        let mut fewer = pipeline(dir.path(), 3, &fail, &calls);
        fewer.stages[1].inputs.clear();
        assert!(
            matches!(fewer.status().unwrap()[1].1, Staleness::InputChanged(ref p) if p.contains("no longer an input"))
        );
        let err = runner.run(Some("nope"), &[]).unwrap_err().to_string();
        assert!(
            err.contains("unknown stage 'nope'") && err.contains("double, sum"),
            "{err}"
        );
    }

    #[test]
    fn files_no_stage_declares_are_listed_as_strays() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("in.txt"), "1 2").unwrap();
        let (fail, calls) = (Cell::new(false), Cell::new(0));
        let runner = pipeline(dir.path(), 2, &fail, &calls);
        let out = dir.path().join("out");
        assert!(runner.stray_files(&out).unwrap().is_empty(), "nothing yet");
        runner.run(None, &[]).unwrap();
        assert!(
            runner.stray_files(&out).unwrap().is_empty(),
            "only declared outputs"
        );
        // What an older layout left behind, one level down too; a stage's own temporary is not a stray.
        std::fs::create_dir_all(out.join("old")).unwrap();
        std::fs::write(out.join("old/samples.parquet"), "12345").unwrap();
        std::fs::write(out.join("aaa.txt"), "1").unwrap();
        std::fs::write(tmp_path(&out.join("sum.txt")), "9").unwrap();
        assert_eq!(
            runner.stray_files(&out).unwrap(),
            vec![
                (out.join("aaa.txt"), 1),
                (out.join("old/samples.parquet"), 5)
            ]
        );
    }

    #[test]
    fn a_killed_stage_leaves_nothing_finished_and_rerun_gives_the_same_hashes() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("in.txt"), "5 6").unwrap();
        let (fail, calls) = (Cell::new(false), Cell::new(0));
        let clean_run = pipeline(dir.path(), 2, &fail, &calls);
        clean_run.run(None, &[]).unwrap();
        let reference = clean_run.load_lock().unwrap();
        clean_run.clean().unwrap();
        assert!(
            !dir.path().join("out/sum.txt").exists()
                && !dir.path().join("pipeline.lock.json").exists()
        );

        fail.set(true);
        let runner = pipeline(dir.path(), 2, &fail, &calls);
        assert!(runner
            .run(None, &[])
            .unwrap_err()
            .to_string()
            .contains("stage 'sum' failed"));
        assert!(
            !dir.path().join("out/sum.txt").exists(),
            "no finished-looking output"
        );
        assert!(!runner.load_lock().unwrap().stages.contains_key("sum"));
        assert_eq!(runner.status().unwrap()[1].1, Staleness::NeverRun);
        fail.set(false);
        assert_eq!(
            runner.run(None, &[]).unwrap(),
            vec!["sum"],
            "only the killed stage reruns"
        );
        assert_eq!(
            runner.load_lock().unwrap(),
            reference,
            "same hashes as an uninterrupted run"
        );
    }
}
