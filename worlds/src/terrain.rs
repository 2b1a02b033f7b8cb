//! The terrain heightfield: a regular grid of heights over a rectangle centred on the world origin.

use nalgebra::{Point2, Vector3};
use serde::{Deserialize, Serialize};

/// Heights on a regular grid. Sample `(i, j)` is at `x = min_x + i * cell`, `y = min_y + j * cell`;
/// heights are stored row by row (`j` major, `i` minor).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Heightfield {
    /// Samples along x.
    pub nx: usize,
    /// Samples along y.
    pub ny: usize,
    /// Grid spacing, metres.
    pub cell: f64,
    /// Position of sample (0, 0) in the world frame.
    pub origin: Point2<f64>,
    /// Heights, metres, `heights[j * nx + i]`.
    pub heights: Vec<f64>,
}

impl Heightfield {
    /// A flat grid covering `size` (centred on the origin) at spacing `cell`.
    pub fn flat(size: [f64; 2], cell: f64) -> Self {
        let nx = (size[0] / cell).round() as usize + 1;
        let ny = (size[1] / cell).round() as usize + 1;
        let origin = Point2::new(-((nx - 1) as f64) * cell / 2.0, -((ny - 1) as f64) * cell / 2.0);
        Heightfield { nx, ny, cell, origin, heights: vec![0.0; nx * ny] }
    }

    /// Extent along x and y, metres.
    pub fn size(&self) -> [f64; 2] {
        [(self.nx - 1) as f64 * self.cell, (self.ny - 1) as f64 * self.cell]
    }

    /// World position of sample (i, j).
    pub fn position(&self, i: usize, j: usize) -> Point2<f64> {
        Point2::new(self.origin.x + i as f64 * self.cell, self.origin.y + j as f64 * self.cell)
    }

    /// Height of sample (i, j).
    pub fn at(&self, i: usize, j: usize) -> f64 {
        self.heights[j * self.nx + i]
    }

    /// True if (x, y) lies over the grid.
    pub fn contains(&self, x: f64, y: f64) -> bool {
        let [sx, sy] = self.size();
        (x - self.origin.x) >= 0.0
            && (x - self.origin.x) <= sx
            && (y - self.origin.y) >= 0.0
            && (y - self.origin.y) <= sy
    }

    /// Height at (x, y), bilinear between samples; clamped to the edge outside the grid.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let fx = ((x - self.origin.x) / self.cell).clamp(0.0, (self.nx - 1) as f64);
        let fy = ((y - self.origin.y) / self.cell).clamp(0.0, (self.ny - 1) as f64);
        let (i, j) = ((fx.floor() as usize).min(self.nx - 2), (fy.floor() as usize).min(self.ny - 2));
        let (tx, ty) = (fx - i as f64, fy - j as f64);
        let h00 = self.at(i, j);
        let h10 = self.at(i + 1, j);
        let h01 = self.at(i, j + 1);
        let h11 = self.at(i + 1, j + 1);
        (h00 * (1.0 - tx) + h10 * tx) * (1.0 - ty) + (h01 * (1.0 - tx) + h11 * tx) * ty
    }

    /// Unit surface normal at (x, y), from central differences.
    pub fn normal(&self, x: f64, y: f64) -> Vector3<f64> {
        let d = self.cell;
        let dzdx = (self.height(x + d, y) - self.height(x - d, y)) / (2.0 * d);
        let dzdy = (self.height(x, y + d) - self.height(x, y - d)) / (2.0 * d);
        Vector3::new(-dzdx, -dzdy, 1.0).normalize()
    }

    /// Slope angle at (x, y), radians.
    pub fn slope(&self, x: f64, y: f64) -> f64 {
        self.normal(x, y).z.clamp(-1.0, 1.0).acos()
    }

    /// Lowest and highest heights.
    pub fn height_range(&self) -> (f64, f64) {
        self.heights.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), h| (lo.min(*h), hi.max(*h)))
    }

    /// Applies `f(x, y, h) -> h'` to every sample.
    pub fn map(&mut self, mut f: impl FnMut(f64, f64, f64) -> f64) {
        for j in 0..self.ny {
            for i in 0..self.nx {
                let p = self.position(i, j);
                let k = j * self.nx + i;
                self.heights[k] = f(p.x, p.y, self.heights[k]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_geometry_and_interpolation() {
        let mut h = Heightfield::flat([4.0, 2.0], 0.5);
        assert_eq!((h.nx, h.ny), (9, 5));
        assert_eq!(h.size(), [4.0, 2.0]);
        assert_eq!(h.origin, Point2::new(-2.0, -1.0));
        h.map(|x, y, _| 0.1 * x + 0.2 * y);
        assert!((h.height(0.3, -0.7) - (0.03 - 0.14)).abs() < 1e-12);
        let n = h.normal(0.0, 0.0);
        assert!((n - Vector3::new(-0.1, -0.2, 1.0).normalize()).norm() < 1e-9);
        assert!((h.slope(0.0, 0.0) - (0.1f64.powi(2) + 0.04).sqrt().atan()).abs() < 1e-9);
        assert!(h.contains(2.0, 1.0) && !h.contains(2.1, 0.0));
    }
}
