//! Estimates with their uncertainty (seed 004, "Representing Uncertainty").
//!
//! An [`Estimate`] carries a value and its covariance together, so that no module passes a bare number
//! where a belief is meant. `Estimate<f64, f64>` is a scalar with its variance; `Estimate<SVector<f64,
//! N>, SMatrix<f64, N, N>>` ([`GaussianEstimate`]) is a Gaussian vector with its covariance matrix, with
//! the operations estimation code needs: linear propagation, fusion of independent estimates and the
//! Mahalanobis distance used to gate measurements.

use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// A value together with its uncertainty (its covariance, or variance for scalars).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate<T, C> {
    /// The estimated value (the mean, for a Gaussian).
    pub value: T,
    /// Its uncertainty: variance for scalars, covariance matrix for vectors.
    pub covariance: C,
}

/// A Gaussian estimate of an N-vector with its N x N covariance.
pub type GaussianEstimate<const N: usize> = Estimate<SVector<f64, N>, SMatrix<f64, N, N>>;

/// Why an estimate operation could not be carried out.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimateError {
    /// A covariance that had to be inverted was singular.
    #[error("covariance is singular and cannot be inverted")]
    Singular,
}

impl<T, C> Estimate<T, C> {
    /// An estimate from its value and uncertainty.
    pub const fn new(value: T, covariance: C) -> Self {
        Estimate { value, covariance }
    }
}

impl Estimate<f64, f64> {
    /// Standard deviation of a scalar estimate.
    pub fn std_dev(&self) -> f64 {
        self.covariance.max(0.0).sqrt()
    }
    /// Inverse-variance fusion of two independent scalar estimates.
    pub fn fuse(&self, other: &Self) -> Result<Self, EstimateError> {
        let s = self.covariance + other.covariance;
        if s <= 0.0 {
            return Err(EstimateError::Singular);
        }
        let k = self.covariance / s;
        Ok(Estimate::new(self.value + k * (other.value - self.value), (1.0 - k) * self.covariance))
    }
}

impl<const N: usize> GaussianEstimate<N> {
    /// An estimate with independent components of the given standard deviations.
    pub fn with_std_devs(value: SVector<f64, N>, std_devs: SVector<f64, N>) -> Self {
        Estimate::new(value, SMatrix::from_diagonal(&std_devs.component_mul(&std_devs)))
    }
    /// Standard deviation of each component (square roots of the covariance diagonal).
    pub fn std_devs(&self) -> SVector<f64, N> {
        self.covariance.diagonal().map(|v| v.max(0.0).sqrt())
    }
    /// Propagates through the linear model `x' = F x + u` with process noise `Q`.
    pub fn propagate(&self, f: &SMatrix<f64, N, N>, u: &SVector<f64, N>, q: &SMatrix<f64, N, N>) -> Self {
        Estimate::new(f * self.value + u, f * self.covariance * f.transpose() + q)
    }
    /// Fuses two independent estimates of the same quantity (Kalman update with H = I).
    pub fn fuse(&self, other: &Self) -> Result<Self, EstimateError> {
        let s = self.covariance + other.covariance;
        let s_inv = s.try_inverse().ok_or(EstimateError::Singular)?;
        let k = self.covariance * s_inv;
        let value = self.value + k * (other.value - self.value);
        let i_k = SMatrix::<f64, N, N>::identity() - k;
        // Joseph form keeps the covariance symmetric and positive semi-definite.
        let cov = i_k * self.covariance * i_k.transpose() + k * other.covariance * k.transpose();
        Ok(Estimate::new(value, cov))
    }
    /// Mahalanobis distance of a point from this estimate.
    pub fn mahalanobis(&self, x: &SVector<f64, N>) -> Result<f64, EstimateError> {
        let inv = self.covariance.try_inverse().ok_or(EstimateError::Singular)?;
        let d = x - self.value;
        Ok((d.transpose() * inv * d)[(0, 0)].max(0.0).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    #[test]
    fn scalar_fusion_is_inverse_variance_weighting() {
        let a = Estimate::new(1.0, 4.0);
        let b = Estimate::new(3.0, 4.0);
        let f = a.fuse(&b).unwrap();
        assert!((f.value - 2.0).abs() < 1e-12);
        assert!((f.covariance - 2.0).abs() < 1e-12);
        assert_eq!(Estimate::new(0.0, 9.0).std_dev(), 3.0);
    }

    #[test]
    fn vector_fusion_shrinks_covariance_and_weights_by_certainty() {
        let a = GaussianEstimate::<2>::with_std_devs(Vector2::new(0.0, 0.0), Vector2::new(1.0, 0.1));
        let b = GaussianEstimate::<2>::with_std_devs(Vector2::new(1.0, 1.0), Vector2::new(0.1, 1.0));
        let f = a.fuse(&b).unwrap();
        // x is known better by b, y by a.
        assert!(f.value.x > 0.95 && f.value.y < 0.05, "{:?}", f.value);
        assert!(f.covariance[(0, 0)] < 0.01 + 1e-9 && f.covariance[(1, 1)] < 0.01 + 1e-9);
        assert!((f.covariance - f.covariance.transpose()).norm() < 1e-12);
    }

    #[test]
    fn propagation_and_gating() {
        let x = GaussianEstimate::<2>::with_std_devs(Vector2::new(0.0, 1.0), Vector2::new(0.5, 0.5));
        let dt = 0.1;
        let f = Matrix2::new(1.0, dt, 0.0, 1.0);
        let p = x.propagate(&f, &Vector2::zeros(), &(Matrix2::identity() * 0.01));
        assert!((p.value.x - 0.1).abs() < 1e-12);
        assert!(p.covariance[(0, 0)] > x.covariance[(0, 0)]);
        let d = x.mahalanobis(&Vector2::new(1.0, 1.0)).unwrap();
        assert!((d - 2.0).abs() < 1e-12);
        let singular = GaussianEstimate::<2>::new(Vector2::zeros(), Matrix2::zeros());
        assert_eq!(singular.mahalanobis(&Vector2::zeros()), Err(EstimateError::Singular));
    }
}
