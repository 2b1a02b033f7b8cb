//! # framework: the Robot Management Framework of the rover digital twin
//!
//! After the TAS-I Robot Management Framework (seed 000) and the lessons of a reusable rover
//! framework (seed 004). Every other crate of the workbench builds on this one; it depends on none of
//! them.
//!
//! | idea (paper) | here |
//! |---|---|
//! | KAL: clocks, tasks | [`time`], [`clock`], [`executor`] |
//! | WorkFrame core: system manager, scheduler, watchdog | [`system`], [`executor`] |
//! | BlackBoard System, Data Interface | [`blackboard`], [`data`] |
//! | Messages Passing System | [`message`] |
//! | Module base: FSM, meta-states, commands, scheduling | [`module`] |
//! | Modules configuration, execution context | [`config`], [`exec_context`] |
//! | Overall FSM (Startup ... Safe) | [`lifecycle`] |
//! | Shared resources, reservation tokens | [`resources`] |
//! | Estimates with uncertainty | [`estimate`] |
//! | Object database: marker tables (seed 000, 8.4) | [`objects`] |
//! | Debug / framework console | [`console`] |
//!
//! Time is integer nanoseconds from the executor's clock; modules never read the OS clock. Runs
//! under the [`executor::LockstepExecutor`] are deterministic.

pub mod angle;
pub mod blackboard;
pub mod camera;
pub mod clock;
pub mod config;
pub mod console;
pub mod data;
pub mod debugger;
pub mod estimate;
pub mod events;
pub mod exec_context;
pub mod executor;
pub mod hal;
pub mod lifecycle;
pub mod mechanism;
pub mod message;
pub mod module;
pub mod objects;
pub mod remote;
pub mod resources;
pub mod runtime;
pub mod seed;
pub mod stats;
pub mod system;
pub mod time;

pub use blackboard::{BlackBoard, Reader, Stamped, Writer};
pub use config::{ConfigError, ConfigSource, NoParams};
pub use estimate::{Estimate, GaussianEstimate};
pub use exec_context::{ExecContext, Mode, Purpose};
pub use executor::{Executor, LockstepExecutor, RealtimeExecutor};
pub use lifecycle::Lifecycle;
pub use message::{Ack, AckStatus, Command, MessageId, Outcome, Queue};
pub use module::{Ctx, Declare, Module, ModuleError, ModuleKind, StateResult};
pub use system::{Endpoint, StartupError, SystemBuilder, SystemError};
pub use time::{Duration, Time};

/// Everything a module author needs, in one import.
pub mod prelude {
    pub use crate::blackboard::{Reader, Stamped, Writer};
    pub use crate::config::NoParams;
    pub use crate::exec_context::ExecContext;
    pub use crate::lifecycle::Lifecycle;
    pub use crate::message::{Command, Outcome, Queue};
    pub use crate::module::{Ctx, Declare, Module, ModuleError, ModuleKind, StateResult};
    pub use crate::time::{Duration, Time};
}
