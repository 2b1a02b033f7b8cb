//! The twin does not let the software cheat: what the software is told (calibrations, models,
//! the start pose) differs from the truth by the configured errors; readings arrive late, quantized
//! and per reader; cameras have their own lenses and a photometric model.

use framework::hal::DeviceMap;
use framework::resources::Resources;
use framework::time::{Duration, Time};
use nalgebra::Point3;
use twin::belief::{StereoBelief, believed_locomotor, believed_mechanism};
use twin::config::CalibrationConfig;
use twin::devices::{DryRunDeviceMap, SharedTwin, share};
use twin::render::sensors::{Exposure, ExposureControl, SensorConfig};
use twin::{Fidelity, StartPose, Twin};
use worlds::World;

fn flat() -> World {
    let text = "name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n";
    World::from_str(text, "<test>", std::path::Path::new("."), None).unwrap()
}

fn kinematic() -> SharedTwin {
    share(Twin::with_defaults(flat(), StartPose { x: 0.0, y: 0.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap())
}

fn no_errors() -> CalibrationConfig {
    CalibrationConfig {
        wheel_radius_fraction: 0.0,
        track_fraction: 0.0,
        arm_joint_zero_deg: 0.0,
        arm_link_length_m: 0.0,
        camera_focal_fraction: 0.0,
        camera_principal_point_px: 0.0,
        camera_k1: 0.0,
        stereo_rotation_deg: 0.0,
        stereo_translation_m: 0.0,
        camera_mount_rotation_deg: 0.0,
        camera_mount_translation_m: 0.0,
    }
}

fn sd(v: &[f64]) -> f64 {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

#[test]
fn two_imu_readers_get_every_sample_and_the_same_samples() {
    let t = kinematic();
    let map = DryRunDeviceMap::new(t.clone(), Resources::new(), 7);
    let (mut a, mut b) = (map.imu().unwrap(), map.imu().unwrap());
    let cfg = t.lock().config().imu.clone();
    let mut got_a = Vec::new();
    let mut got_b = Vec::new();
    // Reader a every 20 ms, reader b every 70 ms, for 2 s.
    for k in 1..=400 {
        t.lock().step();
        if k % 4 == 0 {
            got_a.extend(a.read());
        }
        if k % 14 == 0 {
            got_b.extend(b.read());
        }
    }
    got_b.extend(b.read());
    got_a.extend(a.read());
    assert_eq!(got_a, got_b, "both readers see the same samples");
    // Every sample, one per period, none before its capture time + latency.
    let period = Duration::from_hz(cfg.rate_hz);
    assert!(got_a.len() >= 198, "{} samples in 2 s at 100 Hz", got_a.len());
    for w in got_a.windows(2) {
        assert_eq!(w[1].stamp - w[0].stamp, period);
    }
    let now = t.lock().time();
    assert!(got_a.last().unwrap().stamp <= now - Duration::from_secs_f64(cfg.latency_s));
    // The IMU delivers nothing new until the next sample arrives.
    assert!(a.read().is_empty());
}

#[test]
fn encoder_readings_step_in_counts_and_arrive_after_their_latency() {
    let t = kinematic();
    let map = DryRunDeviceMap::new(t.clone(), Resources::new(), 7);
    let mut enc = map.encoders().unwrap();
    let c = t.lock().config().encoders.clone();
    assert!(enc.read().is_none(), "no reading before the first sample has arrived");
    let count = std::f64::consts::TAU / f64::from(c.counts_per_rev);
    t.lock().set_wheel_rates(&[0.333; 4]);
    let mut last_stamp = Time::ZERO;
    for _ in 0..200 {
        t.lock().step();
        let Some(r) = enc.read() else { continue };
        let now = t.lock().time();
        assert!(now - r.stamp >= Duration::from_secs_f64(c.latency_s), "arrived before its latency");
        for (a, w) in r.angles.iter().zip(&r.rates) {
            let counts = a / count;
            assert!((counts - counts.round()).abs() < 1e-9, "angle {a} is not a whole count");
            // A rate is a whole number of counts per sample period.
            let per_sample = w / count / c.rate_hz;
            assert!((per_sample - per_sample.round()).abs() < 1e-6, "rate {w} is not whole counts");
        }
        assert!(r.stamp >= last_stamp);
        last_stamp = r.stamp;
    }
    // 1 s at 0.333 rad/s: the last rate is within one count per period of the truth.
    let r = enc.read().unwrap();
    assert!((r.rates[0] - 0.333).abs() <= count * c.rate_hz + 1e-9, "rate {}", r.rates[0]);
}

#[test]
fn the_believed_locomotor_and_arm_differ_from_the_truth_by_the_configured_errors() {
    let t = kinematic();
    let t = t.lock();
    let cal = t.config().calibration.clone();
    let truth = t.locomotor_model();
    let (mut radius, mut track) = (Vec::new(), Vec::new());
    for seed in 0..400 {
        let b = believed_locomotor(truth, &cal, seed);
        radius.push(b.wheel_radius / truth.wheel_radius - 1.0);
        track.push(b.track / truth.track - 1.0);
    }
    let (sr, st) = (sd(&radius), sd(&track));
    assert!((sr / cal.wheel_radius_fraction - 1.0).abs() < 0.15, "wheel radius error sd {sr}");
    assert!((st / cal.track_fraction - 1.0).abs() < 0.15, "track error sd {st}");
    assert_eq!(believed_locomotor(truth, &no_errors(), 5), *truth);

    // The arm: open-loop, the gripper misses where the believed model puts it by centimetres.
    let arm = ["arm_joint_1", "arm_joint_2", "arm_joint_3", "arm_joint_4", "arm_joint_5", "arm_joint_6"];
    let mech = t.mechanism();
    let mut q = vec![0.0; mech.dof_count()];
    for (name, v) in arm.iter().zip([0.3, 0.6, -0.9, 0.2, 0.5, 0.1]) {
        let i = mech.dof_names().iter().position(|n| n == name).unwrap();
        q[i] = v;
    }
    let tcp = |m: &framework::mechanism::MechanismModel| m.transform("base_link", "gripper_tcp", &q).unwrap();
    let mut miss: Vec<f64> = (0..50)
        .map(|seed| {
            let b = believed_mechanism(mech, &arm, &cal, seed).unwrap();
            (tcp(&b).translation.vector - tcp(mech).translation.vector).norm()
        })
        .collect();
    miss.sort_by(f64::total_cmp);
    let median = miss[25];
    assert!(median > 0.005 && median < 0.08, "median open-loop miss {median} m");
    let exact = believed_mechanism(mech, &arm, &no_errors(), 3).unwrap();
    assert!((tcp(&exact).translation.vector - tcp(mech).translation.vector).norm() < 1e-12);
}

/// A point straight ahead of the left camera at `z`, triangulated with the believed calibration
/// from its projections in the cameras as built: the ratio of the triangulated depth to the true.
fn depth_ratio(pair: &StereoBelief, t: &Twin, z: f64) -> f64 {
    let pose = |c: &twin::belief::CameraTruth| t.link_pose(&c.model.frame).unwrap() * c.offset;
    let (left, right) = (pose(&pair.left), pose(&pair.right));
    let p_world = left * Point3::new(0.1, 0.05, z);
    let ul = pair.left.model.project(&(left.inverse() * p_world)).unwrap();
    let ur = pair.right.model.project(&(right.inverse() * p_world)).unwrap();
    pair.calibration.triangulate(&ul, &ur).unwrap().z / z
}

#[test]
fn stereo_triangulation_with_the_calibration_is_biased_by_its_error() {
    let t = kinematic();
    let t = t.lock();
    let cfg = SensorConfig::load(SensorConfig::default_path()).unwrap();
    let build = t.config().camera_build.clone();
    let mech = t.mechanism();
    let draw = |cal: &CalibrationConfig, seed| {
        StereoBelief::draw("head_stereo", &cfg.head_stereo, mech, &build, cal, seed).unwrap()
    };
    // The two cameras of a pair are not copies of each other.
    let pair = draw(&no_errors(), 1);
    assert_ne!(pair.left.model.pinhole, pair.right.model.pinhole);
    // A perfect calibration triangulates exactly, whatever the build.
    for seed in 0..5 {
        let r = depth_ratio(&draw(&no_errors(), seed), &t, 5.0);
        assert!((r - 1.0).abs() < 1e-9, "perfect calibration: depth ratio {r}");
    }
    // A baseline error alone biases the depth by its relative size: Z' / Z = B' / B.
    let cal = CalibrationConfig { stereo_translation_m: 0.002, ..no_errors() };
    for seed in 0..10 {
        let pair = draw(&cal, seed);
        let truth = draw(&no_errors(), seed);
        let (b_believed, b_true) =
            (pair.calibration.left_from_right.translation.x, truth.calibration.left_from_right.translation.x);
        let expected = b_believed / b_true;
        let r = depth_ratio(&pair, &t, 5.0);
        assert!((r - expected).abs() < 2e-3, "depth ratio {r}, baseline ratio {expected}");
        assert!((r - 1.0).abs() > 1e-5, "the error shows");
    }
    // With the shipped errors, ranges at 5 m are off by per mille to a few per cent.
    let shipped = t.config().calibration.clone();
    let errs: Vec<f64> = (0..40).map(|s| (depth_ratio(&draw(&shipped, s), &t, 5.0) - 1.0).abs()).collect();
    let mean = errs.iter().sum::<f64>() / errs.len() as f64;
    assert!(mean > 1e-3 && mean < 0.05, "mean relative range error at 5 m: {mean}");
}

#[test]
fn the_software_gets_the_believed_models_through_the_hal() {
    let t = kinematic();
    let map = DryRunDeviceMap::new(t.clone(), Resources::new(), 11);
    let truth = t.lock().locomotor_model().clone();
    let loco = map.locomotor().unwrap();
    assert_ne!(loco.model().wheel_radius, truth.wheel_radius);
    let cal = map.stereo_camera("head_stereo").unwrap().calibration().clone();
    let built = map.stereo_belief("head_stereo").unwrap();
    assert_eq!(cal, built.calibration);
    assert_ne!(cal.left.model, built.left.model, "the calibration is not the truth");
    assert_ne!(map.mechanism().unwrap().joint("arm_joint_2").unwrap().origin, {
        let tw = t.lock();
        tw.mechanism().joint("arm_joint_2").unwrap().origin
    });
    // The same seed gives the same beliefs.
    let again = DryRunDeviceMap::new(t.clone(), Resources::new(), 11);
    assert_eq!(again.stereo_belief("head_stereo").unwrap(), built);
}

#[test]
fn auto_exposure_brings_a_dark_scene_to_its_target() {
    let c = ExposureControl {
        exposure_s: 0.004,
        auto: true,
        target_mean_dn: 110.0,
        min_exposure_s: 0.0001,
        max_exposure_s: 0.008,
        max_gain: 4.0,
    };
    // A scene at 30 grey levels at the nominal exposure; the image mean is linear in exposure x gain.
    let mut e = Exposure::NOMINAL;
    for _ in 0..20 {
        e = e.next(&c, (30.0 * e.relative * e.gain).min(255.0));
    }
    let mean = 30.0 * e.relative * e.gain;
    assert!((mean - 110.0).abs() < 2.0, "mean {mean} after 20 frames ({e:?})");
    // The exposure time saturates first (8 ms = 2x nominal), then the gain makes up the rest.
    assert!((e.relative - 2.0).abs() < 1e-9 && e.gain > 1.5, "{e:?}");
    // Off: always nominal.
    assert_eq!(Exposure::NOMINAL.next(&ExposureControl { auto: false, ..c }, 10.0), Exposure::NOMINAL);
}

#[test]
fn joint_states_arrive_after_their_latency() {
    let t = kinematic();
    let map = DryRunDeviceMap::new(t.clone(), Resources::new(), 7);
    let arm = map.joint_group("arm").unwrap();
    let c = t.lock().config().servos.clone();
    t.lock().start_move("arm", &[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0).unwrap();
    let name = vec!["arm_joint_1".to_string()];
    let mut truth: Vec<(Time, f64)> = Vec::new();
    for _ in 0..100 {
        t.lock().step();
        let now = t.lock().time();
        truth.push((now, t.lock().joint_states(&name)[0].position));
        let measured = arm.states()[0].position;
        // The newest measurement taken at a sample time no later than now - latency.
        let period = Duration::from_hz(c.state_rate_hz);
        let ready = now - Duration::from_secs_f64(c.state_latency_s);
        let expected = truth
            .iter()
            .rev()
            .find(|(t, _)| *t <= ready && (t.as_nanos() % period.as_nanos()) == 0)
            .map(|(_, q)| *q);
        if let Some(q) = expected {
            assert!((measured - q).abs() < 1e-12, "at {now:?}: measured {measured}, truth {q} at the sample");
            assert!(measured < truth.last().unwrap().1, "the measurement lags the moving joint");
        }
    }
}
