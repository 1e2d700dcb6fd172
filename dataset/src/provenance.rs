//! Where and when a measurement was taken, written next to it (`provenance.json` of `eval`, `report`,
//! `model-choice` and `compare-evals --out`, the `provenance` of `bench`'s record, `run-record.json` of
//! `g2r-pipeline run`), so a figure quoted later carries its command, commit, machine and date from the record
//! rather than from memory. Kept out of the measured outputs themselves (`metrics.json`, the dataset), which stay
//! byte-identical from run to run.

use hifitime::Epoch;

/// The command, checkout, machine and time of one run.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Provenance {
    /// The command line as the process received it.
    pub command: String,
    /// `git describe --always --dirty` of the working directory's checkout when the command ran; `None` outside
    /// a git checkout. It names the source the binary was built from only when it was built from that checkout.
    pub checkout: Option<String>,
    /// The CPU's model name (`/proc/cpuinfo`); `None` where it is not available.
    pub cpu: Option<String>,
    /// Threads the process could run at once.
    pub logical_cores: usize,
    /// When the record was taken, UTC, ISO 8601.
    pub date_utc: String,
}

impl Provenance {
    /// This process's provenance, now.
    pub fn capture() -> Self {
        let command = std::env::args().collect::<Vec<_>>().join(" ");
        let checkout = std::process::Command::new("git")
            .args(["describe", "--always", "--dirty"])
            .output()
            .ok()
            .filter(|out| out.status.success())
            .and_then(|out| String::from_utf8(out.stdout).ok())
            .map(|text| text.trim().to_string());
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|text| {
                text.lines()
                    .find_map(|line| line.strip_prefix("model name")?.split_once(':'))
                    .map(|(_, name)| name.trim().to_string())
            });
        let logical_cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let date_utc = Epoch::now().map_or_else(
            |_| "unknown".to_string(),
            |now| {
                let (y, mo, d, h, mi, s, _) = now.to_gregorian_utc();
                format!("{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}Z")
            },
        );
        Self {
            command,
            checkout,
            cpu,
            logical_cores,
            date_utc,
        }
    }

    /// Write it as `path` (JSON, atomically).
    pub fn write(&self, path: &std::path::Path) -> anyhow::Result<()> {
        Ok(crate::files::write_json_atomic(path, self)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_capture_names_this_process_and_a_parseable_time() {
        let p = Provenance::capture();
        let program = std::env::args().next().unwrap();
        assert!(p.command.starts_with(&program), "{}", p.command);
        assert!(p.logical_cores >= 1);
        let parsed = crate::contract::acquisition::j2000_seconds_from_iso_utc(&p.date_utc).unwrap();
        // After 2026-01-01 (this code's first year).
        assert!(parsed > 820_454_400.0, "{}", p.date_utc);
    }
}
