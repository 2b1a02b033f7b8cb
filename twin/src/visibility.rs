//! Lines of sight through the twin's world (ground truth, for the scripted operator and the
//! scorer): whether the terrain, a rock, an object or the rover itself blocks the segment between
//! two points. Rocks and objects are the physics' convex shapes, the rover its URDF collision shapes
//! at the present joint positions, the terrain the world's heightfield sampled along the segment.

use crate::convert::{point_to_rapier, pose_to_rapier};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rapier3d::parry::query::Ray;
use rapier3d::parry::shape::SharedShape;
use rapier3d::prelude::Pose;
use worlds::World;
use worlds::spec::ObjectKind;

/// The static things that can block a view: rocks and fixed objects, in the world frame.
#[derive(Clone, Default)]
pub struct Occluders {
    shapes: Vec<(Pose, SharedShape)>,
}

impl Occluders {
    /// The rocks and fixed objects of `world`.
    pub fn new(world: &World) -> Self {
        let mut shapes = Vec::new();
        for r in &world.rocks {
            let pts: Vec<_> = r.points.iter().map(point_to_rapier).collect();
            let Some(hull) = SharedShape::convex_hull(&pts) else { continue };
            let pose = Isometry3::from_parts(
                Translation3::from(r.position.coords),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), r.yaw),
            );
            shapes.push((pose_to_rapier(&pose), hull));
        }
        for o in &world.objects {
            let half = match o.kind {
                ObjectKind::Lander => Vector3::new(1.0, 1.0, 0.75),
                ObjectKind::MarkerTable => Vector3::new(0.5, 0.3, 0.4),
                ObjectKind::Canister => continue,
            };
            let pose = Isometry3::from_parts(
                Translation3::new(o.position.x, o.position.y, o.position.z + half.z),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), o.yaw),
            );
            let shape = SharedShape::cuboid(half.x as f32, half.y as f32, half.z as f32);
            shapes.push((pose_to_rapier(&pose), shape));
        }
        Occluders { shapes }
    }

    /// True when a static shape blocks the segment from `a` to `b` (its ends excluded by `margin`).
    pub fn block(&self, a: &Point3<f64>, b: &Point3<f64>, margin: f64) -> bool {
        blocked_by(self.shapes.iter().map(|(p, s)| (*p, s)), a, b, margin)
    }
}

/// True when one of `shapes` (posed) blocks the segment from `a` to `b`, ends excluded by `margin`.
pub(crate) fn blocked_by<'s>(
    shapes: impl Iterator<Item = (Pose, &'s SharedShape)>,
    a: &Point3<f64>,
    b: &Point3<f64>,
    margin: f64,
) -> bool {
    let d = b - a;
    let len = d.norm();
    if len <= 2.0 * margin {
        return false;
    }
    let dir = d / len;
    let start = a + dir * margin;
    let ray = Ray::new(point_to_rapier(&start), crate::convert::to_rapier(&dir));
    let reach = (len - 2.0 * margin) as f32;
    shapes.into_iter().any(|(pose, s)| s.cast_ray(&pose, &ray, reach, true).is_some())
}

/// True when the terrain rises above the segment from `a` to `b` anywhere between its ends (sampled
/// every 5 cm; `margin` at each end is not tested, where the points themselves may touch the ground).
pub(crate) fn terrain_blocks(world: &World, a: &Point3<f64>, b: &Point3<f64>, margin: f64) -> bool {
    let d = b - a;
    let len = d.norm();
    let n = (len / 0.05).ceil() as usize;
    (1..n).any(|k| {
        let s = k as f64 / n as f64 * len;
        if s < margin || s > len - margin {
            return false;
        }
        let p = a + d * (s / len);
        p.z < world.ground_height(p.x, p.y) - 0.005
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rock_between_two_points_blocks_the_view_and_one_beside_does_not() {
        let text = "name = \"t\"\n[terrain]\nsize_m = [20.0, 20.0]\nresolution_m = 0.5\n";
        let mut w = World::from_str(text, "<t>", std::path::Path::new("."), None).unwrap();
        let points: Vec<Point3<f64>> = [(-0.3, -0.3), (0.3, -0.3), (0.3, 0.3), (-0.3, 0.3)]
            .iter()
            .flat_map(|(x, y)| [Point3::new(*x, *y, 0.0), Point3::new(*x, *y, 0.6)])
            .collect();
        w.rocks.push(worlds::Rock {
            position: Point3::new(0.0, 0.0, 0.0),
            yaw: 0.0,
            diameter: 0.6,
            height: 0.6,
            points,
        });
        let o = Occluders::new(&w);
        let (a, b) = (Point3::new(-3.0, 0.0, 0.3), Point3::new(3.0, 0.0, 0.3));
        assert!(o.block(&a, &b, 0.01));
        assert!(!o.block(&a, &Point3::new(3.0, 2.0, 0.3), 0.01));
        assert!(!o.block(&Point3::new(-3.0, 0.0, 1.0), &Point3::new(3.0, 0.0, 1.0), 0.01), "over the top");
        // Flat ground: a segment just above it is clear, one dipping below is not.
        assert!(!terrain_blocks(&w, &Point3::new(-5.0, 5.0, 0.05), &Point3::new(5.0, 5.0, 0.05), 0.02));
        assert!(terrain_blocks(&w, &Point3::new(-5.0, 5.0, 0.5), &Point3::new(5.0, 5.0, -0.5), 0.02));
    }
}
