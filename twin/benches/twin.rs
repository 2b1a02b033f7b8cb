//! `cargo bench -p twin`: simulation cost of the rover on the Mars-like yard.
//!
//! - `full_dynamics_step`: one physics step of the rover (chassis, rockers, wheels, pan-tilt, 6-DoF
//!   arm, gripper) and the canister on the 257 x 257 heightfield with its rock field, while driving
//!   and moving the arm. Target: at most 100 us (10,000 steps/s) on one core.
//! - `kinematic_step`: the same rover in locomotion-level kinematic mode. Target: 10x cheaper.
//!
//! divan prints the time per step; items/s is steps per second.

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
