//! Progress of long work, the one helper every command uses: on a terminal an `indicatif` bar with count, rate and
//! ETA; anywhere else (a Slurm log, CI, `| tee`) a structured log line every [`log_every`] with the same figures,
//! so a slow run can be told from a hung one. Both go to stderr, never stdout: reports piped to a file stay clean.
//!
//! Work that takes less than one interval off a terminal logs nothing, so short runs and tests stay quiet.

use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// The interval between log lines off a terminal when `G2R_PROGRESS_SECONDS` is not set.
pub const DEFAULT_LOG_EVERY: Duration = Duration::from_secs(30);

/// The variable that sets the interval between log lines off a terminal, in seconds (e.g. `0.5`).
pub const LOG_EVERY_VAR: &str = "G2R_PROGRESS_SECONDS";

/// The interval between log lines off a terminal: `G2R_PROGRESS_SECONDS`, or [`DEFAULT_LOG_EVERY`] when it is
/// unset or not a positive number of seconds.
pub fn log_every() -> Duration {
    std::env::var(LOG_EVERY_VAR)
        .ok()
        .and_then(|text| text.trim().parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s > 0.0)
        .map_or(DEFAULT_LOG_EVERY, Duration::from_secs_f64)
}

/// Where progress goes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Output {
    /// A bar redrawn on stderr.
    Bar,
    /// A structured log line (`tracing`, info) at this interval, and one when the work ends.
    Log(Duration),
    /// Nowhere (library calls from tests, ranks other than the lead).
    Hidden,
}

impl Output {
    /// A bar when stderr is a terminal, log lines at [`log_every`] otherwise.
    pub fn detect() -> Self {
        if std::io::stderr().is_terminal() {
            Self::Bar
        } else {
            Self::Log(log_every())
        }
    }
}

/// One piece of long work: `task` counting `unit`s towards a total. [`Progress::finish`] ends the report as
/// finished; dropped without it (an error, a stop), it ends as stopped where it was.
pub struct Progress {
    bar: ProgressBar,
    logger: Option<Logger>,
    /// The count the work resumed from: rates and ETAs count only what this run did.
    resumed_from: Arc<AtomicU64>,
    finished: bool,
}

impl Progress {
    /// Progress of `task` over `total` `unit`s (0 while unknown: [`Progress::set_length`]), shown as
    /// [`Output::detect`] says.
    pub fn start(task: &str, unit: &str, total: u64) -> Self {
        Self::with_output(task, unit, total, Output::detect())
    }

    /// Progress that shows nothing, for callers that report their own way.
    pub fn hidden() -> Self {
        Self::with_output("", "", 0, Output::Hidden)
    }

    /// Progress shown as `output` says.
    pub fn with_output(task: &str, unit: &str, total: u64, output: Output) -> Self {
        Self::build(task, unit, total, output, "")
    }

    /// [`Progress::start`] with `context` (e.g. `rank=0 world=2`) in every log line and before the bar.
    pub fn start_in(task: &str, unit: &str, total: u64, context: &str) -> Self {
        Self::build(task, unit, total, Output::detect(), context)
    }

    fn build(task: &str, unit: &str, total: u64, output: Output, context: &str) -> Self {
        let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::hidden());
        let resumed_from = Arc::new(AtomicU64::new(0));
        let logger = match output {
            Output::Bar => {
                let label = if context.is_empty() {
                    task.to_string()
                } else {
                    format!("{task} {context}")
                };
                bar.set_style(
                    ProgressStyle::with_template(&format!(
                        "{{prefix}} [{{bar:30}}] {{pos}}/{{len}} {unit} {{per_sec}} eta {{eta}} {{msg}}"
                    ))
                    .expect("a valid template")
                    .progress_chars("=> "),
                );
                bar.set_prefix(label);
                bar.set_draw_target(ProgressDrawTarget::stderr());
                None
            }
            Output::Log(every) => Some(Logger::start(
                bar.clone(),
                resumed_from.clone(),
                LogLabels {
                    task: task.to_string(),
                    unit: unit.to_string(),
                    context: context.to_string(),
                },
                every,
            )),
            Output::Hidden => None,
        };
        Self {
            bar,
            logger,
            resumed_from,
            finished: false,
        }
    }

    /// The bar itself, for code that takes an `indicatif::ProgressBar`: its count is this progress's count.
    pub fn bar(&self) -> &ProgressBar {
        &self.bar
    }

    pub fn inc(&self, delta: u64) {
        self.bar.inc(delta);
    }

    pub fn set_position(&self, position: u64) {
        self.bar.set_position(position);
    }

    /// Start the count at `position`, work done before this run (a resumed fit): the rate and the ETA count only
    /// what is done from here.
    pub fn resume_at(&self, position: u64) {
        self.bar.set_position(position);
        self.bar.reset_eta();
        self.resumed_from.store(position, Ordering::Relaxed);
    }

    pub fn set_length(&self, total: u64) {
        self.bar.set_length(total);
    }

    pub fn inc_length(&self, delta: u64) {
        self.bar.inc_length(delta);
    }

    /// A short note shown after the figures (e.g. the current loss or file).
    pub fn set_message(&self, message: impl Into<std::borrow::Cow<'static, str>>) {
        self.bar.set_message(message);
    }

    /// End the report as finished: the bar is cleared; off a terminal a last `finished` line is logged if any
    /// line was.
    pub fn finish(mut self) {
        self.finished = true;
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if let Some(logger) = self.logger.take() {
            logger.stop(self.finished);
        }
        if self.finished {
            self.bar.finish_and_clear();
        } else {
            // Left where it stopped, with its message (a stopped fit says how to resume).
            self.bar.abandon();
        }
    }
}

