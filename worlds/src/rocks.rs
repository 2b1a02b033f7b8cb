//! Rock fields by size-frequency distribution (Golombek & Rapp 1997) and convex rock shapes.

use crate::spec::RockFieldSpec;
use nalgebra::{Point3, Vector3};
use rand::Rng;
use rand_distr::{Distribution, Poisson};
use serde::{Deserialize, Serialize};

/// One rock: a convex polyhedron given by its points (its convex hull is the rock).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rock {
    /// Position of the rock's local origin in the world frame (on the ground, at its centre).
    pub position: Point3<f64>,
    /// Heading, radians.
    pub yaw: f64,
    /// Equivalent diameter, metres.
    pub diameter: f64,
    /// Height above its base, metres.
    pub height: f64,
    /// Points in the rock's local frame (z up); their convex hull is the rock.
    pub points: Vec<Point3<f64>>,
}

/// `q` of the model for a coverage `k`.
pub fn golombek_q(k: f64) -> f64 {
    1.79 + 0.152 / k
}

/// Number density of rocks per unit area per unit diameter: `n(D) = k q e^{-qD} / (pi D^2 / 4)`.
pub fn number_density(k: f64, d: f64) -> f64 {
    let q = golombek_q(k);
    k * q * (-q * d).exp() / (std::f64::consts::PI * d * d / 4.0)
}

/// Cumulative table of the number of rocks per m^2 with diameter in [min, D], on `n` steps.
fn cumulative(spec: &RockFieldSpec, n: usize) -> Vec<(f64, f64)> {
    let (a, b) = (spec.min_diameter_m, spec.max_diameter_m);
    let h = (b - a) / n as f64;
    let mut acc = 0.0;
    let mut table = vec![(a, 0.0)];
    for s in 0..n {
        let (d0, d1) = (a + s as f64 * h, a + (s + 1) as f64 * h);
        // Simpson on each step: the density varies fast at small diameters.
        let m = 0.5 * (d0 + d1);
        acc += h / 6.0
            * (number_density(spec.coverage_k, d0)
                + 4.0 * number_density(spec.coverage_k, m)
                + number_density(spec.coverage_k, d1));
        table.push((d1, acc));
    }
    table
}

/// Expected number of rocks per square metre between the spec's diameter bounds.
pub fn expected_density(spec: &RockFieldSpec) -> f64 {
    cumulative(spec, 512).last().map(|x| x.1).unwrap_or(0.0)
}

/// Scatters rocks over `area` (x range, y range), skipping keep-out circles. `ground(x, y)` gives the
/// terrain height where a rock sits.
pub fn scatter(
    spec: &RockFieldSpec,
    area: ([f64; 2], [f64; 2]),
    ground: impl Fn(f64, f64) -> f64,
    rng: &mut impl Rng,
) -> Vec<Rock> {
    let table = cumulative(spec, 512);
    let total = table.last().map(|x| x.1).unwrap_or(0.0);
    let surface = (area.0[1] - area.0[0]) * (area.1[1] - area.1[0]);
    let mean = total * surface;
    let count = if mean > 0.0 { Poisson::new(mean).map(|p| p.sample(rng) as usize).unwrap_or(0) } else { 0 };
    let mut rocks = Vec::with_capacity(count);
    for _ in 0..count {
        // Inverse-CDF sampling of the diameter on the tabulated cumulative.
        let u = rng.random::<f64>() * total;
        let k = table.partition_point(|(_, c)| *c < u).clamp(1, table.len() - 1);
        let (d0, c0) = table[k - 1];
        let (d1, c1) = table[k];
        let d = if c1 > c0 { d0 + (u - c0) / (c1 - c0) * (d1 - d0) } else { d0 };
        let x = rng.random_range(area.0[0]..area.0[1]);
        let y = rng.random_range(area.1[0]..area.1[1]);
        let shape_seed = rng.random::<u64>();
        let yaw = rng.random_range(0.0..std::f64::consts::TAU);
        if spec.keep_out.iter().any(|c| {
            ((x - c.center_m[0]).powi(2) + (y - c.center_m[1]).powi(2)).sqrt() < c.radius_m + d / 2.0
        }) {
            continue;
        }
        let height = d * spec.height_ratio;
        // Rocks sit partly buried: a fifth of their height below the local ground.
        let position = Point3::new(x, y, ground(x, y) - 0.2 * height);
        rocks.push(Rock { position, yaw, diameter: d, height, points: rock_points(d, height, shape_seed) });
    }
    rocks
}

