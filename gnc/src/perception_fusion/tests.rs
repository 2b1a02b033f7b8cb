//! PerceptionDataFusion in a lockstep system fed local maps and poses by a stub.

use super::*;
use framework::data::{ElevationMap, GridGeometry};
use framework::{ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use std::sync::{Arc, Mutex};

/// One local map: a 1 m square of level ground centred on `centre` (`map`), of images captured
/// `age_s` ago, fused with the pose estimate at the origin having been relocalized
/// `relocalizations` times.
#[derive(Clone, Copy)]
struct Step {
    centre: [f64; 2],
    relocalizations: u32,
    age_s: f64,
}

/// Writes the pose estimate and one local map of `steps` every third cycle, and keeps the newest
/// global map published.
struct Feed {
    steps: Vec<Step>,
    cycle: u32,
    seen: Arc<Mutex<Option<ElevationMap>>>,
    pose: Option<Writer<PoseEstimate>>,
    local: Option<Writer<ElevationMap>>,
    global: Option<Reader<ElevationMap>>,
}

impl Module for Feed {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.pose = Some(d.writes("pose"));
        self.local = Some(d.writes("perception/local_dem"));
        self.global = Some(d.reads("perception/global_dem"));
        d.state("feeding", |m, ctx| {
            if let Some(g) = m.global.as_ref().and_then(|r| ctx.read(r)) {
                *m.seen.lock().unwrap() = Some(g.value.clone());
            }
            m.cycle += 1;
            if m.cycle % 3 != 0 || m.steps.is_empty() {
                return Ok(());
            }
            let step = m.steps.remove(0);
            let pose = PoseEstimate {
                relocalizations: step.relocalizations,
                covariance: nalgebra::Matrix6::identity() * 1e-4,
                ..PoseEstimate::planar("map", 0.0, 0.0, 0.0, 0.0)
            };
            let mut local = ElevationMap::unknown(GridGeometry::centred("map", step.centre, 0.1, 10, 10));
            local.height.fill(0.0);
            local.variance.fill(1e-4);
            local.count.fill(1);
            local.min.fill(0.0);
            local.max.fill(0.0);
            ctx.write(m.pose.as_ref().unwrap(), pose);
            let captured = ctx.now() - Duration::from_secs_f64(step.age_s);
            ctx.write_stamped(m.local.as_ref().unwrap(), local, captured);
            Ok(())
        });
    }
}

/// The global map published once every step of `steps` was fused.
fn fused(steps: &[Step]) -> ElevationMap {
    let seen = Arc::new(Mutex::new(None));
    let feed =
        Feed { steps: steps.to_vec(), cycle: 0, seen: seen.clone(), pose: None, local: None, global: None };
    let mut b = SystemBuilder::new();
    let cfg = |name: &str, params: &str| {
        ConfigSource::inline(name, format!("[framework]\nperiod_s = 0.1\n[params]\n{params}\n"))
    };
    b.add("feed", feed, cfg("feed", ""));
    b.add("fusion", PerceptionDataFusion::new("pose", "feed"), cfg("fusion", "publish_hz = 10.0"));
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    for _ in 0..(3 * steps.len() as u32 + 10) {
        ex.tick();
    }
    seen.lock().unwrap().clone().expect("a global map")
}

/// Measurements fused into the global cell at (x, y).
fn count_at(map: &ElevationMap, x: f64, y: f64) -> u32 {
    let (i, j) = map.geometry.cell(x, y).expect("on the map");
    map.count[map.geometry.index(i, j)]
}

#[test]
fn a_relocalized_pose_estimate_starts_the_map_again() {
    let here = Step { centre: [0.0, 0.0], relocalizations: 0, age_s: 0.0 };
    let ahead = Step { centre: [3.0, 0.0], relocalizations: 0, age_s: 0.0 };
    let both = fused(&[here, ahead]);
    assert!(count_at(&both, 0.0, 0.0) > 0 && count_at(&both, 3.0, 0.0) > 0);
    // Relocalized between the two: what was mapped before is displaced, and forgotten.
    let moved = fused(&[here, Step { relocalizations: 1, ..ahead }]);
    assert_eq!(count_at(&moved, 0.0, 0.0), 0);
    assert!(count_at(&moved, 3.0, 0.0) > 0);
    // A local map of images captured before the relocalization (placed with the estimate before
    // the move) does not start the new map; the next one does.
    let stale = Step { centre: [0.0, 2.0], relocalizations: 1, age_s: 0.2 };
    let late = fused(&[here, stale, Step { relocalizations: 1, ..ahead }]);
    assert_eq!(count_at(&late, 0.0, 2.0), 0);
    assert!(count_at(&late, 3.0, 0.0) > 0);
}
