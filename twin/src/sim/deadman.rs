//! The actuator drivers' deadman: wheels commanded through the HAL stop, and joint groups commanded
//! through it hold where they are, when the software that commands them falls silent for longer
//! than the configured time (`[locomotor] deadman_s`, `[servos] deadman_s`). A module that panics
//! or hangs mid-drive therefore leaves the rover stopped, whatever it commanded last.
//!
//! Only commands that come through the HAL devices arm it ([`Twin::command_wheels`],
//! [`Twin::keep_group_alive`]); the twin's own API (tests, the scripted operator) drives without one.

use super::*;
use serde::{Deserialize, Serialize};

/// A deadman that fired: which device, when, and after how long without a command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeadmanTrip {
    /// Simulated time, s.
    pub t_s: f64,
    /// The device: `locomotor` or a joint group.
    pub device: String,
    /// Time since its last command, s.
    pub silent_s: f64,
}

impl Twin {
    /// Commands wheel rates as the locomotor driver does: like [`Twin::set_wheel_rates`], and arms
    /// the deadman, which stops the wheels when no command follows within `locomotor.deadman_s`.
    pub fn command_wheels(&mut self, rates: &[f64]) {
        self.set_wheel_rates(rates);
        self.wheel_cmd_at = Some(self.time);
    }

    /// Notes that the software commanding joint group `group` is alive (every command through its
    /// driver, and its keep-alives): the group's deadman counts from here.
    pub fn keep_group_alive(&mut self, group: &str) {
        self.group_alive_at.insert(group.to_string(), self.time);
    }

    /// The deadmen that fired so far.
    pub fn deadman_trips(&self) -> &[DeadmanTrip] {
        &self.deadman_trips
    }

    /// Fires the deadmen whose time has passed (called every physics step).
    pub(super) fn update_deadman(&mut self) {
        let now = self.time;
        let wheels = self.config.locomotor.deadman_s;
        if let Some(at) = self.wheel_cmd_at
            && wheels > 0.0
            && (now - at).as_secs_f64() > wheels
        {
            self.wheel_cmd_at = None;
            if self.wheel_cmd.iter().any(|&r| r != 0.0) {
                self.wheel_cmd.iter_mut().for_each(|r| *r = 0.0);
                self.trip(crate::devices::LOCOMOTOR, at);
            }
        }
        let joints = self.config.servos.deadman_s;
        if joints <= 0.0 {
            return;
        }
        let silent: Vec<(String, Time)> = self
            .group_alive_at
            .iter()
            .filter(|(_, at)| (now - **at).as_secs_f64() > joints)
            .map(|(g, at)| (g.clone(), *at))
            .collect();
        for (group, at) in silent {
            self.group_alive_at.remove(&group);
            let moving = self.moves.values().any(|m| m.group == group && m.state == MoveState::Active);
            if moving && self.stop_group(&group).is_ok() {
                self.trip(&group, at);
            }
        }
    }

    fn trip(&mut self, device: &str, last: Time) {
        let silent_s = (self.time - last).as_secs_f64();
        tracing::warn!(device, silent_s, "deadman: no command from the software, actuator stopped");
        self.deadman_trips.push(DeadmanTrip {
            t_s: self.time.as_secs_f64(),
            device: device.to_string(),
            silent_s,
        });
    }
}