/// The rocks the spec places by hand, sitting on `ground` like the scattered ones.
pub fn placed(spec: &RockFieldSpec, ground: impl Fn(f64, f64) -> f64, rng: &mut impl Rng) -> Vec<Rock> {
    spec.placed
        .iter()
        .map(|p| {
            let [x, y] = p.center_m;
            let d = p.diameter_m;
            let height = d * spec.height_ratio;
            let yaw = rng.random_range(0.0..std::f64::consts::TAU);
            let position = Point3::new(x, y, ground(x, y) - 0.2 * height);
            Rock { position, yaw, diameter: d, height, points: rock_points(d, height, rng.random::<u64>()) }
        })
        .collect()
}

/// Points of an irregular rock: a perturbed half-ellipsoid plus its base ring, so the hull is convex
/// and flat-bottomed.
pub fn rock_points(diameter: f64, height: f64, seed: u64) -> Vec<Point3<f64>> {
    use rand::SeedableRng;
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed);
    let r = diameter / 2.0;
    let squash = rng.random_range(0.7..1.0);
    let mut pts = Vec::new();
    let rings = 4;
    let per_ring = 9;
    for ring in 0..=rings {
        let phi = ring as f64 / rings as f64 * std::f64::consts::FRAC_PI_2; // 0 at the base, pi/2 at the top
        let n = if ring == rings { 1 } else { per_ring };
        for s in 0..n {
            let th = (s as f64 + rng.random_range(-0.3..0.3)) / per_ring as f64 * std::f64::consts::TAU;
            let jitter = rng.random_range(0.8..1.1);
            let rr = r * phi.cos() * jitter;
            let dir = Vector3::new(th.cos(), th.sin() * squash, 0.0);
            pts.push(Point3::new(rr * dir.x, rr * dir.y, height * phi.sin() * jitter.min(1.0)));
        }
    }
    pts
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn spec(k: f64) -> RockFieldSpec {
        RockFieldSpec {
            coverage_k: k,
            min_diameter_m: 0.1,
            max_diameter_m: 1.0,
            height_ratio: 0.5,
            keep_out: vec![],
            placed: vec![],
        }
    }

    #[test]
    fn scattered_coverage_follows_the_model() {
        let s = spec(0.05);
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(3);
        let rocks = scatter(&s, ([-50.0, 50.0], [-50.0, 50.0]), |_, _| 0.0, &mut rng);
        let q = golombek_q(0.05);
        // Model area fraction of rocks in [0.1, 1.0]: k (e^{-q 0.1} - e^{-q 1.0}).
        let model = 0.05 * ((-q * 0.1f64).exp() - (-q).exp());
        let covered: f64 =
            rocks.iter().map(|r| std::f64::consts::PI * r.diameter.powi(2) / 4.0).sum::<f64>() / 1e4;
        assert!(
            (covered - model).abs() / model < 0.1,
            "covered {covered}, model {model}, {} rocks",
            rocks.len()
        );
        let expected = expected_density(&s) * 1e4;
        assert!(
            (rocks.len() as f64 - expected).abs() < 4.0 * expected.sqrt(),
            "{} vs {expected}",
            rocks.len()
        );
        assert!(rocks.iter().all(|r| (0.1..=1.0).contains(&r.diameter)));
    }

    #[test]
    fn keep_out_is_respected_and_rocks_are_bounded() {
        let mut s = spec(0.1);
        s.keep_out.push(crate::spec::KeepOutSpec { center_m: [0.0, 0.0], radius_m: 3.0 });
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(9);
        let rocks = scatter(&s, ([-10.0, 10.0], [-10.0, 10.0]), |x, _| 0.1 * x, &mut rng);
        assert!(!rocks.is_empty());
        for r in &rocks {
            assert!(r.position.coords.xy().norm() >= 3.0 + r.diameter / 2.0);
            assert!((r.position.z - (0.1 * r.position.x - 0.2 * r.height)).abs() < 1e-12);
            for p in &r.points {
                assert!(
                    p.coords.xy().norm() <= r.diameter / 2.0 * 1.1 + 1e-12
                        && p.z <= r.height + 1e-12
                        && p.z >= 0.0
                );
            }
        }
    }
}
