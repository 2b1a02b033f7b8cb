//! Clearance of the arm from the rover's own body: the URDF's collision shapes of the believed
//! mechanism, each as its bounding box (`framework::mechanism::CollisionBox`), tested pairwise
//! (separating axes) between the arm side (arm links, gripper, a held object) and the body side
//! (chassis, mast, pan-tilt, rockers, wheels), with a margin; and the arm kept above the ground
//! plane the wheels stand on. A joint-space segment is checked at samples no farther apart than
//! a joint step (`step`): with 0.02 rad the tool can move 2-4 cm between samples, more than the
//! margin, so a thin part could be passed between two samples (a known gap: a finer sampling made
//! planning too slow for a module's step).
//!
//! Written by hand (an oriented-box test is 15 axes): `gnc` does not depend on parry, and boxes
//! bounding the URDF's cylinders are conservative for the arm's clearance.

use framework::mechanism::{CollisionBox, MechanismModel};
use nalgebra::{Isometry3, Matrix3, Point3, Vector3};

/// An oriented box in a common frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Obb {
    /// Centre.
    pub center: Point3<f64>,
    /// Its axes (columns, unit vectors).
    pub axes: Matrix3<f64>,
    /// Half extents along its axes, m.
    pub half: Vector3<f64>,
}

impl Obb {
    /// The box `b` of a link whose frame is at `pose`.
    pub fn placed(pose: &Isometry3<f64>, b: &CollisionBox) -> Self {
        let p = pose * b.origin;
        Obb {
            center: Point3::from(p.translation.vector),
            axes: *p.rotation.to_rotation_matrix().matrix(),
            half: b.half_extents,
        }
    }

    /// Lowest point along `z` of the common frame.
    pub fn min_z(&self) -> f64 {
        let reach: f64 = (0..3).map(|i| self.axes[(2, i)].abs() * self.half[i]).sum();
        self.center.z - reach
    }

    /// True when the two boxes come closer than `margin` (the separating-axis test with both
    /// boxes grown by half the margin along their own axes: conservative, as a tilted edge or a
    /// corner grows by up to sqrt 3 times that, so a gap a little wider than the margin there
    /// counts as near too).
    pub fn near(&self, o: &Obb, margin: f64) -> bool {
        let (a, b) = (&self.axes, &o.axes);
        let t = o.center - self.center;
        let ha = self.half.add_scalar(margin / 2.0);
        let hb = o.half.add_scalar(margin / 2.0);
        // r[i][j] = a_i . b_j; a small epsilon for nearly parallel edges.
        let r = a.transpose() * b;
        let abs_r = r.map(|v| v.abs() + 1e-9);
        let ta = a.transpose() * t;
        for i in 0..3 {
            let rb: f64 = (0..3).map(|j| hb[j] * abs_r[(i, j)]).sum();
            if ta[i].abs() > ha[i] + rb {
                return false;
            }
        }
        for j in 0..3 {
            let ra: f64 = (0..3).map(|i| ha[i] * abs_r[(i, j)]).sum();
            let tb = (b.column(j).transpose() * t)[0];
            if tb.abs() > ra + hb[j] {
                return false;
            }
        }
        for i in 0..3 {
            for j in 0..3 {
                let (i1, i2) = ((i + 1) % 3, (i + 2) % 3);
                let (j1, j2) = ((j + 1) % 3, (j + 2) % 3);
                let ra = ha[i1] * abs_r[(i2, j)] + ha[i2] * abs_r[(i1, j)];
                let rb = hb[j1] * abs_r[(i, j2)] + hb[j2] * abs_r[(i, j1)];
                let d = (ta[i2] * r[(i1, j)] - ta[i1] * r[(i2, j)]).abs();
                if d > ra + rb {
                    return false;
                }
            }
        }
        true
    }
}

/// What a configuration touches.
#[derive(Clone, Debug, PartialEq)]
pub enum Contact {
    /// An arm-side part comes within the margin of a body-side part.
    Body {
        /// The arm-side link (or `held`).
        arm: String,
        /// The body-side link.
        body: String,
    },
    /// An arm-side part reaches below the ground plane's clearance.
    Ground {
        /// The arm-side link (or `held`).
        arm: String,
    },
}

impl std::fmt::Display for Contact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Contact::Body { arm, body } => write!(f, "{arm} would touch {body}"),
            Contact::Ground { arm } => write!(f, "{arm} would reach the ground"),
        }
    }
}

/// An object the gripper holds, as a box in the frame of the link that holds it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Held {
    /// The holding link (index in the mechanism).
    pub link: usize,
    /// The object's bounding box in that link's frame.
    pub shape: CollisionBox,
}

/// The name a held object's contacts carry.
pub const HELD: &str = "held";
/// The name an object set down on the body carries.
pub const PLACED: &str = "placed object";

/// Clearance settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClearanceParams {
    /// Smallest gap between the arm side and the body side, m.
    pub margin_m: f64,
    /// Height of `base_link`'s ground plane (where the wheels stand), m (negative: below).
    pub ground_z_m: f64,
    /// Smallest height of the arm side above that plane, m.
    pub ground_margin_m: f64,
    /// Largest joint step between checked samples of a segment, rad (or m).
    pub step: f64,
}

/// The robot's two sides and the checks between them.
#[derive(Clone, Debug)]
pub struct Clearance {
    mechanism: MechanismModel,
    arm: Vec<(usize, String, CollisionBox)>,
    body: Vec<(usize, String, CollisionBox)>,
    /// Objects set down on the body (a stowed canister): body side from then on.
    placed: Vec<Held>,
    params: ClearanceParams,
}

