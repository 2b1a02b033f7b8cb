//! PerceptionToF's local elevation map of rendered ToF frames of a known geometry (a 15-degree
//! slope and a box), through the HAL devices with their believed calibrations: the map matches the
//! geometry within the sensor's noise.

use framework::hal::{DeviceMap, TofCamera};
use framework::time::Duration;
use gnc::navigation::dem::{DemFilter, LocalDem};
use std::path::PathBuf;
use twin::{Fidelity, StartPose, Twin};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/e2e/data").join(name)
}

#[test]
fn the_local_dem_of_a_rendered_slope_and_box_matches_their_geometry() {
    let world = worlds::World::load(data("dem_world.toml")).unwrap();
    let twin =
        Twin::with_defaults(world, StartPose { x: 0.0, y: 0.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
    let shared = twin::devices::share(twin);
    let map = twin::devices::DryRunDeviceMap::new(shared.clone(), framework::resources::Resources::new(), 5);
    // Look down at the ground ahead and to the right, where the table stands.
    let id = shared.lock().start_move("ptu", &[-0.3, 0.55], 1.0).unwrap();
    shared.lock().run_until(Duration::from_secs(5), |t| t.move_status(id).is_over());
    let mut cams: Vec<Box<dyn TofCamera>> =
        ["tof_left", "tof_right"].iter().map(|n| map.tof_camera(n).unwrap()).collect();
    let mut frames = Vec::new();
    for _ in 0..200 {
        shared.lock().step();
        for (k, c) in cams.iter_mut().enumerate() {
            if let Some(f) = c.capture().unwrap() {
                frames.push((k, f));
            }
        }
        if frames.len() >= 4 {
            break;
        }
    }
    assert!(frames.len() >= 2, "ToF frames arrive");
    // The rover stands still: the cameras' true poses now are those at capture (the truth places
    // the frames; the software's own calibration projects the pixels).
    let t = shared.lock();
    let base = t.base_pose();
    let geometry = framework::data::GridGeometry::centred("map", [2.5, 0.0], 0.1, 60, 60);
    let mut dem = LocalDem::new(geometry);
    let filter = DemFilter::default();
    for (k, f) in &frames {
        let cal = cams[*k].calibration();
        let map_from_optical = t.link_pose(&cal.model.frame).unwrap();
        let base_from_optical = base.inverse() * map_from_optical;
        dem.add_depth_image(&f.depth, &cal.model, &map_from_optical, &base_from_optical, &[], &filter);
    }
    let m = dem.finish(filter.min_points);
    let world = t.world();
    let table = world.objects.iter().find(|o| o.name == "table").unwrap();
    let g = &m.geometry;
    let (mut ground_err, mut top_err) = (Vec::new(), Vec::new());
    for j in 0..g.height {
        for i in 0..g.width {
            let k = g.index(i, j);
            if m.count[k] < 5 {
                continue;
            }
            let c = g.centre(i, j);
            let (dx, dy) = (c[0] - table.position.x, c[1] - table.position.y);
            let h = f64::from(m.height[k]);
            if dx.abs() < 0.5 - 0.1 && dy.abs() < 0.3 - 0.1 {
                top_err.push(h - (table.position.z + 0.8));
            } else if dx.abs() > 0.5 + 0.15 || dy.abs() > 0.3 + 0.15 {
                ground_err.push(h - world.ground_height(c[0], c[1]));
            }
        }
    }
    let pct = |v: &mut Vec<f64>, p: f64| {
        v.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
        v[((v.len() - 1) as f64 * p) as usize].abs()
    };
    assert!(
        ground_err.len() > 300 && top_err.len() >= 6,
        "{} ground cells, {} table cells",
        ground_err.len(),
        top_err.len()
    );
    // The ToF's range noise is 1 % of the range (2-4 cm per point here); cell means average many.
    let (g50, g95) = (pct(&mut ground_err, 0.5), pct(&mut ground_err, 0.95));
    let t95 = pct(&mut top_err, 0.95);
    eprintln!(
        "slope: median |error| {g50:.3} m, 95th {g95:.3} m over {} cells; table top 95th {t95:.3} m over {} cells",
        ground_err.len(),
        top_err.len()
    );
    assert!(g50 < 0.02 && g95 < 0.05, "slope errors: median {g50}, 95th {g95}");
    assert!(t95 < 0.05, "table top errors: 95th {t95}");
    // The slope of the map: a plane through the ground cells falls 15 degrees to the east.
    let mut pts = Vec::new();
    for j in 0..g.height {
        for i in 0..g.width {
            let k = g.index(i, j);
            let c = g.centre(i, j);
            let (dx, dy) = (c[0] - table.position.x, c[1] - table.position.y);
            if m.count[k] >= 5 && (dx.abs() > 0.8 || dy.abs() > 0.6) {
                pts.push((c[0], c[1], f64::from(m.height[k])));
            }
        }
    }
    let a = nalgebra::DMatrix::from_fn(pts.len(), 3, |r, c| [pts[r].0, pts[r].1, 1.0][c]);
    let b = nalgebra::DVector::from_fn(pts.len(), |r, _| pts[r].2);
    let x = a.clone().svd(true, true).solve(&b, 1e-12).unwrap();
    let slope = x[0].hypot(x[1]).atan().to_degrees();
    assert!((slope - 15.0).abs() < 1.0, "fitted slope {slope} deg");
}
