//! Time as integer nanoseconds (seed 004, "Different Time Representations").
//!
//! [`Time`] is an instant on a [`crate::clock::Clock`]'s time line, counted in nanoseconds from the
//! clock's epoch (the start of a run). [`Duration`] is a signed span in nanoseconds. Integer time keeps
//! the lockstep executor exact: a 50 Hz module on a 1 ms base period is due on exactly every 20th tick,
//! with no floating-point drift. Floating-point seconds exist only at the edges (files, plots).
//! Arithmetic saturates at the ends of the range (about ±292 years): a huge configured span is a
//! far future, never an overflow.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::{Add, AddAssign, Div, Mul, Sub, SubAssign};

const NANOS_PER_SEC: i64 = 1_000_000_000;

/// An instant: nanoseconds since the clock's epoch.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Time(i64);

/// A signed time span in nanoseconds.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Duration(i64);

impl Time {
    /// The clock's epoch.
    pub const ZERO: Time = Time(0);
    /// The largest representable instant (about 292 years).
    pub const MAX: Time = Time(i64::MAX);

    /// An instant `ns` nanoseconds after the epoch.
    pub const fn from_nanos(ns: i64) -> Self {
        Time(ns)
    }
    /// An instant from seconds after the epoch, rounded to the nearest nanosecond.
    pub fn from_secs_f64(s: f64) -> Self {
        Time((s * NANOS_PER_SEC as f64).round() as i64)
    }
    /// Nanoseconds since the epoch.
    pub const fn as_nanos(self) -> i64 {
        self.0
    }
    /// Seconds since the epoch (for plots and files only).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 / NANOS_PER_SEC as f64
    }
    /// The span since the epoch.
    pub const fn since_epoch(self) -> Duration {
        Duration(self.0)
    }
}

impl Duration {
    /// No time at all.
    pub const ZERO: Duration = Duration(0);
    /// The largest representable span.
    pub const MAX: Duration = Duration(i64::MAX);

    /// A span of `ns` nanoseconds.
    pub const fn from_nanos(ns: i64) -> Self {
        Duration(ns)
    }
    /// A span of `us` microseconds.
    pub const fn from_micros(us: i64) -> Self {
        Duration(us * 1_000)
    }
    /// A span of `ms` milliseconds.
    pub const fn from_millis(ms: i64) -> Self {
        Duration(ms * 1_000_000)
    }
    /// A span of `s` whole seconds.
    pub const fn from_secs(s: i64) -> Self {
        Duration(s * NANOS_PER_SEC)
    }
    /// A span from seconds, rounded to the nearest nanosecond.
    pub fn from_secs_f64(s: f64) -> Self {
        Duration((s * NANOS_PER_SEC as f64).round() as i64)
    }
    /// The period of a rate in hertz, rounded to the nearest nanosecond.
    pub fn from_hz(hz: f64) -> Self {
        Duration((NANOS_PER_SEC as f64 / hz).round() as i64)
    }
    /// Nanoseconds.
    pub const fn as_nanos(self) -> i64 {
        self.0
    }
    /// Seconds as a float (for arithmetic in SI units).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 / NANOS_PER_SEC as f64
    }
    /// True for a span of zero or less.
    pub const fn is_zero_or_negative(self) -> bool {
        self.0 <= 0
    }
    /// The equivalent `std::time::Duration` (negative spans saturate to zero).
    pub fn to_std(self) -> std::time::Duration {
        std::time::Duration::from_nanos(self.0.max(0) as u64)
    }
    /// From a `std::time::Duration` (saturating at [`Duration::MAX`]).
    pub fn from_std(d: std::time::Duration) -> Self {
        Duration(i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
    }
}

impl Add<Duration> for Time {
    type Output = Time;
    fn add(self, d: Duration) -> Time {
        Time(self.0.saturating_add(d.0))
    }
}
impl AddAssign<Duration> for Time {
    fn add_assign(&mut self, d: Duration) {
        self.0 = self.0.saturating_add(d.0);
    }
}
impl Sub<Duration> for Time {
    type Output = Time;
    fn sub(self, d: Duration) -> Time {
        Time(self.0.saturating_sub(d.0))
    }
}
impl Sub for Time {
    type Output = Duration;
    fn sub(self, other: Time) -> Duration {
        Duration(self.0.saturating_sub(other.0))
    }
}
impl Add for Duration {
    type Output = Duration;
    fn add(self, o: Duration) -> Duration {
        Duration(self.0.saturating_add(o.0))
    }
}
impl AddAssign for Duration {
    fn add_assign(&mut self, o: Duration) {
        self.0 = self.0.saturating_add(o.0);
    }
}
impl Sub for Duration {
    type Output = Duration;
    fn sub(self, o: Duration) -> Duration {
        Duration(self.0.saturating_sub(o.0))
    }
}
impl SubAssign for Duration {
    fn sub_assign(&mut self, o: Duration) {
        self.0 = self.0.saturating_sub(o.0);
    }
}
impl Mul<i64> for Duration {
    type Output = Duration;
    fn mul(self, k: i64) -> Duration {
        Duration(self.0.saturating_mul(k))
    }
}
impl Div<i64> for Duration {
    type Output = Duration;
    fn div(self, k: i64) -> Duration {
        Duration(self.0 / k)
    }
}

impl fmt::Display for Time {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:.6} s", self.as_secs_f64())
    }
}
impl fmt::Display for Duration {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let ns = self.0.unsigned_abs();
        let sign = if self.0 < 0 { "-" } else { "" };
        if ns >= NANOS_PER_SEC as u64 {
            write!(f, "{sign}{:.3} s", ns as f64 / 1e9)
        } else if ns >= 1_000_000 {
            write!(f, "{sign}{:.3} ms", ns as f64 / 1e6)
        } else if ns >= 1_000 {
            write!(f, "{sign}{:.3} us", ns as f64 / 1e3)
        } else {
            write!(f, "{sign}{ns} ns")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_are_exact_in_nanoseconds() {
        assert_eq!(Duration::from_hz(50.0), Duration::from_millis(20));
        assert_eq!(Duration::from_hz(10.0), Duration::from_millis(100));
        assert_eq!(Duration::from_secs_f64(0.1).as_nanos(), 100_000_000);
        assert_eq!(Time::from_secs_f64(1.5) - Time::ZERO, Duration::from_millis(1500));
    }

    #[test]
    fn arithmetic_and_display() {
        let t = Time::ZERO + Duration::from_secs(2);
        assert_eq!((t - Duration::from_millis(500)).as_secs_f64(), 1.5);
        assert_eq!(Duration::from_micros(3) * 2, Duration::from_nanos(6000));
        assert_eq!(Duration::from_micros(1500).to_string(), "1.500 ms");
        assert_eq!(Duration::from_nanos(-20).to_string(), "-20 ns");
        assert_eq!(Duration::from_nanos(-5).to_std(), std::time::Duration::ZERO);
    }

    #[test]
    fn huge_spans_saturate_instead_of_overflowing() {
        let far = Duration::from_secs_f64(1e300);
        assert_eq!(far, Duration::MAX);
        assert_eq!(Time::from_secs_f64(10.0) + far, Time::MAX);
        let mut t = Time::from_secs_f64(1.0);
        t += far;
        assert_eq!(t, Time::MAX);
        assert_eq!((Time::ZERO - Time::MAX) - Duration::MAX, Duration::from_nanos(i64::MIN));
        assert_eq!(far * 3, Duration::MAX);
        assert_eq!(far + far, Duration::MAX);
    }
}
