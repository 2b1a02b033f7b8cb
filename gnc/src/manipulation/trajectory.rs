//! Arm motions: joint-space paths clear of the rover's body, and the timing of each segment within
//! the joints' speed and acceleration limits.
//!
//! The arm's device moves all joints of a segment along a straight line in joint space with one
//! smooth (cubic) profile, so a path is a list of via-points and its collision check is the
//! segments' (see [`Clearance::segment_contact`]). A path goes straight when that is clear; else
//! through one or two of the configured via-poses (safe poses high above the body), the cheapest
//! clear combination first.

use super::clearance::{Clearance, Contact, Held};
use super::kinematics::distance;

/// Why no path was found.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PathError {
    /// Straight and through every via-pose, something is in the way.
    #[error("no clear path to the goal: straight, {0}; no via-pose clears it")]
    Blocked(Contact),
    /// The goal itself touches.
    #[error("the goal is not clear: {0}")]
    Goal(Contact),
    /// The start itself touches (the arm must first be moved clear by hand or by a straight move).
    #[error("the arm is not clear where it stands: {0}")]
    Start(Contact),
    /// The model refused the joint values.
    #[error("{0}")]
    Model(String),
}

/// A path from `from` to `to` (arm joint values) as the via-points after `from` (ending with
/// `to`), every segment clear. `full` turns arm values into the whole mechanism's; `vias` are the
/// via-poses to try.
pub fn plan_path(
    clearance: &Clearance,
    full: &dyn Fn(&[f64]) -> Vec<f64>,
    from: &[f64],
    to: &[f64],
    vias: &[Vec<f64>],
    held: Option<&Held>,
) -> Result<Vec<Vec<f64>>, PathError> {
    let segment = |a: &[f64], b: &[f64]| -> Result<Option<Contact>, PathError> {
        let c = clearance.segment_contact(&full(a), &full(b), held, true).map_err(PathError::Model)?;
        Ok(c.map(|(_, c)| c))
    };
    let point = |q: &[f64]| clearance.contact(&full(q), held, true).map_err(PathError::Model);
    if let Some(c) = point(to)? {
        return Err(PathError::Goal(c));
    }
    if let Some(c) = point(from)? {
        return Err(PathError::Start(c));
    }
    let Some(straight) = segment(from, to)? else { return Ok(vec![to.to_vec()]) };
    let clear_vias: Vec<&Vec<f64>> = vias.iter().filter(|v| point(v).ok().flatten().is_none()).collect();
    // One via-pose, the shortest detour first.
    let mut ones: Vec<(f64, &Vec<f64>)> =
        clear_vias.iter().map(|v| (distance(from, v) + distance(v, to), *v)).collect();
    ones.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (_, v) in &ones {
        if segment(from, v)?.is_none() && segment(v, to)?.is_none() {
            return Ok(vec![(*v).clone(), to.to_vec()]);
        }
    }
    // Two via-poses.
    let mut twos = Vec::new();
    for a in &clear_vias {
        for b in &clear_vias {
            if a != b {
                twos.push((distance(from, a) + distance(a, b) + distance(b, to), *a, *b));
            }
        }
    }
    twos.sort_by(|x, y| x.0.total_cmp(&y.0));
    for (_, a, b) in twos {
        if segment(from, a)?.is_none() && segment(a, b)?.is_none() && segment(b, to)?.is_none() {
            return Ok(vec![a.clone(), b.clone(), to.to_vec()]);
        }
    }
    Err(PathError::Blocked(straight))
}

/// The speed fraction to ask the arm's device for so that a segment from `from` to `to` keeps
/// within the limits. The device gives a segment the duration `max_j |dq_j| / (v_j s)` and a cubic
/// profile (peak speed 1.5 times the mean, peak acceleration `6 |dq| / T^2`): the duration is the
/// longest of what each joint's speed limit `v_j` (times `max_speed`, a fraction) and acceleration
/// limit `a_j` allow, and the fraction that gives it is returned, in (0, 1].
pub fn segment_speed(
    from: &[f64],
    to: &[f64],
    speed_limits: &[f64],
    accel_limits: &[f64],
    max_speed: f64,
) -> f64 {
    let mut duration: f64 = 0.0;
    let mut nominal: f64 = 0.0;
    for (((a, b), v), acc) in from.iter().zip(to).zip(speed_limits).zip(accel_limits) {
        let d = (b - a).abs();
        if *v <= 0.0 {
            continue;
        }
        nominal = nominal.max(d / v);
        duration = duration.max(1.5 * d / (v * max_speed));
        if *acc > 0.0 {
            duration = duration.max((6.0 * d / acc).sqrt());
        }
    }
    if duration <= 0.0 { 1.0 } else { (nominal / duration).clamp(1e-3, 1.0) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_segment_speed_keeps_each_joint_within_its_speed_and_acceleration() {
        let (from, to) = ([0.0, 0.0], [1.0, -0.2]);
        let (v, a) = ([1.0, 0.5], [2.0, 2.0]);
        for max in [0.3, 0.6, 1.0] {
            let s = segment_speed(&from, &to, &v, &a, max);
            // The device's duration for that fraction.
            let t = (1.0 / (1.0 * s)).max(0.2 / (0.5 * s));
            for j in 0..2 {
                let d = (to[j] - from[j]).abs();
                assert!(1.5 * d / t <= v[j] * max + 1e-9, "speed of joint {j} at {max}");
                assert!(6.0 * d / (t * t) <= a[j] + 1e-9, "acceleration of joint {j} at {max}");
            }
        }
        // A short segment is limited by acceleration alone: the slowest speed fraction.
        let s = segment_speed(&[0.0], &[0.01], &[1.0], &[2.0], 1.0);
        let t = 0.01 / s;
        assert!((6.0 * 0.01 / (t * t) - 2.0).abs() < 1e-9);
    }
}
