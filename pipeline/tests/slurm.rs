//! The pipeline as a Slurm job array, with the scripts users submit (docs/slurm/): a one-node cluster from Debian's
//! packages on 127.0.0.1 runs the demo manifest as a 4-, 2- and 1-task map array plus the publish job, and every
//! published byte equals the single-process build's. A cancelled map task cancels the publish (nothing published), and
//! submitting again resumes to the same bytes; so do a task that exits non-zero and one killed mid-stage.
//!
//! Needs `slurmctld`, `slurmd` and the client commands (`.ci/setup` installs them); the cluster is
//! [`dataset::testing::slurm`]'s, on loopback only.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use dataset::testing::slurm::Cluster;

/// How long one array and its publish job may take.
const JOB_LIMIT: Duration = Duration::from_secs(1800);

/// `docs/slurm/submit.sh MANIFEST N EXTRA…` from `dir`: the map array and publish job ids.
fn submit(
    cluster: &Cluster,
    dir: &Path,
    manifest: &Path,
    partitions: usize,
    extra: &[&str],
) -> (String, String) {
    submit_with(
        cluster,
        dir,
        manifest,
        partitions,
        extra,
        Path::new(env!("CARGO_BIN_EXE_g2r-pipeline")),
    )
}

/// [`submit`] with the jobs running `pipeline` as their g2r-pipeline.
fn submit_with(
    cluster: &Cluster,
    dir: &Path,
    manifest: &Path,
    partitions: usize,
    extra: &[&str],
    pipeline: &Path,
) -> (String, String) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/slurm/submit.sh");
    let out = cluster
        .client("bash")
        .arg(script)
        .arg(manifest)
        .arg(partitions.to_string())
        .args(extra)
        .current_dir(dir)
        .env("G2R_PIPELINE", pipeline)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "submit.sh: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ids = String::from_utf8(out.stdout).unwrap();
    let mut ids = ids.split_whitespace().map(str::to_string);
    (ids.next().unwrap(), ids.next().unwrap())
}

/// A build directory laid out like the repository (`manifests/demo.toml`, `out/demo-world`), so every build's
/// lock keys and published manifest are the same.
fn build_dir(root: &Path, world: &Path, name: &str) -> PathBuf {
    let build = root.join(name);
    std::fs::create_dir_all(build.join("manifests")).unwrap();
    std::fs::create_dir_all(build.join("out")).unwrap();
    std::os::unix::fs::symlink(world, build.join("out/demo-world")).unwrap();
    let manifest = build.join("manifests/demo.toml");
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../manifests/demo.toml"),
        &manifest,
    )
    .unwrap();
    manifest
}

/// Every published file's bytes.
fn published(build: &Path) -> BTreeMap<String, Vec<u8>> {
    let dir = build.join("out/demo-dataset/dataset");
    std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| {
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect()
}

fn assert_same(reference: &BTreeMap<String, Vec<u8>>, build: &Path, what: &str) {
    let got = published(build);
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        reference.keys().collect::<Vec<_>>(),
        "{what}"
    );
    for (name, bytes) in reference {
        assert!(
            bytes == &got[name],
            "{what}: {name} differs from the single-process build"
        );
    }
}

/// Wait for a map array and its publish job; the publish job completed and published the single-process bytes.
fn assert_published(
    cluster: &Cluster,
    map: &str,
    publish: &str,
    reference: &BTreeMap<String, Vec<u8>>,
    build: &Path,
    what: &str,
) {
    cluster.wait(&[map, publish], JOB_LIMIT);
    let state = cluster.state(publish);
    assert!(state.starts_with("JobState=COMPLETED"), "{what}: {state}");
    assert_same(reference, build, what);
}

/// Wait for a map array and its publish job; a failed map task cancelled the publish job (not left pending).
fn assert_publish_cancelled(cluster: &Cluster, map: &str, publish: &str) {
    cluster.wait(&[map, publish], JOB_LIMIT);
    let state = cluster.state(publish);
    assert!(
        state.contains("JobState=CANCELLED") && state.contains("DependencyNeverSatisfied"),
        "{state}"
    );
}

