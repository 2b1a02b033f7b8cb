//! `cargo bench -p twin`: simulation cost of the rover on the Mars-like yard.
//!
//! - `full_dynamics_step`: one physics step of the rover (chassis, rockers, wheels, pan-tilt, 6-DoF
//!   arm, gripper, self-collision between the arm and the body) and the canister on the Mars yard's
//!   collision grid with its rock field, while driving and moving the arm, with the IMU, encoder
//!   and joint-state sampling. Target: at most 100 us (10,000 steps/s) on one core.
//! - `kinematic_step`: the same rover in locomotion-level kinematic mode. Target: 10x cheaper.
//! - `tof_pair`: both ToF cameras (176 x 144), rendered, read back, noise and validity applied.
//!   Target on 2 cores with software Vulkan: under 4 ms.
//! - `stereo_pair_640x480`: the head stereo pair as built (each camera its own intrinsics and
//!   distortion), rendered in one submission after the sun's shadow pass, with the sky, read back,
//!   lens (without a black border) and photometric model applied. `loc_stereo_pair_640x480`: the
//!   same for the body's localization pair (wider, looking down: more terrain near the camera).
//!   Compare with an older renderer in one run (machines here differ by up to 2x between runs).
//!   Both with their shipped pixel samples (the head pair 4: each pixel integrates the light over
//!   its area; the localization pair 1);
//!   `stereo_pair_640x480_one_sample`: the head pair with one sample a pixel, what the samples
//!   cost measured in the same run.
//!
//! The sensor benches stand the rover on the Mars-like yard with its pan-tilt looking at the ground
//! ahead (full terrain, rocks, the arm and the canister in view) and print the adapter in use.
//! divan prints the time per step or frame set; items/s is steps per second.

use divan::counter::ItemsCount;
use divan::{Bencher, black_box};
use framework::hal::BodyTwist;
use twin::{Fidelity, StartPose, Twin};

fn main() {
    divan::main();
}

fn rover(fidelity: Fidelity) -> Twin {
    let world = worlds::World::load(worlds::worlds_dir().join("mars_yard.toml")).expect("mars yard");
    let mut t =
        Twin::with_defaults(world, StartPose { x: -12.0, y: -12.0, yaw: 0.785 }, fidelity).expect("twin");
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.2, omega: 0.02 }).expect("within limits");
    t.set_wheel_rates(&rates);
    t.start_move("arm", &[0.3, -0.6, 1.2, 0.0, 0.5, 0.0], 0.2).expect("arm move");
    t.start_move("ptu", &[0.5, 0.3], 0.2).expect("ptu move");
    for _ in 0..200 {
        t.step();
    }
    t
}

#[divan::bench(sample_count = 30, sample_size = 200)]
fn full_dynamics_step(b: Bencher<'_, '_>) {
    let mut t = rover(Fidelity::Dynamic);
    b.counter(ItemsCount::new(1usize)).bench_local(|| {
        t.step();
        black_box(t.time())
    });
}

#[divan::bench(sample_count = 30, sample_size = 2000)]
fn kinematic_step(b: Bencher<'_, '_>) {
    let mut t = rover(Fidelity::Kinematic);
    b.counter(ItemsCount::new(1usize)).bench_local(|| {
        t.step();
        black_box(t.time())
    });
}

/// The rover on the Mars yard with its pan-tilt looking at the ground ahead, and the renderer.
fn sensing() -> (Twin, twin::render::SensorRenderer, twin::render::sensors::SensorConfig) {
    let world = worlds::World::load(worlds::worlds_dir().join("mars_yard.toml")).expect("mars yard");
    let mut t = Twin::with_defaults(world, StartPose { x: 3.5, y: 2.0, yaw: 0.6 }, Fidelity::Kinematic)
        .expect("twin");
    let id = t.start_move("ptu", &[0.0, 0.5], 1.0).expect("ptu");
    t.run_until(framework::time::Duration::from_secs(3), |t| t.move_status(id).is_over());
    let r = twin::render::SensorRenderer::new(&t).expect("a graphics adapter");
    eprintln!("adapter: {}", r.adapter());
    let cfg = twin::render::sensors::SensorConfig::load(twin::render::sensors::SensorConfig::default_path())
        .expect("sensors");
    (t, r, cfg)
}

/// Both ToF cameras (176 x 144 each), rendered and read back, noise and validity applied.
#[divan::bench(sample_count = 20, sample_size = 10)]
fn tof_pair(b: Bencher<'_, '_>) {
    use rand::SeedableRng;
    let (t, mut r, cfg) = sensing();
    let cams: Vec<_> = cfg.tof.frames.iter().map(|f| twin::render::sensors::tof_model(&cfg.tof, f)).collect();
    let poses: Vec<_> = cams.iter().map(|c| t.link_pose(&c.frame).expect("frame")).collect();
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
    b.bench_local(|| {
        for (c, p) in cams.iter().zip(&poses) {
            black_box(r.tof(&t, c, p, &cfg.tof, c, &mut rng).expect("render"));
        }
    });
}

/// One stereo pair (as built: each camera its own intrinsics and distortion) rendered in one
/// submission, lens and photometric model applied.
fn stereo_pair(
    b: Bencher<'_, '_>,
    name: &str,
    which: fn(&twin::render::SensorConfig) -> &twin::render::sensors::StereoConfig,
    pixel_samples: Option<u32>,
) {
    use rand::SeedableRng;
    let (t, mut r, cfg) = sensing();
    let s = which(&cfg);
    let photometry = twin::render::sensors::Photometry {
        pixel_samples: pixel_samples.unwrap_or(s.photometry.pixel_samples),
        ..s.photometry
    };
    let c = t.config();
    let pair = twin::belief::StereoBelief::draw(name, s, t.mechanism(), &c.camera_build, &c.calibration, 1)
        .expect("stereo pair");
    let pose = |cam: &twin::belief::CameraTruth| t.link_pose(&cam.model.frame).expect("frame") * cam.offset;
    let cams = [(&pair.left.model, pose(&pair.left)), (&pair.right.model, pose(&pair.right))];
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
    let exposure = twin::render::sensors::Exposure::NOMINAL;
    b.bench_local(|| black_box(r.grey_views(&t, &cams, &photometry, exposure, &mut rng).expect("pair")));
}

/// The head stereo pair on the pan-tilt (640 x 480 each, 70 degrees).
#[divan::bench(sample_count = 30, sample_size = 5)]
fn stereo_pair_640x480(b: Bencher<'_, '_>) {
    stereo_pair(b, "head_stereo", |c| &c.head_stereo, None);
}

/// The head stereo pair with one sample a pixel (aliased; what the samples cost).
#[divan::bench(sample_count = 30, sample_size = 5)]
fn stereo_pair_640x480_one_sample(b: Bencher<'_, '_>) {
    stereo_pair(b, "head_stereo", |c| &c.head_stereo, Some(1));
}

/// The localization stereo pair on the body (640 x 480 each, 80 degrees, looking ahead and down).
#[divan::bench(sample_count = 30, sample_size = 5)]
fn loc_stereo_pair_640x480(b: Bencher<'_, '_>) {
    stereo_pair(b, "loc_stereo", |c| &c.loc_stereo, None);
}
