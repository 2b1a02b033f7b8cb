//! The Dry-Run joint groups: the arm, the pan-tilt unit and the gripper.

use super::SharedTwin;
use framework::hal::{DeviceError, JointGroup, JointLimits, JointState, MoveId, MoveStatus, check_token};
use framework::resources::{ReservationToken, Resources};

/// A joint group (arm, pan-tilt unit, gripper).
pub struct DryRunJointGroup {
    pub(super) twin: SharedTwin,
    pub(super) resources: Resources,
    pub(super) device: String,
    pub(super) joints: Vec<String>,
    pub(super) limits: Vec<JointLimits>,
}

impl DryRunJointGroup {
    fn invalid(&self, reason: String) -> DeviceError {
        DeviceError::InvalidCommand { device: self.device.clone(), reason }
    }
}

impl JointGroup for DryRunJointGroup {
    fn device(&self) -> &str {
        &self.device
    }
    fn joint_names(&self) -> Vec<String> {
        self.joints.clone()
    }
    fn limits(&self) -> Vec<JointLimits> {
        self.limits.clone()
    }
    fn states(&self) -> Vec<JointState> {
        self.twin.lock().measured_joint_states(&self.joints)
    }
    fn move_to(
        &mut self,
        token: &ReservationToken,
        targets: &[f64],
        speed: f64,
    ) -> Result<MoveId, DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        let mut t = self.twin.lock();
        if let Some(f) = t.joint_states(&self.joints).iter().find_map(|s| s.status.fault.clone()) {
            return Err(DeviceError::Fault { device: self.device.clone(), reason: f });
        }
        t.keep_group_alive(&self.device);
        t.start_move(&self.device, targets, speed).map_err(|e| self.invalid(e))
    }
    fn move_status(&self, id: MoveId) -> MoveStatus {
        self.twin.lock().move_status(id)
    }
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        let mut t = self.twin.lock();
        t.keep_group_alive(&self.device);
        t.stop_group(&self.device).map_err(|e| self.invalid(e))
    }
    fn recover(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        let mut t = self.twin.lock();
        t.keep_group_alive(&self.device);
        t.recover_group(&self.device).map_err(|e| self.invalid(e))
    }
    fn keep_alive(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        self.twin.lock().keep_group_alive(&self.device);
        Ok(())
    }
}
