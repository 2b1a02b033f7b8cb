//! What stops the rover in kinematic fidelity: rocks it cannot climb and fixed objects, as 2D
//! footprints tested against the rover's footprint.
//!
//! A rock taller than the rover's maximum step (`locomotor.max_step_m`) is an obstacle: its
//! footprint is the convex hull of its points seen from above. Objects (a lander, a marker table)
//! are obstacles by their boxes. The rover's footprint is the rectangle around its wheels. A step
//! that would make the footprints overlap is not taken: the rover stands blocked, its wheels held
//! (as drives at their torque limit), and the contact counts as a collision once per touch.

use nalgebra::{Point2, Vector2};
use worlds::World;
use worlds::spec::ObjectKind;

/// One obstacle's footprint.
#[derive(Clone, Debug)]
pub struct Obstacle {
    /// Name (for the ground truth): `rock_<index>` or the object's name.
    pub name: String,
    centre: Point2<f64>,
    radius: f64,
    /// Convex hull, counter-clockwise.
    hull: Vec<Point2<f64>>,
}

/// The obstacles of a world.
#[derive(Clone, Debug, Default)]
pub struct Obstacles {
    list: Vec<Obstacle>,
}

impl Obstacles {
    /// The rocks of `world` taller than `max_step` and its fixed objects.
    pub fn new(world: &World, max_step: f64) -> Self {
        let mut list = Vec::new();
        for (i, r) in world.rocks.iter().enumerate() {
            if r.height <= max_step {
                continue;
            }
            let (s, c) = r.yaw.sin_cos();
            let pts: Vec<Point2<f64>> = r
                .points
                .iter()
                .map(|p| Point2::new(r.position.x + c * p.x - s * p.y, r.position.y + s * p.x + c * p.y))
                .collect();
            list.push(Obstacle::from_points(format!("rock_{i}"), &pts));
        }
        for o in &world.objects {
            let (hx, hy) = match o.kind {
                ObjectKind::Lander => (1.0, 1.0),
                ObjectKind::MarkerTable => (0.5, 0.3),
                ObjectKind::Canister => continue,
            };
            let pts = rectangle(Point2::new(o.position.x, o.position.y), o.yaw, hx, hy);
            list.push(Obstacle::from_points(o.name.clone(), &pts));
        }
        Obstacles { list }
    }

    /// The obstacle with index `k`.
    pub fn get(&self, k: usize) -> Option<&Obstacle> {
        self.list.get(k)
    }

    /// The centre of obstacle `k`'s footprint.
    pub fn centre(&self, k: usize) -> Option<Point2<f64>> {
        self.list.get(k).map(|o| o.centre)
    }

    /// Indices of the obstacles that a rectangle at (x, y), heading `yaw`, with half-length
    /// `half_length` and half-width `half_width` overlaps.
    pub fn hits(&self, x: f64, y: f64, yaw: f64, half_length: f64, half_width: f64) -> Vec<usize> {
        let centre = Point2::new(x, y);
        let reach = half_length.hypot(half_width);
        let rect = rectangle(centre, yaw, half_length, half_width);
        self.list
            .iter()
            .enumerate()
            .filter(|(_, o)| (o.centre - centre).norm() < o.radius + reach)
            .filter(|(_, o)| overlap(&rect, &o.hull))
            .map(|(k, _)| k)
            .collect()
    }
}

impl Obstacle {
    fn from_points(name: String, pts: &[Point2<f64>]) -> Self {
        let hull = convex_hull(pts);
        let n = hull.len().max(1) as f64;
        let centre = Point2::from(hull.iter().map(|p| p.coords).sum::<Vector2<f64>>() / n);
        let radius = hull.iter().map(|p| (p - centre).norm()).fold(0.0, f64::max);
        Obstacle { name, centre, radius, hull }
    }
}

/// The corners of a rectangle, counter-clockwise.
fn rectangle(c: Point2<f64>, yaw: f64, hx: f64, hy: f64) -> Vec<Point2<f64>> {
    let (s, co) = yaw.sin_cos();
    [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
        .iter()
        .map(|(a, b)| Point2::new(c.x + co * a - s * b, c.y + s * a + co * b))
        .collect()
}

/// Convex hull (Andrew's monotone chain), counter-clockwise.
fn convex_hull(pts: &[Point2<f64>]) -> Vec<Point2<f64>> {
    let mut p: Vec<Point2<f64>> = pts.to_vec();
    p.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: &Point2<f64>, a: &Point2<f64>, b: &Point2<f64>| (a - o).perp(&(b - o));
    let mut hull: Vec<Point2<f64>> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Point2<f64>>> =
            if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for q in iter {
            while hull.len() >= start + 2 && cross(&hull[hull.len() - 2], &hull[hull.len() - 1], q) <= 0.0 {
                hull.pop();
            }
            hull.push(*q);
        }
        hull.pop();
    }
    hull
}

/// Whether two convex polygons overlap (separating axis theorem).
fn overlap(a: &[Point2<f64>], b: &[Point2<f64>]) -> bool {
    let separated_by_edges_of = |p: &[Point2<f64>], q: &[Point2<f64>]| {
        (0..p.len()).any(|i| {
            let e = p[(i + 1) % p.len()] - p[i];
            let axis = Vector2::new(-e.y, e.x);
            let range = |s: &[Point2<f64>]| {
                s.iter()
                    .map(|v| v.coords.dot(&axis))
                    .fold((f64::MAX, f64::MIN), |(lo, hi), d| (lo.min(d), hi.max(d)))
            };
            let ((a0, a1), (b0, b1)) = (range(p), range(q));
            a1 < b0 || b1 < a0
        })
    };
    a.len() >= 3 && b.len() >= 3 && !separated_by_edges_of(a, b) && !separated_by_edges_of(b, a)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_and_overlap_of_simple_shapes() {
        let square = rectangle(Point2::origin(), 0.0, 1.0, 1.0);
        let inner = [Point2::new(0.1, 0.2)];
        let hull = convex_hull(&[square.clone(), inner.to_vec()].concat());
        assert_eq!(hull.len(), 4);
        let near = rectangle(Point2::new(1.9, 0.0), 0.0, 1.0, 1.0);
        let far = rectangle(Point2::new(2.1, 0.0), 0.0, 1.0, 1.0);
        assert!(overlap(&square, &near) && !overlap(&square, &far));
        // A diamond whose tip is outside a box's corner region: separated by the diamond's edge.
        let diamond = rectangle(Point2::new(1.75, 1.75), std::f64::consts::FRAC_PI_4, 0.5, 0.5);
        assert!(!overlap(&square, &diamond));
    }
}