#[test]
fn a_slurm_array_publishes_the_same_bytes_and_a_failed_task_publishes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let preset = pipeline::synth::config::preset("demo").unwrap();
    let world = pipeline::synth::generate(
        &pipeline::synth::WorldConfig::from_toml(preset).unwrap(),
        42,
        &root.join("demo-world"),
        false,
    )
    .unwrap();

    let single = build_dir(root, &world, "single");
    let status = Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(&single)
        .status()
        .unwrap();
    assert!(status.success());
    let reference = published(&root.join("single"));
    assert!(reference.contains_key("manifest.json"));

    let cluster = Cluster::start(&root.join("slurm"));
    // Four, two and one partitions, two tasks at a time on the node's two CPUs.
    for partitions in [4, 2, 1] {
        let name = format!("array-{partitions}");
        let manifest = build_dir(root, &world, &name);
        let (map, publish) = submit(
            &cluster,
            &root.join(&name),
            &manifest,
            partitions,
            &["--cpus-per-task=1"],
        );
        assert_published(
            &cluster,
            &map,
            &publish,
            &reference,
            &root.join(&name),
            &format!("{partitions}-task array"),
        );
    }

    // One map task cancelled before it ran: the publish job is cancelled (not left pending) and nothing is
    // published; submitting again finishes that partition only and publishes the same bytes.
    let manifest = build_dir(root, &world, "cancelled");
    let dir = root.join("cancelled");
    let (map, publish) = submit(
        &cluster,
        &dir,
        &manifest,
        4,
        &["--cpus-per-task=1", "--", "--hold"],
    );
    cluster.command("scancel", &[&format!("{map}_3")]);
    cluster.command("scontrol", &["release", &map]);
    assert_publish_cancelled(&cluster, &map, &publish);
    assert!(
        !dir.join("out/demo-dataset/dataset/manifest.json").exists(),
        "nothing published"
    );
    assert!(dir
        .join("out/demo-dataset/partitions/4/2/pipeline.lock.json")
        .exists());
    assert!(
        !dir.join("out/demo-dataset/partitions/4/3").exists(),
        "task 3 never ran"
    );
    let (map, publish) = submit(&cluster, &dir, &manifest, 4, &["--cpus-per-task=1"]);
    assert_published(
        &cluster,
        &map,
        &publish,
        &reference,
        &dir,
        "resubmitted after a cancelled task",
    );

    // Tasks that fail while running: task 1 exits non-zero, task 2 is killed mid-stage. The publish job never
    // runs, nothing is published, and submitting again publishes the same bytes.
    let manifest = build_dir(root, &world, "failing");
    let dir = root.join("failing");
    let wrapper = dir.join("task-1-fails.sh");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/bash\nif [ \"$SLURM_ARRAY_TASK_ID\" = 1 ]; then echo 'task 1 fails (injected)' >&2; exit 3; fi\n\
             exec {} \"$@\"\n",
            env!("CARGO_BIN_EXE_g2r-pipeline")
        ),
    )
    .unwrap();
    std::fs::set_permissions(
        &wrapper,
        std::os::unix::fs::PermissionsExt::from_mode(0o755),
    )
    .unwrap();
    let (map, publish) = submit_with(
        &cluster,
        &dir,
        &manifest,
        4,
        &["--cpus-per-task=1"],
        &wrapper,
    );
    let task2 = format!("{map}_2");
    let partition2 = dir.join("out/demo-dataset/partitions/4/2");
    let started = std::time::Instant::now();
    while !(cluster.state(&task2).starts_with("JobState=RUNNING") && partition2.exists()) {
        assert!(
            started.elapsed() < JOB_LIMIT,
            "task 2 never ran: {}",
            cluster.state(&task2)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // Mid-stage: a second into its work.
    std::thread::sleep(Duration::from_secs(1));
    cluster.command("scancel", &["--signal=KILL", "--full", &task2]);
    assert_publish_cancelled(&cluster, &map, &publish);
    let task1 = cluster.state(&format!("{map}_1"));
    assert!(task1.contains("JobState=FAILED"), "task 1: {task1}");
    let task2_state = cluster.state(&task2);
    assert!(
        !task2_state.contains("JobState=COMPLETED"),
        "task 2 was not killed mid-stage: {task2_state}"
    );
    assert!(
        !dir.join("out/demo-dataset/dataset").exists(),
        "something was published after failed tasks"
    );
    let (map, publish) = submit(&cluster, &dir, &manifest, 4, &["--cpus-per-task=1"]);
    assert_published(
        &cluster,
        &map,
        &publish,
        &reference,
        &dir,
        "resubmitted after a failed and a killed task",
    );
}
