//! The motions locomotion names in a stall's reason, and which way round the rover turns.

use framework::hal::BodyTwist;
use serde::{Deserialize, Serialize};

/// What the rover was doing when a wheel stalled, as named in the stall's reason: the navigator
/// infers something ahead the map does not show only from a stall while driving forward (a skid
/// turn in place that stalls on a slope, or a stall while reversing, says nothing of the way ahead).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Motion {
    /// Forward speed, with or without turning.
    Forward,
    /// Backwards.
    Reversing,
    /// Turning with (almost) no forward speed.
    TurningInPlace,
}

impl Motion {
    /// Forward speeds under this count as none, m/s.
    const STANDING_M_S: f64 = 0.01;

    /// The motion a twist commands.
    pub fn of(t: BodyTwist) -> Self {
        if t.v > Self::STANDING_M_S {
            Motion::Forward
        } else if t.v < -Self::STANDING_M_S {
            Motion::Reversing
        } else {
            Motion::TurningInPlace
        }
    }

    /// The words in a stall's reason ("while driving forward", ...).
    pub fn describe(self) -> &'static str {
        match self {
            Motion::Forward => "while driving forward",
            Motion::Reversing => "while reversing",
            Motion::TurningInPlace => "while turning in place",
        }
    }
}

/// Which way round the rover turns: to the left (counter-clockwise seen from above, a positive yaw
/// rate) or to the right.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sense {
    /// Counter-clockwise.
    Left,
    /// Clockwise.
    Right,
}

impl Sense {
    /// The sense of a yaw rate (none: left).
    pub fn of(omega: f64) -> Self {
        if omega < 0.0 { Sense::Right } else { Sense::Left }
    }

    /// The other way round.
    pub fn opposite(self) -> Self {
        match self {
            Sense::Left => Sense::Right,
            Sense::Right => Sense::Left,
        }
    }

    /// +1 (left) or -1 (right).
    pub fn sign(self) -> f64 {
        match self {
            Sense::Left => 1.0,
            Sense::Right => -1.0,
        }
    }

    /// The words in a stall's reason after "while turning in place" (" to the left", ...).
    pub fn describe(self) -> &'static str {
        match self {
            Sense::Left => " to the left",
            Sense::Right => " to the right",
        }
    }
}

/// The yaw rate of a turn in place by `alpha` (rad, positive to the left) at `gain` (1/s), at
/// most `most` (rad/s): the shorter way round, or only the way `only` says (the long way round
/// while `alpha` points the other way).
pub fn pivot_rate(alpha: f64, gain: f64, most: f64, only: Option<Sense>) -> f64 {
    match only {
        Some(s) if alpha * s.sign() < 0.0 => s.sign() * most,
        _ => (gain * alpha).clamp(-most, most),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stall_names_the_motion_the_navigator_infers_an_obstacle_ahead_from() {
        let twist = |v, omega| BodyTwist { v, omega };
        assert_eq!(Motion::of(twist(0.2, 0.1)), Motion::Forward);
        assert_eq!(Motion::of(twist(-0.1, 0.0)), Motion::Reversing);
        // A skid turn in place, and the creep out of one, are not forward driving.
        assert_eq!(Motion::of(twist(0.0, 0.4)), Motion::TurningInPlace);
        assert_eq!(Motion::of(twist(0.005, -0.4)), Motion::TurningInPlace);
        // The three are told apart by their words, which the navigator looks for.
        let words = [Motion::Forward, Motion::Reversing, Motion::TurningInPlace].map(Motion::describe);
        for (i, a) in words.iter().enumerate() {
            for b in &words[i + 1..] {
                assert!(!a.contains(b) && !b.contains(a), "{a:?} / {b:?}");
            }
        }
    }

    #[test]
    fn a_turn_in_place_goes_the_shorter_way_round_unless_a_sense_is_imposed() {
        let (gain, most) = (1.5, 0.4);
        let right = -100f64.to_radians();
        // The shorter way: to the right, at the rate limit far off, proportionally near.
        assert_eq!(pivot_rate(right, gain, most, None), -most);
        assert!((pivot_rate(-0.1, gain, most, None) + 0.15).abs() < 1e-12);
        // Only to the left: the long way round, at full rate, while the goal lies to the right...
        assert_eq!(pivot_rate(right, gain, most, Some(Sense::Left)), most);
        assert_eq!(pivot_rate(-0.1, gain, most, Some(Sense::Left)), most);
        // ... and once past the back (alpha wraps to the left), proportionally as ever.
        assert!((pivot_rate(0.1, gain, most, Some(Sense::Left)) - 0.15).abs() < 1e-12);
        assert_eq!(pivot_rate(right, gain, most, Some(Sense::Right)), -most);
        // The senses of yaw rates, and the words a stall's reason names them by.
        assert_eq!(Sense::of(0.4), Sense::Left);
        assert_eq!(Sense::of(-0.4), Sense::Right);
        assert_eq!(Sense::Left.opposite(), Sense::Right);
        assert!(!Sense::Left.describe().contains(Sense::Right.describe()));
        assert_eq!(serde_json::to_value(Sense::Right).unwrap(), serde_json::json!("right"));
    }
}
