//! The overall finite state machine of the system and of each module (seed 000, section 7, Fig. 2).
//!
//! `Startup -> Config -> Standby -> Hold -> Run -> Shutdown`, with `Safe` the off-nominal state
//! reachable from any state on failure and left only by command, to `Standby` (after analysis and
//! re-configuration) or to `Shutdown`. [`Lifecycle::check_transition`] is the single place that says
//! which moves are legal; everything else asks it.

use serde::{Deserialize, Serialize};
use std::fmt;

/// A lifecycle state.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Lifecycle {
    /// Framework tasks start; local and remote modules register.
    Startup,
    /// Modules can be configured: files loaded, reloaded and saved, parameters and meta-states set,
    /// execution contexts chosen.
    Config,
    /// Waiting for a command to start (to Hold) or to shut down; devices may be switched on or off.
    Standby,
    /// Execution state, idle, with sensors and actuators on.
    Hold,
    /// The module executes its mission function.
    Run,
    /// The shutdown procedure ran; terminal.
    Shutdown,
    /// Off-nominal state after a failure; left only by command.
    Safe,
}

/// Why a lifecycle transition was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("illegal transition {from} -> {to}: {reason}")]
pub struct TransitionError {
    /// The state the transition started from.
    pub from: Lifecycle,
    /// The requested state.
    pub to: Lifecycle,
    /// Why it is refused.
    pub reason: String,
}

impl Lifecycle {
    /// All states, in nominal order.
    pub const ALL: [Lifecycle; 7] = [
        Lifecycle::Startup,
        Lifecycle::Config,
        Lifecycle::Standby,
        Lifecycle::Hold,
        Lifecycle::Run,
        Lifecycle::Shutdown,
        Lifecycle::Safe,
    ];

    /// Checks whether a commanded move from `self` to `to` is legal.
    pub fn check_transition(self, to: Lifecycle) -> Result<(), TransitionError> {
        use Lifecycle::*;
        let refuse = |reason: &str| Err(TransitionError { from: self, to, reason: reason.to_string() });
        match (self, to) {
            (a, b) if a == b => refuse("already in that state"),
            (Shutdown, _) => refuse("Shutdown is terminal"),
            (_, Safe) => Ok(()),
            (Startup, Config) => Ok(()),
            (Startup, _) => refuse("from Startup the only way is Config, once registration is complete"),
            (Config, Standby) => Ok(()),
            (Standby, Config | Hold | Shutdown) => Ok(()),
            (Hold, Run | Standby) => Ok(()),
            (Run, Hold) => Ok(()),
            (Safe, Standby | Shutdown) => Ok(()),
            (Safe, _) => refuse("Safe is left only by command, to Standby or Shutdown"),
            (_, Startup) => refuse("Startup is entered only once, when the framework starts"),
            (Run, _) => refuse("from Run the only way is Hold (or Safe)"),
            (Hold, _) => refuse("from Hold the ways are Run or Standby (or Safe)"),
            (Config, _) => refuse("from Config the way is Standby (or Safe)"),
            (Standby, _) => refuse("from Standby the ways are Config, Hold or Shutdown (or Safe)"),
        }
    }

    /// The legal path from `self` to `to` through nominal states (shortest), if any, excluding `self`.
    /// Used to walk the whole system to a state, e.g. `Run -> Hold -> Standby -> Shutdown`.
    pub fn path_to(self, to: Lifecycle) -> Option<Vec<Lifecycle>> {
        let mut frontier = vec![(self, Vec::new())];
        let mut seen = vec![self];
        while !frontier.is_empty() {
            let mut next = Vec::new();
            for (s, path) in frontier {
                if s == to {
                    return Some(path);
                }
                for n in Lifecycle::ALL {
                    // Safe is never a waypoint of a nominal path.
                    if (n != Lifecycle::Safe || to == Lifecycle::Safe)
                        && !seen.contains(&n)
                        && s.check_transition(n).is_ok()
                    {
                        seen.push(n);
                        let mut p = path.clone();
                        p.push(n);
                        next.push((n, p));
                    }
                }
            }
            frontier = next;
        }
        None
    }

    /// Parses a state name, case-insensitively.
    pub fn parse(s: &str) -> Option<Lifecycle> {
        Lifecycle::ALL.into_iter().find(|l| l.name().eq_ignore_ascii_case(s))
    }

    /// The state's name.
    pub fn name(self) -> &'static str {
        match self {
            Lifecycle::Startup => "Startup",
            Lifecycle::Config => "Config",
            Lifecycle::Standby => "Standby",
            Lifecycle::Hold => "Hold",
            Lifecycle::Run => "Run",
            Lifecycle::Shutdown => "Shutdown",
            Lifecycle::Safe => "Safe",
        }
    }
}

impl fmt::Display for Lifecycle {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::Lifecycle::*;
    use super::*;

    #[test]
    fn nominal_chain_is_legal() {
        for w in [Startup, Config, Standby, Hold, Run].windows(2) {
            w[0].check_transition(w[1]).unwrap();
        }
        Run.check_transition(Hold).unwrap();
        Hold.check_transition(Standby).unwrap();
        Standby.check_transition(Shutdown).unwrap();
    }

    #[test]
    fn safe_reachable_from_anywhere_but_left_only_to_standby_or_shutdown() {
        for s in [Startup, Config, Standby, Hold, Run] {
            s.check_transition(Safe).unwrap();
        }
        Safe.check_transition(Standby).unwrap();
        Safe.check_transition(Shutdown).unwrap();
        for s in [Startup, Config, Hold, Run] {
            let e = Safe.check_transition(s).unwrap_err();
            assert!(e.reason.contains("left only by command"), "{e}");
        }
    }

    #[test]
    fn illegal_transitions_have_reasons() {
        let e = Standby.check_transition(Run).unwrap_err();
        assert_eq!((e.from, e.to), (Standby, Run));
        assert!(e.to_string().contains("Standby -> Run"));
        assert!(Shutdown.check_transition(Standby).is_err());
        assert!(Run.check_transition(Shutdown).is_err());
        assert!(Run.check_transition(Run).is_err());
        assert!(Config.check_transition(Startup).is_err());
    }

    #[test]
    fn paths_walk_nominal_states() {
        assert_eq!(Run.path_to(Shutdown).unwrap(), vec![Hold, Standby, Shutdown]);
        assert_eq!(Config.path_to(Run).unwrap(), vec![Standby, Hold, Run]);
        assert_eq!(Safe.path_to(Run).unwrap(), vec![Standby, Hold, Run]);
        assert!(Shutdown.path_to(Run).is_none());
        assert_eq!(Lifecycle::parse("run"), Some(Run));
    }
}
