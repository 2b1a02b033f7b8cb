//! The Dry-Run locomotor: body twists and wheel rates to the twin's wheel drives.

use super::{LOCOMOTOR, SharedTwin};
use framework::hal::{BodyTwist, DeviceError, Locomotor, LocomotorModel, check_token};
use framework::resources::{ReservationToken, Resources};

/// Locomotion driver. Its model is the one the software believes (the calibrated wheel radius and
/// track): a body twist becomes wheel rates through it, as a real driver's software does, so the
/// rover moves by the true geometry, not by the command.
pub struct DryRunLocomotor {
    pub(super) twin: SharedTwin,
    pub(super) resources: Resources,
    pub(super) model: LocomotorModel,
}

impl Locomotor for DryRunLocomotor {
    fn device(&self) -> &str {
        LOCOMOTOR
    }
    fn model(&self) -> &LocomotorModel {
        &self.model
    }
    fn drive(&mut self, token: &ReservationToken, cmd: BodyTwist) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        let rates = self.model.wheel_rates(cmd).ok_or_else(|| DeviceError::InvalidCommand {
            device: LOCOMOTOR.into(),
            reason: format!(
                "twist v={} m/s, omega={} rad/s beyond limits ({} m/s, {} rad/s, {} rad/s per wheel)",
                cmd.v, cmd.omega, self.model.max_speed, self.model.max_yaw_rate, self.model.max_wheel_rate
            ),
        })?;
        self.twin.lock().command_wheels(&rates);
        Ok(())
    }
    fn set_wheel_rates(&mut self, token: &ReservationToken, rates: &[f64]) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        if rates.len() != self.model.wheels.len()
            || rates.iter().any(|r| !r.is_finite() || r.abs() > self.model.max_wheel_rate)
        {
            return Err(DeviceError::InvalidCommand {
                device: LOCOMOTOR.into(),
                reason: format!(
                    "need {} finite wheel rates within +-{} rad/s, got {rates:?}",
                    self.model.wheels.len(),
                    self.model.max_wheel_rate
                ),
            });
        }
        self.twin.lock().command_wheels(rates);
        Ok(())
    }
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        let n = self.model.wheels.len();
        self.twin.lock().command_wheels(&vec![0.0; n]);
        Ok(())
    }
}
