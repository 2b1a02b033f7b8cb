//! Clocks and timers (seed 000 KAL; seed 004 "Use abstract clocks and timers").
//!
//! Modules never read the operating system's clock: they get [`Time`] from their context, which reads
//! the executor's [`Clock`]. Under the lockstep executor that is a [`SimClock`], advanced only by the
//! holder of its [`ClockDriver`] (the executor), so a mission runs faster than real time and
//! deterministically. Under the real-time executor it is a [`WallClock`].

use crate::time::{Duration, Time};
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, Ordering};

/// What kind of time a clock keeps.
#[derive(Copy, Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ClockKind {
    /// Simulated time, advanced in lockstep with the simulation.
    Simulated,
    /// Wall-clock time of this host.
    Wall,
}

/// A source of time for the framework.
pub trait Clock: Send + Sync {
    /// The current time.
    fn now(&self) -> Time;
    /// What kind of time this clock keeps.
    fn kind(&self) -> ClockKind;
}

/// Simulated time, shared by every reader; only its [`ClockDriver`] moves it.
#[derive(Clone, Debug, Default)]
pub struct SimClock {
    ns: Arc<AtomicI64>,
}

/// The only handle that can advance a [`SimClock`]. Held by the lockstep executor.
#[derive(Debug)]
pub struct ClockDriver {
    ns: Arc<AtomicI64>,
}

impl SimClock {
    /// A simulated clock at [`Time::ZERO`] and the driver that advances it.
    pub fn new() -> (SimClock, ClockDriver) {
        let ns = Arc::new(AtomicI64::new(0));
        (SimClock { ns: ns.clone() }, ClockDriver { ns })
    }
}

impl Clock for SimClock {
    fn now(&self) -> Time {
        Time::from_nanos(self.ns.load(Ordering::Acquire))
    }
    fn kind(&self) -> ClockKind {
        ClockKind::Simulated
    }
}

impl ClockDriver {
    /// Moves the clock forward to `t`.
    ///
    /// # Panics
    /// If `t` is earlier than the current time: simulated time never runs backwards.
    pub fn advance_to(&self, t: Time) {
        let prev = self.ns.swap(t.as_nanos(), Ordering::AcqRel);
        assert!(prev <= t.as_nanos(), "simulated clock moved backwards from {prev} ns to {t}");
    }
    /// Moves the clock forward by `d` and returns the new time.
    pub fn advance_by(&self, d: Duration) -> Time {
        let t = self.now() + d;
        self.advance_to(t);
        t
    }
    /// The current time.
    pub fn now(&self) -> Time {
        Time::from_nanos(self.ns.load(Ordering::Acquire))
    }
}

/// Wall-clock time of this host, counted from the clock's creation.
#[derive(Clone, Debug)]
pub struct WallClock {
    start: std::time::Instant,
}

impl WallClock {
    /// A wall clock whose epoch is now.
    #[allow(clippy::disallowed_methods)] // the wall clock is the one place that reads the OS clock
    pub fn new() -> Self {
        WallClock { start: std::time::Instant::now() }
    }
    /// The OS instant matching a time on this clock (for sleeping until it).
    pub fn instant_at(&self, t: Time) -> std::time::Instant {
        self.start + Duration::from_nanos(t.as_nanos()).to_std()
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for WallClock {
    fn now(&self) -> Time {
        Time::from_nanos(i64::try_from(self.start.elapsed().as_nanos()).unwrap_or(i64::MAX))
    }
    fn kind(&self) -> ClockKind {
        ClockKind::Wall
    }
}

/// A timer attached to a clock: measures intervals and deadlines in that clock's time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Timer {
    started: Time,
    timeout: Duration,
}

impl Timer {
    /// A timer started at `now` that expires after `timeout`.
    pub fn start(now: Time, timeout: Duration) -> Self {
        Timer { started: now, timeout }
    }
    /// Time elapsed since the timer started.
    pub fn elapsed(&self, now: Time) -> Duration {
        now - self.started
    }
    /// True once `timeout` has elapsed.
    pub fn expired(&self, now: Time) -> bool {
        self.elapsed(now) >= self.timeout
    }
    /// Fraction of the timeout elapsed, clamped to [0, 1].
    pub fn fraction(&self, now: Time) -> f64 {
        if self.timeout.is_zero_or_negative() {
            return 1.0;
        }
        (self.elapsed(now).as_secs_f64() / self.timeout.as_secs_f64()).clamp(0.0, 1.0)
    }
    /// Restarts the timer at `now`.
    pub fn reset(&mut self, now: Time) {
        self.started = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sim_clock_moves_only_with_its_driver() {
        let (clock, driver) = SimClock::new();
        let reader = clock.clone();
        assert_eq!(reader.now(), Time::ZERO);
        driver.advance_by(Duration::from_millis(5));
        assert_eq!(reader.now(), Time::from_nanos(5_000_000));
        assert_eq!(clock.kind(), ClockKind::Simulated);
    }

    #[test]
    #[should_panic(expected = "backwards")]
    fn sim_clock_never_runs_backwards() {
        let (_c, driver) = SimClock::new();
        driver.advance_to(Time::from_nanos(10));
        driver.advance_to(Time::from_nanos(5));
    }

    #[test]
    fn wall_clock_is_monotonic() {
        let c = WallClock::new();
        let a = c.now();
        let b = c.now();
        assert!(b >= a);
    }

    #[test]
    fn timer_follows_the_clock() {
        let t = Timer::start(Time::from_secs_f64(1.0), Duration::from_secs(2));
        assert!(!t.expired(Time::from_secs_f64(2.9)));
        assert!(t.expired(Time::from_secs_f64(3.0)));
        assert_eq!(t.fraction(Time::from_secs_f64(2.0)), 0.5);
    }
}
