//! How a run ends when its loop cannot end it: a module that hangs (the watchdog's callback), a
//! signal no step answers ([`StuckWatch`]), a module that hangs on its way down after the score
//! was written. The loop and an abort claim the end of the run atomically, so an abort never cuts
//! into a run that is finalizing itself, and a finished run never waits on a hung module.

use super::RunLogger;
use crate::score::LogFiles;
use anyhow::{Context, Result};
use parking_lot::Mutex;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU8, AtomicU64, Ordering};

/// The run's loop is going.
const RUNNING: u8 = 0;
/// The loop ended and the run is being finalized: no abort may exit the process now.
const FINALIZING: u8 = 1;
/// The score is written: a hang from now on (the shutdown) exits with the run's own status.
const SCORED: u8 = 2;
/// An abort is finalizing the logs and will exit the process.
const ABORTING: u8 = 3;

/// Who ends the run.
pub(super) struct Ending {
    state: Arc<AtomicU8>,
    code: Arc<AtomicI32>,
}

/// Ends the run from another thread, with the reason.
pub(super) type AbortNow = Arc<dyn Fn(String) + Send + Sync>;

impl Ending {
    pub(super) fn new() -> Self {
        Ending { state: Arc::new(AtomicU8::new(RUNNING)), code: Arc::new(AtomicI32::new(2)) }
    }

    /// The abort: if it is first to claim the run, it finalizes the logs, writes what is known of
    /// the run as `score.json` (`partial(reason, sim_time_s, logs)`) and exits with status 2.
    /// After the score is written it exits with the run's own status and leaves the score as it
    /// is. While the run finalizes itself it does nothing.
    pub(super) fn abort_handler(
        &self,
        logger: Arc<Mutex<Option<RunLogger>>>,
        out: PathBuf,
        core: Arc<framework::system::Core>,
        partial: impl Fn(&str, f64, Option<LogFiles>) -> serde_json::Value + Send + Sync + 'static,
    ) -> AbortNow {
        let (state, code) = (self.state.clone(), self.code.clone());
        Arc::new(move |reason: String| {
            match state.compare_exchange(RUNNING, ABORTING, Ordering::SeqCst, Ordering::SeqCst) {
                Ok(_) => {}
                Err(SCORED) => {
                    let _ = writeln!(std::io::stderr(), "error: {reason} (after the run was scored)");
                    std::process::exit(code.load(Ordering::SeqCst));
                }
                Err(_) => return,
            }
            let _ = writeln!(std::io::stderr(), "error: {reason}");
            let logs = logger.lock().take().and_then(|l| l.finish(None).ok());
            let score = partial(&reason, core.now().as_secs_f64(), logs);
            let _ = std::fs::write(
                out.join("score.json"),
                serde_json::to_string_pretty(&score).unwrap_or_default() + "\n",
            );
            std::process::exit(2);
        })
    }

    /// The score is written; `code` is the run's exit status.
    pub(super) fn scored(&self, code: i32) {
        self.code.store(code, Ordering::SeqCst);
        let _ = self.state.compare_exchange(FINALIZING, SCORED, Ordering::SeqCst, Ordering::SeqCst);
    }
}

/// Ends a run whose simulation is stuck when SIGINT/SIGTERM comes (a module's cycle that never
/// returns and a hang timeout too long to matter, as when a sweep's wall-clock limit stops it):
/// if no step finishes within [`StuckWatch::PATIENCE`] of the signal, the logs are finalized and
/// the process leaves through the abort. Stops watching when dropped (when the run's loops end).
pub(super) struct StuckWatch {
    done: Arc<AtomicBool>,
    state: Arc<AtomicU8>,
}

impl StuckWatch {
    /// How long a signalled run's loop may take to see the signal.
    const PATIENCE: std::time::Duration = std::time::Duration::from_secs(5);

    pub(super) fn start(
        interrupt: Arc<AtomicBool>,
        steps: Arc<AtomicU64>,
        abort_now: AbortNow,
        ending: &Ending,
    ) -> Result<Self> {
        let done = Arc::new(AtomicBool::new(false));
        let d = done.clone();
        let tick = std::time::Duration::from_millis(100);
        std::thread::Builder::new()
            .name("stuck-watch".into())
            .spawn(move || {
                while !d.load(Ordering::SeqCst) && !interrupt.load(Ordering::SeqCst) {
                    std::thread::sleep(tick);
                }
                let at = steps.load(Ordering::SeqCst);
                let mut waited = std::time::Duration::ZERO;
                while !d.load(Ordering::SeqCst) && steps.load(Ordering::SeqCst) == at {
                    if waited >= Self::PATIENCE {
                        // Does nothing if the loop got to finalizing first.
                        abort_now(format!(
                            "interrupted (SIGINT/SIGTERM) while the simulation was stuck: no step finished within {} s",
                            Self::PATIENCE.as_secs()
                        ));
                        return;
                    }
                    std::thread::sleep(tick);
                    waited += tick;
                }
            })
            .context("starting the stuck-run watch")?;
        Ok(Self { done, state: ending.state.clone() })
    }
}

impl Drop for StuckWatch {
    /// The loop is over: from now on the run finalizes itself. If an abort claimed the run first,
    /// it is writing the logs and will exit the process: this thread waits for that.
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
        if self.state.compare_exchange(RUNNING, FINALIZING, Ordering::SeqCst, Ordering::SeqCst).is_err() {
            loop {
                std::thread::park();
            }
        }
    }
}
