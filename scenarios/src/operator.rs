//! The scripted operator: the person at the ground station who, as in the canister mission of
//! seed 000, marks the target region in the first tracking-camera image of the plan (captured
//! after the settle period, when the rover stands and the exposure has adjusted). A person sees the canister
//! in the image; the script finds it from ground truth (the canister's true pose and the camera as
//! built, at the image's capture time) — the only use of ground truth on the GNC side, marked as
//! operator input: the selection is published as `operator/target_selection` with
//! `source = "operator"`. Like a person, the script marks only what the image shows: a canister
//! behind a rock, the rover's own arm or the horizon, or out of the frame, is reported as not seen.
//!
//! Images arrive after the camera's latency; the script keeps what the scene looked like at each of
//! its ticks and judges an image by the scene at its capture time.

use framework::data::{StereoImages, TargetSelection};
use framework::prelude::*;
use nalgebra::Point3;
use std::collections::VecDeque;
use twin::belief::CameraTruth;
use twin::devices::SharedTwin;

/// Module name.
pub const NAME: &str = "operator";

/// The scripted operator.
pub struct Operator {
    twin: SharedTwin,
    camera: String,
    truth: CameraTruth,
    image: Option<Reader<StereoImages>>,
    out: Option<Writer<TargetSelection>>,
    done: bool,
    /// Images captured before this are not looked at (the rover settles and the cameras adjust
    /// their exposure while it stands still before the plan).
    from: Time,
    /// What the scene showed at each recent tick: the canister's region, or why it was not seen.
    seen: VecDeque<(Time, Result<[f64; 4], String>)>,
}

/// Share of the canister's sample points that must be in view for the operator to mark it.
const MIN_VISIBLE: f64 = 0.5;

impl Operator {
    /// An operator who looks at the left image of stereo camera `camera` (as built: `truth`).
    /// The first image it looks at is the first captured at or after `from`.
    pub fn new(twin: SharedTwin, camera: &str, truth: CameraTruth, from: Time) -> Self {
        Operator {
            twin,
            camera: camera.to_string(),
            truth,
            image: None,
            out: None,
            done: false,
            from,
            seen: VecDeque::new(),
        }
    }

    /// The canister's image region now, if enough of it is in view; else why not.
    fn select(&self) -> Result<[f64; 4], String> {
        let t = self.twin.lock();
        let can = t.canister_truth().ok_or("there is no canister")?;
        let cam = t.link_pose(&self.truth.model.frame).ok_or("the camera has no pose")? * self.truth.offset;
        // The canister body's corners (0.1 x 0.1 x 0.15 m box plus handle, canister frame) for the
        // region; its faces' and handle's centres as well for what is in view.
        let mut corners = Vec::new();
        for x in [-0.05, 0.05] {
            for y in [-0.05, 0.05] {
                for z in [0.0, 0.2] {
                    corners.push(Point3::new(x, y, z));
                }
            }
        }
        let to_cam = cam.inverse() * can;
        let uv: Vec<_> = corners.iter().filter_map(|p| self.truth.model.project(&(to_cam * p))).collect();
        if uv.len() < corners.len() {
            return Err("the canister is behind the camera".into());
        }
        let (w, h) = (self.truth.model.pinhole.width as f64, self.truth.model.pinhole.height as f64);
        let u0 = uv.iter().map(|p| p.x).fold(f64::INFINITY, f64::min).max(0.0);
        let u1 = uv.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max).min(w);
        let v0 = uv.iter().map(|p| p.y).fold(f64::INFINITY, f64::min).max(0.0);
        let v1 = uv.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max).min(h);
        if !(u1 - u0 >= 2.0 && v1 - v0 >= 2.0) {
            return Err("the canister is outside the image".into());
        }
        // What faces the camera: points just outside the canister's surface, seen if nothing else
        // (terrain, a rock, an object, the rover) is in the way.
        let eye = Point3::from(cam.translation.vector);
        let samples = [
            Point3::new(0.0, 0.0, 0.1975),
            Point3::new(0.0, 0.0, 0.151),
            Point3::new(0.051, 0.0, 0.075),
            Point3::new(-0.051, 0.0, 0.075),
            Point3::new(0.0, 0.051, 0.075),
            Point3::new(0.0, -0.051, 0.075),
            Point3::new(0.051, 0.051, 0.02),
            Point3::new(-0.051, -0.051, 0.02),
        ];
        let facing: Vec<Point3<f64>> = samples
            .iter()
            .map(|p| can * p)
            .filter(|p| {
                let outward = (p - can.translation.vector).coords
                    - can.rotation * nalgebra::Vector3::new(0.0, 0.0, 0.075);
                outward.dot(&(eye - p)) > 0.0
            })
            .collect();
        // In view: inside the image (projected within the field of view the lens covers) and not
        // hidden by anything.
        let in_image = |p: &Point3<f64>| {
            let c = cam.inverse() * p;
            let (hfov, vfov) = self.truth.model.fov();
            c.z > 0.0
                && (c.x / c.z).atan().abs() < 0.5 * hfov
                && (c.y / c.z).atan().abs() < 0.5 * vfov
                && self.truth.model.project(&c).is_some_and(|uv| self.truth.model.contains(&uv))
        };
        let visible = facing.iter().filter(|p| in_image(p) && t.line_of_sight(&eye, p)).count();
        if (visible as f64) < MIN_VISIBLE * facing.len() as f64 {
            return Err(format!(
                "the canister is hidden: {visible} of the {} points facing the camera are in view",
                facing.len()
            ));
        }
        Ok([u0, v0, u1, v1])
    }
}

