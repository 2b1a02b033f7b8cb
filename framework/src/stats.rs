//! Per-module task statistics (seed 004, "Periodic_Thread ... recording execution statistics").

use crate::time::Duration;
use serde::{Deserialize, Serialize};

/// Execution statistics of one module, kept by both executors.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TaskStats {
    /// State-function cycles executed.
    pub cycles: u64,
    /// Cycles whose execution time exceeded the deadline.
    pub overruns: u64,
    /// Cycles skipped because the module was late by a whole period or more (real-time executor).
    pub skipped: u64,
    /// Messages handled (commands and acknowledgements).
    pub messages: u64,
    /// Shortest cycle execution time (wall clock), ns.
    pub exec_min_ns: i64,
    /// Longest cycle execution time (wall clock), ns.
    pub exec_max_ns: i64,
    /// Total cycle execution time (wall clock), ns.
    pub exec_total_ns: i64,
    /// Total execution time the module declared it would take on its target (simulated), ns.
    pub charged_total_ns: i64,
}

impl TaskStats {
    /// Records one cycle's execution time.
    pub fn record_cycle(&mut self, exec: Duration) {
        let ns = exec.as_nanos();
        if self.cycles == 0 || ns < self.exec_min_ns {
            self.exec_min_ns = ns;
        }
        self.exec_max_ns = self.exec_max_ns.max(ns);
        self.exec_total_ns += ns;
        self.cycles += 1;
    }
    /// Mean cycle execution time.
    pub fn exec_mean(&self) -> Duration {
        if self.cycles == 0 {
            Duration::ZERO
        } else {
            // Checked: statistics may come from another host.
            Duration::from_nanos(
                self.exec_total_ns.checked_div(self.cycles.min(i64::MAX as u64) as i64).unwrap_or(0),
            )
        }
    }
    /// Shortest cycle execution time.
    pub fn exec_min(&self) -> Duration {
        Duration::from_nanos(self.exec_min_ns)
    }
    /// Longest cycle execution time.
    pub fn exec_max(&self) -> Duration {
        Duration::from_nanos(self.exec_max_ns)
    }
}