impl Clearance {
    /// The shapes of `mechanism`: links for which `is_arm` holds on the arm side, the others on
    /// the body side; links in `skip` are left out (an arm link coaxial with its mount joint,
    /// which no motion of the arm brings nearer the body).
    pub fn new(
        mechanism: &MechanismModel,
        is_arm: impl Fn(&str) -> bool,
        skip: &[&str],
        params: ClearanceParams,
    ) -> Self {
        let (mut arm, mut body) = (Vec::new(), Vec::new());
        for (i, l) in mechanism.links().iter().enumerate() {
            if skip.contains(&l.name.as_str()) {
                continue;
            }
            for b in &l.collision_boxes {
                let entry = (i, l.name.clone(), *b);
                if is_arm(&l.name) { arm.push(entry) } else { body.push(entry) }
            }
        }
        Clearance { mechanism: mechanism.clone(), arm, body, placed: Vec::new(), params }
    }

    /// The settings.
    pub fn params(&self) -> &ClearanceParams {
        &self.params
    }

    /// An object set down on the body (its box on a body-side link): the arm keeps clear of it.
    pub fn add_placed(&mut self, object: Held) {
        self.placed.push(object);
    }

    /// Forgets the objects set down on the body (one was taken again).
    pub fn clear_placed(&mut self) {
        self.placed.clear();
    }

    /// The first contact of the robot at joint values `q` (the mechanism's order), holding `held`;
    /// with the objects set down on the body when `placed` (not while the gripper lets go of one).
    pub fn contact(&self, q: &[f64], held: Option<&Held>, placed: bool) -> Result<Option<Contact>, String> {
        let poses = self.mechanism.link_poses(q).map_err(|e| e.to_string())?;
        let arm = self
            .arm
            .iter()
            .map(|(l, name, b)| (name.as_str(), Obb::placed(&poses[*l], b)))
            .chain(held.map(|h| (HELD, Obb::placed(&poses[h.link], &h.shape))));
        let body: Vec<(&str, Obb)> = self
            .body
            .iter()
            .map(|(l, name, b)| (name.as_str(), Obb::placed(&poses[*l], b)))
            .chain(
                self.placed
                    .iter()
                    .filter(|_| placed)
                    .map(|h| (PLACED, Obb::placed(&poses[h.link], &h.shape))),
            )
            .collect();
        let floor = self.params.ground_z_m + self.params.ground_margin_m;
        for (name, a) in arm {
            if a.min_z() < floor {
                return Ok(Some(Contact::Ground { arm: name.to_string() }));
            }
            if let Some((bn, _)) = body.iter().find(|(_, b)| a.near(b, self.params.margin_m)) {
                return Ok(Some(Contact::Body { arm: name.to_string(), body: bn.to_string() }));
            }
        }
        Ok(None)
    }

    /// The first contact on the joint-space segment from `from` to `to` (the mechanism's order),
    /// checked every `step`, the end included; with where along it (0..1). `held` and `placed` as
    /// for [`Clearance::contact`].
    pub fn segment_contact(
        &self,
        from: &[f64],
        to: &[f64],
        held: Option<&Held>,
        placed: bool,
    ) -> Result<Option<(f64, Contact)>, String> {
        let span = from.iter().zip(to).map(|(a, b)| (b - a).abs()).fold(0.0, f64::max);
        let n = (span / self.params.step).ceil().max(1.0) as usize;
        for k in 0..=n {
            let s = k as f64 / n as f64;
            let q: Vec<f64> = from.iter().zip(to).map(|(a, b)| a + (b - a) * s).collect();
            if let Some(c) = self.contact(&q, held, placed)? {
                return Ok(Some((s, c)));
            }
        }
        Ok(None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn cube(x: f64, y: f64, z: f64, yaw: f64, half: f64) -> Obb {
        let p = Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        );
        Obb::placed(&p, &CollisionBox { origin: Isometry3::identity(), half_extents: Vector3::repeat(half) })
    }

    #[test]
    fn boxes_are_near_within_the_margin_and_apart_beyond_it() {
        let a = cube(0.0, 0.0, 0.0, 0.0, 0.5);
        // Face to face, 5 cm apart.
        let b = cube(1.05, 0.0, 0.0, 0.0, 0.5);
        assert!(!b.near(&a, 0.04));
        assert!(b.near(&a, 0.06));
        // A box turned 45 degrees: its edge reaches 0.5 sqrt 2 from its centre.
        let c = cube(0.5 + 0.5 * 2f64.sqrt() + 0.03, 0.0, 0.0, std::f64::consts::FRAC_PI_4, 0.5);
        assert!(!c.near(&a, 0.02));
        assert!(c.near(&a, 0.04));
        // Edge against edge (a cross-product axis separates them).
        let tilt = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(std::f64::consts::FRAC_PI_4, 0.0, 0.0),
        );
        let d = Obb::placed(
            &(Isometry3::translation(0.0, 0.0, 1.2) * tilt),
            &CollisionBox { origin: Isometry3::identity(), half_extents: Vector3::new(0.5, 0.1, 0.1) },
        );
        let e = cube(0.0, 0.0, 0.0, std::f64::consts::FRAC_PI_4, 0.5);
        // The tilted bar's lowest edge: 1.2 - 0.1 sqrt 2 = 1.059; the cube's top is 0.5: a gap of
        // 0.559. Grown boxes are conservative along a tilted edge (the edge grows by the half
        // margin times sqrt 2): near from a margin of 0.47, not at 0.3.
        assert!(!d.near(&e, 0.3));
        assert!(d.near(&e, 0.6));
        assert!((d.min_z() - (1.2 - 0.1 * 2f64.sqrt())).abs() < 1e-12);
    }
}
