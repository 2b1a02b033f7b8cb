//! LocalizationVisual rests while the rover stands: the real cameras module over a ray-cast
//! localization pair, a scripted locomotion state (driving, standing, driving again). The module
//! asks for the standing rate once the rover has stood a second, for the configured rate as soon
//! as it moves, and measures the whole drive across the rest.

mod common;

use common::scene::{PairRenderer, body, loc_pair};
use framework::camera::{GreyImage, StereoCalibration};
use framework::data::{LocomotionState, PoseEstimate, VisualOdometry, VisualOdometryStatus};
use framework::executor::Executor;
use framework::hal::{BodyTwist, DeviceError, StereoCamera};
use framework::mechanism::MechanismModel;
use framework::prelude::*;
use framework::{ConfigSource, LockstepExecutor, SystemBuilder};
use gnc::cameras::Cameras;
use gnc::localization_visual::{LocalizationVisual, POSE_SLOT, SLOT};
use std::sync::{Arc, Mutex};

/// The script: 0.2 m/s ahead until 2 s, standing until 6 s, ahead again until 8 s.
fn speed(t: f64) -> f64 {
    if t < 2.0 || (6.0..8.0).contains(&t) { 0.2 } else { 0.0 }
}

/// Distance driven by `t`.
fn driven(t: f64) -> f64 {
    0.2 * (t.clamp(0.0, 2.0) + (t - 6.0).clamp(0.0, 2.0))
}

/// The simulated time the devices see (set by the test after each tick).
type Clock = Arc<Mutex<Time>>;

/// Publishes the scripted locomotion state.
struct ScriptedLocomotion {
    out: Option<Writer<LocomotionState>>,
}

impl Module for ScriptedLocomotion {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Actuator;
    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("locomotion/state"));
        d.state("active", |m, ctx| {
            let v = speed(ctx.now().as_secs_f64());
            let mode = if v > 0.0 { "follow" } else { "idle" };
            let state =
                LocomotionState { command: BodyTwist { v, omega: 0.0 }, mode: mode.into(), goal: None };
            if let Some(w) = &m.out {
                ctx.write(w, state);
            }
            Ok(())
        });
    }
}

/// The localization pair, ray-cast with the body where the script has it; captures when its
/// period has passed (a faster rate takes effect at once), with no latency. Records every rate it
/// is set to, and the time of every frame.
struct Pair {
    scene: PairRenderer,
    clock: Clock,
    period: Option<f64>,
    next: f64,
    last: Option<f64>,
    rates: Arc<Mutex<Vec<(f64, f64)>>>,
    frames: Arc<Mutex<Vec<f64>>>,
}

impl StereoCamera for Pair {
    fn device(&self) -> &str {
        "loc_stereo"
    }
    fn calibration(&self) -> &StereoCalibration {
        &self.scene.cal
    }
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError> {
        let now = self.clock.lock().unwrap().as_secs_f64();
        self.rates.lock().unwrap().push((now, hz));
        self.period = (hz > 0.0).then(|| 1.0 / hz);
        if let (Some(p), Some(last)) = (self.period, self.last) {
            self.next = self.next.min(last + p);
        }
        Ok(())
    }
    fn capture(&mut self) -> Result<Option<(GreyImage, GreyImage)>, DeviceError> {
        let now = *self.clock.lock().unwrap();
        let t = now.as_secs_f64();
        let Some(p) = self.period else { return Ok(None) };
        if t + 1e-9 < self.next {
            return Ok(None);
        }
        while self.next <= t + 1e-9 {
            self.next += p;
        }
        self.last = Some(t);
        self.frames.lock().unwrap().push(t);
        Ok(Some(self.scene.render(&body(driven(t), 0.0, 0.0), now)))
    }
}

fn mechanism() -> MechanismModel {
    let urdf = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/rover/rover.urdf");
    MechanismModel::from_urdf_file(urdf).expect("rover urdf")
}

#[test]
fn visual_odometry_rests_while_the_rover_stands_and_measures_the_drive_across_the_rest() {
    let clock: Clock = Arc::new(Mutex::new(Time::ZERO));
    let (rates, frames) = (Arc::new(Mutex::new(Vec::new())), Arc::new(Mutex::new(Vec::new())));
    let pair = Pair {
        scene: PairRenderer::new(loc_pair()),
        clock: clock.clone(),
        period: None,
        next: 0.0,
        last: None,
        rates: rates.clone(),
        frames: frames.clone(),
    };
    let cal = pair.scene.cal.clone();
    let cfg = |params: &str| {
        format!(
            "[framework]\nperiod_s = 0.05\ncontext = {{ mode = \"dry-run\", purpose = \"debug\" }}\n{params}"
        )
    };
    let mut b = SystemBuilder::new();
    b.add("locomotion", ScriptedLocomotion { out: None }, ConfigSource::inline("locomotion", cfg("")));
    b.add(
        "cameras",
        Cameras::new(vec![Box::new(pair)], vec![], vec![]),
        ConfigSource::inline("cameras", cfg("[params]\nloc_stereo_hz = 10.0\n")),
    );
    b.add(
        "vo",
        LocalizationVisual::new(cal, "cameras/loc_stereo", mechanism(), &[]).resting_with(
            "cameras",
            "loc_stereo",
            "locomotion/state",
        ),
        ConfigSource::inline("vo", cfg("[params]\nstanding_hz = 0.5\nstanding_after_s = 1.0\n")),
    );
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(50)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let reader = ex.core().board.reader::<VisualOdometry>(SLOT).unwrap().unwrap();
    let pose = ex.core().board.reader::<PoseEstimate>(POSE_SLOT).unwrap().unwrap();
    let (mut seq, mut statuses) = (0, Vec::new());
    while ex.now() < Time::from_secs_f64(9.0) {
        let now = ex.tick();
        *clock.lock().unwrap() = now;
        if let Some(v) = reader.read().filter(|v| v.seq != seq) {
            seq = v.seq;
            statuses.push(v.value.status);
        }
    }
    let rates = rates.lock().unwrap().clone();
    let frames = frames.lock().unwrap().clone();
    // Configured 10 Hz at start; 0.5 Hz about a second after the stop at 2 s; 10 Hz again as soon
    // as the motion at 6 s is commanded.
    assert_eq!(rates.len(), 3, "rates set: {rates:?}");
    assert_eq!(rates[0].1, 10.0);
    assert!(rates[1].1 == 0.5 && (3.0..3.3).contains(&rates[1].0), "rates set: {rates:?}");
    assert!(rates[2].1 == 10.0 && (6.0..6.2).contains(&rates[2].0), "rates set: {rates:?}");
    let during = |a: f64, b: f64| frames.iter().filter(|t| (a..b).contains(*t)).count();
    assert!(during(3.3, 6.0) <= 2, "frames while resting: {frames:?}");
    assert!(during(6.0, 8.0) >= 18, "frames after the restart: {frames:?}");
    // The drive measured across the rest, from the first frame to the last, without a loss.
    assert!(!statuses.contains(&VisualOdometryStatus::Lost), "statuses: {statuses:?}");
    let p = pose.read().unwrap();
    let truth = driven(p.stamp.as_secs_f64()) - driven(frames[0]);
    let x = p.value.pose.translation.vector.x;
    assert!(truth > 0.75 && (x - truth).abs() < 0.02 * truth, "measured {x:.4} m of {truth:.4} m");
}
