//! Execution contexts (seed 000, 6.5): Dry-Run or Operative x Debug or Mission, per module.
//!
//! Dry-Run runs a module against simulated devices (the twin); Operative against real ones. In Debug
//! the module's debug queue is active and debug commands (e.g. failure injection) are accepted; in
//! Mission they are refused back to their sender.

use serde::{Deserialize, Serialize};
use std::fmt;

/// Where a module's devices are: simulated or real.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// Devices are simulated (the twin, or recorded data).
    DryRun,
    /// Devices are the real hardware.
    Operative,
}

/// Whether debug procedures are enabled.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Purpose {
    /// Debug queue active, debug commands accepted.
    Debug,
    /// Nominal: the debug queue is inactive.
    Mission,
}

/// A module's execution context.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExecContext {
    /// Dry-Run or Operative.
    pub mode: Mode,
    /// Debug or Mission.
    pub purpose: Purpose,
}

impl ExecContext {
    /// Dry-Run, Mission: the simulator's nominal context.
    pub const DRY_RUN_MISSION: ExecContext = ExecContext { mode: Mode::DryRun, purpose: Purpose::Mission };
    /// Dry-Run, Debug.
    pub const DRY_RUN_DEBUG: ExecContext = ExecContext { mode: Mode::DryRun, purpose: Purpose::Debug };
    /// Operative, Mission: the nominal context on the robot.
    pub const OPERATIVE_MISSION: ExecContext =
        ExecContext { mode: Mode::Operative, purpose: Purpose::Mission };
    /// Operative, Debug.
    pub const OPERATIVE_DEBUG: ExecContext = ExecContext { mode: Mode::Operative, purpose: Purpose::Debug };

    /// True when the debug queue is active.
    pub fn debug_queue_active(self) -> bool {
        self.purpose == Purpose::Debug
    }
}

impl Default for ExecContext {
    fn default() -> Self {
        ExecContext::DRY_RUN_MISSION
    }
}

impl fmt::Display for ExecContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let m = match self.mode {
            Mode::DryRun => "Dry-Run",
            Mode::Operative => "Operative",
        };
        let p = match self.purpose {
            Purpose::Debug => "Debug",
            Purpose::Mission => "Mission",
        };
        write!(f, "{m}/{p}")
    }
}