impl Module for Operator {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::External;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.image = Some(d.reads(&format!("cameras/{}", self.camera)));
        self.out = Some(d.writes("operator/target_selection"));
        d.state("watching", |m, ctx| {
            if m.done {
                return Ok(());
            }
            // What the scene shows now, for the images captured now (they arrive later).
            let now = ctx.now();
            let seen = m.select();
            m.seen.push_back((now, seen));
            while m.seen.front().is_some_and(|(t, _)| now - *t > Duration::from_secs(5)) {
                m.seen.pop_front();
            }
            let Some(img) = m.image.as_ref().and_then(|r| ctx.read(r)) else { return Ok(()) };
            if img.value.left.stamp < m.from {
                return Ok(());
            }
            // The first image decides: the operator marks the target there, or reports it unseen.
            m.done = true;
            let stamp = img.value.left.stamp;
            let at_capture =
                m.seen.iter().rev().find(|(t, _)| *t <= stamp).map(|(_, s)| s.clone()).unwrap_or_else(|| {
                    Err("the operator has no view of the scene at the image's time".into())
                });
            match at_capture {
                Ok(bbox) => {
                    let sel = TargetSelection {
                        target: "canister".into(),
                        camera: m.camera.clone(),
                        frame: img.value.left.frame.clone(),
                        image_stamp: stamp,
                        bbox,
                        source: "operator".into(),
                    };
                    ctx.note(format!(
                        "operator input: canister marked at {bbox:?} in the first {} image",
                        m.camera
                    ));
                    ctx.write(m.out.as_ref().expect("declared"), sel);
                }
                Err(why) => ctx.note(format!(
                    "operator input: no canister marked in the first {} image: {why}",
                    m.camera
                )),
            }
            Ok(())
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use twin::{Fidelity, StartPose, Twin};

    /// A rover at the origin looking east along the ground at a canister 4 m ahead, with a rock of
    /// height `rock` (0: none) half-way.
    fn operator(rock: f64) -> Operator {
        let text = "name = \"t\"\n[terrain]\nsize_m = [30.0, 30.0]\nresolution_m = 0.5\n\
                    [[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [4.0, 0.0]\n";
        let mut w = worlds::World::from_str(text, "<t>", std::path::Path::new("."), None).unwrap();
        if rock > 0.0 {
            let points = [(-0.4, -0.4), (0.4, -0.4), (0.4, 0.4), (-0.4, 0.4)]
                .iter()
                .flat_map(|(x, y)| [Point3::new(*x, *y, 0.0), Point3::new(*x, *y, rock)])
                .collect();
            w.rocks.push(worlds::Rock {
                position: Point3::new(2.5, 0.0, 0.0),
                yaw: 0.0,
                diameter: 0.8,
                height: rock,
                points,
            });
        }
        let mut t =
            Twin::with_defaults(w, StartPose { x: 0.0, y: 0.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
        // Tilt the head down towards the canister.
        let id = t.start_move("ptu", &[0.0, 0.35], 1.0).unwrap();
        t.run_until(Duration::from_secs(3), |t| t.move_status(id).is_over());
        let twin = twin::devices::share(t);
        let map =
            twin::devices::DryRunDeviceMap::new(twin.clone(), framework::resources::Resources::new(), 1);
        Operator::new(twin, "head_stereo", map.stereo_belief("head_stereo").unwrap().left, Time::ZERO)
    }

    #[test]
    fn the_operator_marks_a_visible_canister_and_refuses_a_hidden_one() {
        let bbox = operator(0.0).select().expect("in plain view");
        assert!(bbox[2] > bbox[0] + 5.0 && bbox[3] > bbox[1] + 5.0, "{bbox:?}");
        let why = operator(1.5).select().expect_err("behind a 1.5 m rock");
        assert!(why.contains("hidden"), "{why}");
    }
}
