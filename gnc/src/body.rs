//! The robot's own body as its software knows it (the believed mechanism model): what a sensor
//! sees of the robot itself, to be filtered out — the chassis as a box in `base_link`, the
//! articulated links (arm, mast, pan-tilt) as segments between joint origins with a radius.

use crate::navigation::dem::segment_distance;
use framework::mechanism::MechanismModel;
use nalgebra::{Isometry3, Point3};

/// A link segment in `base_link`: from its joint's origin to its child joint's origin.
pub type Segment = (Point3<f64>, Point3<f64>);

/// The robot's link segments (between joint origins, below the root) in `base_link` for the joint
/// values `q` (in the mechanism's order).
pub fn link_segments(mechanism: &MechanismModel, q: &[f64]) -> Result<Vec<Segment>, String> {
    let poses = mechanism.link_poses(q).map_err(|e| e.to_string())?;
    let root = mechanism.link(mechanism.root()).map_err(|e| e.to_string())?;
    Ok(mechanism
        .joints()
        .iter()
        .filter(|j| j.parent != root)
        .map(|j| {
            (
                Point3::from(poses[j.parent].translation.vector),
                Point3::from(poses[j.child].translation.vector),
            )
        })
        .collect())
}

/// True when `p` (in `base_link`) lies on the robot: inside `body_box` ([x_min, x_max, y_min,
/// y_max, z_min, z_max], m) or within `radius_m` of one of `links`.
pub fn on_body(p: &Point3<f64>, body_box: &[f64; 6], radius_m: f64, links: &[Segment]) -> bool {
    let b = body_box;
    ((b[0]..=b[1]).contains(&p.x) && (b[2]..=b[3]).contains(&p.y) && (b[4]..=b[5]).contains(&p.z))
        || links.iter().any(|(a, c)| segment_distance(p, a, c) < radius_m)
}

/// A filter of points seen by a camera mounted on link `mount` of `mechanism`: true for a point (in
/// the frame `mount_from_camera` places on the mount) that lies off the robot as it stands at joint
/// values `q` (see [`on_body`]).
pub fn camera_filter(
    mechanism: &MechanismModel,
    q: &[f64],
    mount: &str,
    mount_from_camera: &Isometry3<f64>,
    body_box: [f64; 6],
    radius_m: f64,
) -> Result<impl Fn(&Point3<f64>) -> bool + use<>, String> {
    let links = link_segments(mechanism, q)?;
    let base_from_mount = mechanism.transform(mechanism.root(), mount, q).map_err(|e| e.to_string())?;
    let base_from_camera = base_from_mount * mount_from_camera;
    Ok(move |p: &Point3<f64>| !on_body(&(base_from_camera * p), &body_box, radius_m, &links))
}

/// The joint values of `mechanism` (in its order) from named joint states; joints not named stay 0.
pub fn joint_values<'a>(
    mechanism: &MechanismModel,
    states: impl IntoIterator<Item = (&'a str, f64)>,
) -> Vec<f64> {
    let names = mechanism.dof_names();
    let mut q = vec![0.0; names.len()];
    for (name, value) in states {
        if let Some(d) = names.iter().position(|n| *n == name) {
            q[d] = value;
        }
    }
    q
}
