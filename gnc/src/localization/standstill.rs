//! Whether the wheels stand still, and since when: `LocalizationDataFusion` takes a body whose
//! wheels have stood for a while to turn about no z axis (its zero angular rate updates).

use framework::time::Time;
use nalgebra::Isometry3;

/// Wheel odometry poses closer than this (m, and rad) are the same: an encoder count moves a
/// wheel's odometry by millimetres.
const SAME: f64 = 1e-9;

/// Where and since when the wheel odometry has stood still.
#[derive(Clone, Debug, Default)]
pub struct Standstill {
    since: Option<(Time, Isometry3<f64>)>,
}

impl Standstill {
    /// A new wheel odometry reading `pose`, the previous one `prev` at `prev_stamp`. The wheels
    /// stand while the pose stays where their stillness began (compared with that, not reading by
    /// reading: a creep of less than a count per reading adds up); a reading that moved them
    /// ends it, and one that did not starts it at the previous reading.
    pub fn reading(&mut self, prev_stamp: Time, prev: &Isometry3<f64>, pose: &Isometry3<f64>) {
        let same = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
            (a.translation.vector - b.translation.vector).norm() <= SAME
                && a.rotation.angle_to(&b.rotation) <= SAME
        };
        match &self.since {
            Some((_, start)) if same(start, pose) => {}
            _ => self.since = same(prev, pose).then_some((prev_stamp, *prev)),
        }
    }

    /// Since when the wheels stand, if they do.
    pub fn since(&self) -> Option<Time> {
        self.since.map(|(t, _)| t)
    }

    /// Whether the wheels have stood since no later than `from` and for at least `settle_s` by
    /// `now` (the body has stopped rocking).
    pub fn settled(&self, from: Time, now: Time, settle_s: f64) -> bool {
        self.since().is_some_and(|t| from >= t && (now - t).as_secs_f64() >= settle_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;

    fn at(x: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), nalgebra::UnitQuaternion::identity())
    }

    fn t(s: f64) -> Time {
        Time::from_secs_f64(s)
    }

    #[test]
    fn standing_starts_at_the_last_reading_that_moved_and_ends_with_a_move() {
        let mut s = Standstill::default();
        s.reading(t(0.0), &at(0.0), &at(0.1));
        assert_eq!(s.since(), None);
        s.reading(t(0.02), &at(0.1), &at(0.1));
        assert_eq!(s.since(), Some(t(0.02)));
        s.reading(t(0.04), &at(0.1), &at(0.1));
        assert!(s.settled(t(0.02), t(1.04), 1.0));
        assert!(!s.settled(t(0.02), t(1.0), 1.0), "not for long enough");
        assert!(!s.settled(t(0.01), t(1.04), 1.0), "an interval from before the stillness");
        s.reading(t(1.04), &at(0.1), &at(0.2));
        assert_eq!(s.since(), None);
    }

    #[test]
    fn a_creep_below_the_threshold_per_reading_adds_up() {
        let mut s = Standstill::default();
        s.reading(t(0.0), &at(0.0), &at(0.0));
        let mut x = 0.0;
        for i in 1..=10 {
            let prev = at(x);
            x += 0.4 * SAME;
            s.reading(t(i as f64 * 0.02), &prev, &at(x));
        }
        assert!(s.since().is_some_and(|since| since > t(0.0)), "the creep moved the wheels: {:?}", s.since());
    }
}