struct LogLabels {
    task: String,
    unit: String,
    context: String,
}

/// The thread that writes the log lines: one every interval, and a last one at the end if it wrote any.
struct Logger {
    /// Set once the work ends: whether it finished.
    stop: Arc<(Mutex<Option<bool>>, Condvar)>,
    thread: Option<JoinHandle<()>>,
}

impl Logger {
    fn start(
        bar: ProgressBar,
        resumed_from: Arc<AtomicU64>,
        labels: LogLabels,
        every: Duration,
    ) -> Self {
        let stop = Arc::new((Mutex::new(None), Condvar::new()));
        let thread = {
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("progress-log".into())
                .spawn(move || {
                    let started = Instant::now();
                    let mut logged = false;
                    let (lock, wake) = &*stop;
                    let mut ended = lock.lock().unwrap_or_else(PoisonError::into_inner);
                    loop {
                        let (guard, _) = wake
                            .wait_timeout_while(ended, every, |ended| ended.is_none())
                            .unwrap_or_else(PoisonError::into_inner);
                        ended = guard;
                        let from = resumed_from.load(Ordering::Relaxed);
                        if let Some(finished) = *ended {
                            if logged {
                                let end = if finished { "finished" } else { "stopped" };
                                log_line(&bar, from, &labels, started.elapsed(), end);
                            }
                            return;
                        }
                        log_line(&bar, from, &labels, started.elapsed(), "progress");
                        logged = true;
                    }
                })
                .expect("a thread for progress lines")
        };
        Self {
            stop,
            thread: Some(thread),
        }
    }

    /// End the thread, its last line saying whether the work `finished` or stopped short.
    fn stop(mut self, finished: bool) {
        *self.stop.0.lock().unwrap_or_else(PoisonError::into_inner) = Some(finished);
        self.stop.1.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// `progress task=eval done=120 total=5337 unit=crops rate_per_s=3.21 eta_s=1624 elapsed_s=37`.
/// `what` is `progress`, or `finished` / `stopped` for the last line; the rate counts from `resumed_from`.
fn log_line(
    bar: &ProgressBar,
    resumed_from: u64,
    labels: &LogLabels,
    elapsed: Duration,
    what: &str,
) {
    let done = bar.position();
    let total = bar.length().unwrap_or(0);
    let elapsed_s = elapsed.as_secs_f64();
    let rate = done.saturating_sub(resumed_from) as f64 / elapsed_s.max(f64::MIN_POSITIVE);
    let eta_s =
        (rate > 0.0 && total >= done).then(|| ((total - done) as f64 / rate).round() as u64);
    let message = bar.message();
    tracing::info!(
        task = labels.task.as_str(),
        context = (!labels.context.is_empty()).then_some(labels.context.as_str()),
        done,
        total,
        unit = labels.unit.as_str(),
        rate_per_s = format!("{rate:.3}"),
        eta_s,
        elapsed_s = elapsed_s.round() as u64,
        note = message.as_str(),
        "{what}"
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_interval_comes_from_the_environment_or_the_default() {
        // One test touches the variable, so no other test races it.
        std::env::set_var(LOG_EVERY_VAR, "0.25");
        assert_eq!(log_every(), Duration::from_millis(250));
        for bad in ["0", "-3", "soon", "NaN"] {
            std::env::set_var(LOG_EVERY_VAR, bad);
            assert_eq!(log_every(), DEFAULT_LOG_EVERY, "{bad}");
        }
        std::env::remove_var(LOG_EVERY_VAR);
        assert_eq!(log_every(), DEFAULT_LOG_EVERY);
    }

    #[test]
    fn the_bar_counts_what_the_work_adds_whatever_the_output() {
        for output in [Output::Hidden, Output::Log(Duration::from_millis(5))] {
            let progress = Progress::with_output("t", "items", 10, output);
            progress.inc(3);
            progress.bar().inc(2);
            progress.inc_length(5);
            assert_eq!(progress.bar().position(), 5);
            assert_eq!(progress.bar().length(), Some(15));
            std::thread::sleep(Duration::from_millis(20));
            progress.finish(); // joins the log thread: a hang here fails the test by timeout
        }
    }
}
