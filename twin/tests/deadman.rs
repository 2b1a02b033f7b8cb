//! The actuator drivers' deadman: commanded through the HAL, wheels stop and joint groups hold when
//! the commanding software falls silent for longer than the configured time.

use framework::hal::{BodyTwist, DeviceMap, MoveStatus};
use framework::message::ModuleId;
use framework::resources::Resources;
use framework::time::{Duration, Time};
use twin::devices::{DryRunDeviceMap, SharedTwin, share};
use twin::{Fidelity, StartPose, Twin};
use worlds::World;

fn kinematic() -> SharedTwin {
    let text = "name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n";
    let world = World::from_str(text, "<test>", std::path::Path::new("."), None).unwrap();
    share(Twin::with_defaults(world, StartPose { x: 0.0, y: 0.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap())
}

/// Drives at 0.2 m/s through the locomotor for 2 s of simulated time, commanding again every
/// `every` (never after the first when `None`). Returns the distance driven and the deadman trips.
fn drive(every: Option<Duration>) -> (f64, Vec<twin::sim::DeadmanTrip>) {
    let t = kinematic();
    let resources = Resources::new();
    let map = DryRunDeviceMap::new(t.clone(), resources.clone(), 1);
    let mut loco = map.locomotor().unwrap();
    let token = resources.acquire("locomotor", ModuleId(1)).unwrap();
    let start = t.lock().base_pose().translation.vector;
    let cmd = BodyTwist { v: 0.2, omega: 0.0 };
    loco.drive(&token, cmd).unwrap();
    let mut last = Time::ZERO;
    while t.lock().time() < Time::from_secs_f64(2.0) {
        let now = t.lock().time();
        if let Some(every) = every
            && now - last >= every
        {
            loco.drive(&token, cmd).unwrap();
            last = now;
        }
        t.lock().step();
    }
    let t = t.lock();
    let d = (t.base_pose().translation.vector - start).xy().norm();
    (d, t.deadman_trips().to_vec())
}

#[test]
fn wheels_stop_when_the_locomotor_hears_nothing_for_its_deadman_time() {
    let deadman =
        twin::config::TwinConfig::load(twin::config::TwinConfig::default_path()).unwrap().locomotor.deadman_s;
    assert!(deadman > 0.0);
    let (kept, kept_trips) = drive(Some(Duration::from_millis(50)));
    let (silent, trips) = drive(None);
    assert!(kept_trips.is_empty(), "{kept_trips:?}");
    assert!(kept > 0.3, "commanded every 50 ms it drove {kept} m in 2 s");
    // Silent after the first command: it drove for the deadman time only (0.2 m/s x 0.25 s), then
    // the driver stopped the wheels.
    assert!(silent < 0.2 * deadman + 0.03, "{silent} m");
    assert_eq!(trips.len(), 1, "{trips:?}");
    assert_eq!(trips[0].device, "locomotor");
    assert!((trips[0].silent_s - deadman).abs() < 0.011, "{trips:?}");
}

/// Starts a slow arm move to `aside` and steps 4 s, calling keep-alive every `every` if given.
fn arm_move(every: Option<Duration>) -> (MoveStatus, Vec<twin::sim::DeadmanTrip>) {
    let t = kinematic();
    let resources = Resources::new();
    let map = DryRunDeviceMap::new(t.clone(), resources.clone(), 1);
    let mut arm = map.joint_group("arm").unwrap();
    let token = resources.acquire("arm", ModuleId(1)).unwrap();
    let id = arm.move_to(&token, &[1.4, 0.0, 0.0, 0.0, 0.0, 0.0], 0.5).unwrap();
    let mut last = Time::ZERO;
    while t.lock().time() < Time::from_secs_f64(4.0) {
        let now = t.lock().time();
        if let Some(every) = every
            && now - last >= every
        {
            arm.keep_alive(&token).unwrap();
            last = now;
        }
        t.lock().step();
    }
    let trips = t.lock().deadman_trips().to_vec();
    (arm.move_status(id), trips)
}

#[test]
fn a_joint_group_holds_when_its_software_falls_silent_mid_move() {
    let (kept, kept_trips) = arm_move(Some(Duration::from_millis(100)));
    assert_eq!(kept, MoveStatus::Done, "kept alive every 0.1 s the move completes");
    assert!(kept_trips.is_empty(), "{kept_trips:?}");
    let (silent, trips) = arm_move(None);
    assert_eq!(silent, MoveStatus::Stopped, "silent, the group held where it was");
    assert_eq!(trips.len(), 1, "{trips:?}");
    assert_eq!(trips[0].device, "arm");
}
