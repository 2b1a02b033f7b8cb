//! Reservation tokens for shared devices (seed 004, "Shared Resources").
//!
//! For long time-scales a device has one commander at a time: the holder of its [`ReservationToken`].
//! Anybody may read a device without a token. In an emergency a module may override the reservation:
//! the previous holder's token is revoked (it fails validation from then on) and an event is raised.
//! The system manager owns the table; devices are registered by the device map.

use crate::message::ModuleId;
use parking_lot::Mutex;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Proof of holding a device. Not clonable: there is exactly one per reservation.
#[derive(Debug, PartialEq, Eq)]
pub struct ReservationToken {
    device: String,
    holder: ModuleId,
    generation: u64,
}

impl ReservationToken {
    /// The reserved device.
    pub fn device(&self) -> &str {
        &self.device
    }
    /// The holder.
    pub fn holder(&self) -> ModuleId {
        self.holder
    }
}

/// Why a reservation operation failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReservationError {
    /// No device of that name is registered.
    #[error("no shared device named '{0}'")]
    UnknownDevice(String),
    /// Someone else holds it.
    #[error("device '{device}' is reserved by module #{}", holder.0)]
    Busy {
        /// The device.
        device: String,
        /// Its current holder.
        holder: ModuleId,
    },
    /// The token was revoked by an emergency override or released.
    #[error("reservation of '{0}' is no longer valid (released or overridden)")]
    Revoked(String),
}

#[derive(Debug, Default)]
struct DeviceEntry {
    holder: Option<ModuleId>,
    generation: u64,
}

/// The table of shared devices and their reservations.
#[derive(Clone, Debug, Default)]
pub struct Resources {
    devices: Arc<Mutex<BTreeMap<String, DeviceEntry>>>,
}

impl Resources {
    /// An empty table.
    pub fn new() -> Self {
        Self::default()
    }
    /// Registers a shared device (idempotent).
    pub fn register(&self, device: &str) {
        self.devices.lock().entry(device.to_string()).or_default();
    }
    /// Registered device names.
    pub fn devices(&self) -> Vec<String> {
        self.devices.lock().keys().cloned().collect()
    }
    /// Reserves `device` for `holder`, if free.
    pub fn acquire(&self, device: &str, holder: ModuleId) -> Result<ReservationToken, ReservationError> {
        let mut map = self.devices.lock();
        let e = map.get_mut(device).ok_or_else(|| ReservationError::UnknownDevice(device.into()))?;
        match e.holder {
            Some(h) => Err(ReservationError::Busy { device: device.into(), holder: h }),
            None => {
                e.generation += 1;
                e.holder = Some(holder);
                Ok(ReservationToken { device: device.into(), holder, generation: e.generation })
            }
        }
    }
    /// Takes `device` for `holder` whoever holds it; returns the token and the previous holder.
    pub fn override_emergency(
        &self,
        device: &str,
        holder: ModuleId,
    ) -> Result<(ReservationToken, Option<ModuleId>), ReservationError> {
        let mut map = self.devices.lock();
        let e = map.get_mut(device).ok_or_else(|| ReservationError::UnknownDevice(device.into()))?;
        let previous = e.holder.replace(holder);
        e.generation += 1;
        Ok((ReservationToken { device: device.into(), holder, generation: e.generation }, previous))
    }
    /// Checks that a token still grants command of its device.
    pub fn validate(&self, token: &ReservationToken) -> Result<(), ReservationError> {
        let map = self.devices.lock();
        match map.get(&token.device) {
            Some(e) if e.holder == Some(token.holder) && e.generation == token.generation => Ok(()),
            Some(_) => Err(ReservationError::Revoked(token.device.clone())),
            None => Err(ReservationError::UnknownDevice(token.device.clone())),
        }
    }
    /// Gives a device back. A revoked token releases nothing.
    pub fn release(&self, token: ReservationToken) {
        let mut map = self.devices.lock();
        if let Some(e) = map.get_mut(&token.device)
            && e.holder == Some(token.holder)
            && e.generation == token.generation
        {
            e.holder = None;
            e.generation += 1;
        }
    }
    /// Frees every reservation held by `holder` (used when the watchdog isolates a module).
    pub fn release_all_of(&self, holder: ModuleId) -> Vec<String> {
        let mut freed = Vec::new();
        for (name, e) in self.devices.lock().iter_mut() {
            if e.holder == Some(holder) {
                e.holder = None;
                e.generation += 1;
                freed.push(name.clone());
            }
        }
        freed
    }
    /// The current holder of a device.
    pub fn holder(&self, device: &str) -> Option<ModuleId> {
        self.devices.lock().get(device).and_then(|e| e.holder)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_commander_then_emergency_override() {
        let r = Resources::new();
        r.register("ptu");
        let (nav, track, fdir) = (ModuleId(1), ModuleId(2), ModuleId(3));
        let t1 = r.acquire("ptu", nav).unwrap();
        assert_eq!(
            r.acquire("ptu", track).unwrap_err(),
            ReservationError::Busy { device: "ptu".into(), holder: nav }
        );
        r.validate(&t1).unwrap();
        let (t3, prev) = r.override_emergency("ptu", fdir).unwrap();
        assert_eq!(prev, Some(nav));
        assert_eq!(r.validate(&t1).unwrap_err(), ReservationError::Revoked("ptu".into()));
        r.release(t1); // revoked token releases nothing
        assert_eq!(r.holder("ptu"), Some(fdir));
        r.release(t3);
        assert_eq!(r.holder("ptu"), None);
        let t2 = r.acquire("ptu", track).unwrap();
        assert_eq!(r.release_all_of(track), vec!["ptu".to_string()]);
        assert!(r.validate(&t2).is_err());
        assert!(matches!(r.acquire("arm", nav), Err(ReservationError::UnknownDevice(_))));
    }
}
