//! The scripted operator: the person at the ground station who, as in the canister mission of
//! seed 000, marks the target region in the first tracking-camera image. A person sees the canister
//! in the image; the script finds it from ground truth (the canister's true pose and the camera's
//! true pose) — the only use of ground truth on the GNC side, marked as operator input: the
//! selection is published as `operator/target_selection` with `source = "operator"`.

use framework::data::{StereoImages, TargetSelection};
use framework::prelude::*;
use nalgebra::Point3;
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
}

impl Operator {
    /// An operator who looks at the left image of stereo camera `camera` (as built: `truth`).
    pub fn new(twin: SharedTwin, camera: &str, truth: CameraTruth) -> Self {
        Operator { twin, camera: camera.to_string(), truth, image: None, out: None, done: false }
    }

    /// The canister's image region, if enough of it is in view.
    fn select(&self) -> Option<[f64; 4]> {
        let t = self.twin.lock();
        let can = t.canister_truth()?;
        let cam = t.link_pose(&self.truth.model.frame)? * self.truth.offset;
        drop(t);
        // The canister body's corners (0.1 x 0.1 x 0.15 m box plus handle, canister frame).
        let mut pts = Vec::new();
        for x in [-0.05, 0.05] {
            for y in [-0.05, 0.05] {
                for z in [0.0, 0.2] {
                    pts.push(Point3::new(x, y, z));
                }
            }
        }
        let to_cam = cam.inverse() * can;
        let uv: Vec<_> = pts.iter().filter_map(|p| self.truth.model.project(&(to_cam * p))).collect();
        if uv.len() < pts.len() {
            return None; // partly behind the camera
        }
        let (w, h) = (self.truth.model.pinhole.width as f64, self.truth.model.pinhole.height as f64);
        let u0 = uv.iter().map(|p| p.x).fold(f64::INFINITY, f64::min).max(0.0);
        let u1 = uv.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max).min(w);
        let v0 = uv.iter().map(|p| p.y).fold(f64::INFINITY, f64::min).max(0.0);
        let v1 = uv.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max).min(h);
        (u1 - u0 >= 2.0 && v1 - v0 >= 2.0).then_some([u0, v0, u1, v1])
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
            let Some(img) = m.image.as_ref().and_then(|r| ctx.read(r)) else { return Ok(()) };
            // The first image decides: the operator marks the target there, or reports it unseen.
            m.done = true;
            match m.select() {
                Some(bbox) => {
                    let sel = TargetSelection {
                        target: "canister".into(),
                        camera: m.camera.clone(),
                        frame: img.value.left.frame.clone(),
                        image_stamp: img.stamp,
                        bbox,
                        source: "operator".into(),
                    };
                    ctx.note(format!(
                        "operator input: canister marked at {bbox:?} in the first {} image",
                        m.camera
                    ));
                    ctx.write(m.out.as_ref().expect("declared"), sel);
                }
                None => {
                    ctx.note(format!("operator input: the canister is not in the first {} image", m.camera))
                }
            }
            Ok(())
        });
    }
}
