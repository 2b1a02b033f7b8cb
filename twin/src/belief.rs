//! The robot as built and the robot as believed (seed 004: the software believes a model; DESIGN.md,
//! "believed vs true").
//!
//! Each run draws, from its seed, how each real camera differs from its design
//! ([`crate::config::CameraBuildConfig`]: intrinsics, distortion, orientation on its mount) and how
//! the calibration the software is told differs from that truth
//! ([`crate::config::CalibrationConfig`]: camera intrinsics and extrinsics, the locomotor model's
//! wheel radius and track, the arm's joint zeros and link lengths). The twin simulates and renders
//! the truth; the Dry-Run device map hands the software the beliefs.
//!
//! Every quantity draws from its own random stream, named by what it is (`"camera:head_stereo"`),
//! so adding a camera or a key changes no other draw.

use crate::config::{CalibrationConfig, CameraBuildConfig};
use crate::render::sensors::{MonoConfig, StereoConfig, TofConfig, nominal_camera, tof_model};
use framework::camera::{CameraCalibration, CameraModel, StereoCalibration};
use framework::hal::LocomotorModel;
use framework::mechanism::{JointKind, MechanismModel};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;

/// A seeded stream of standard normal draws for the quantity `name`.
pub struct Draws(Pcg64Mcg);

impl Draws {
    /// The stream of `name` under `seed`.
    pub fn new(seed: u64, name: &str) -> Self {
        // FNV-1a: a name hash that no library version changes.
        let h = name
            .bytes()
            .fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3));
        Draws(Pcg64Mcg::seed_from_u64(framework::seed::mix64(seed ^ h)))
    }
    /// A normal draw with standard deviation `sigma`.
    pub fn normal(&mut self, sigma: f64) -> f64 {
        sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut self.0)
    }
    /// A vector of three independent normal draws.
    pub fn vector(&mut self, sigma: f64) -> Vector3<f64> {
        Vector3::new(self.normal(sigma), self.normal(sigma), self.normal(sigma))
    }
    /// A small rigid motion: rotation about each axis and translation along each, 1-sigma.
    pub fn motion(&mut self, rotation_rad: f64, translation_m: f64) -> Isometry3<f64> {
        let r = self.vector(rotation_rad);
        let t = self.vector(translation_m);
        Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r))
    }
    /// A uniform draw in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (rand::RngCore::next_u64(&mut self.0) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A camera as built: its true intrinsics and distortion, and how its optical frame sits relative
/// to the URDF's optical link (the twin renders from `link pose * offset`).
#[derive(Clone, Debug, PartialEq)]
pub struct CameraTruth {
    /// True intrinsics and distortion (`model.frame` is the URDF optical link).
    pub model: CameraModel,
    /// True optical frame in the URDF optical link's frame.
    pub offset: Isometry3<f64>,
}

/// A camera as built from its nominal model (the lens's distortion too when `lens`: the ToF
/// cameras are rendered as pinholes).
fn build(nominal: &CameraModel, b: &CameraBuildConfig, lens: bool, d: &mut Draws) -> CameraTruth {
    let mut model = nominal.clone();
    let p = &mut model.pinhole;
    let f = 1.0 + d.normal(b.focal_fraction);
    (p.fx, p.fy) = (p.fx * f * (1.0 + d.normal(b.focal_fraction * 0.1)), p.fy * f);
    (p.cx, p.cy) = (p.cx + d.normal(b.principal_point_px), p.cy + d.normal(b.principal_point_px));
    let k1 = d.normal(b.k1);
    if lens {
        model.distortion.k1 += k1;
    }
    let offset = d.motion(b.rotation_deg.to_radians(), 0.0);
    CameraTruth { model, offset }
}

/// What a calibration says of a camera's intrinsics, from the truth.
fn calibrate(truth: &CameraModel, c: &CalibrationConfig, d: &mut Draws) -> CameraModel {
    let mut m = truth.clone();
    let p = &mut m.pinhole;
    (p.fx, p.fy) =
        (p.fx * (1.0 + d.normal(c.camera_focal_fraction)), p.fy * (1.0 + d.normal(c.camera_focal_fraction)));
    (p.cx, p.cy) =
        (p.cx + d.normal(c.camera_principal_point_px), p.cy + d.normal(c.camera_principal_point_px));
    m.distortion.k1 += d.normal(c.camera_k1);
    m
}

/// The true pose of an optical link on the link it is mounted on (fixed joints only between them).
fn mount_pose(mech: &MechanismModel, optical: &str) -> Result<(String, Isometry3<f64>), String> {
    let mount = mech.mount_link(optical).map_err(|e| e.to_string())?.to_string();
    let q = vec![0.0; mech.dof_count()];
    let pose = mech.transform(&mount, optical, &q).map_err(|e| e.to_string())?;
    Ok((mount, pose))
}

/// A stereo pair as built and as calibrated.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoBelief {
    /// The left camera as built.
    pub left: CameraTruth,
    /// The right camera as built.
    pub right: CameraTruth,
    /// What the software is told.
    pub calibration: StereoCalibration,
}

impl StereoBelief {
    /// Draws the pair `name` of configuration `cfg` on the robot `mech` (the true mechanism).
    pub fn draw(
        name: &str,
        cfg: &StereoConfig,
        mech: &MechanismModel,
        build_cfg: &CameraBuildConfig,
        cal: &CalibrationConfig,
        seed: u64,
    ) -> Result<Self, String> {
        let mut d = Draws::new(seed, &format!("camera:{name}"));
        let left = build(&nominal_camera(cfg, &cfg.left_frame), build_cfg, true, &mut d);
        let right = build(&nominal_camera(cfg, &cfg.right_frame), build_cfg, true, &mut d);
        let (mount, mount_left) = mount_pose(mech, &cfg.left_frame)?;
        let (_, mount_right) = mount_pose(mech, &cfg.right_frame)?;
        let true_left = mount_left * left.offset;
        let true_right = mount_right * right.offset;
        let pair = d.motion(cal.stereo_rotation_deg.to_radians(), cal.stereo_translation_m);
        let mounting = d.motion(cal.camera_mount_rotation_deg.to_radians(), cal.camera_mount_translation_m);
        let calibration = StereoCalibration {
            left: CameraCalibration {
                model: calibrate(&left.model, cal, &mut d),
                mount,
                mount_from_optical: true_left * mounting,
            },
            right: calibrate(&right.model, cal, &mut d),
            left_from_right: true_left.inverse() * true_right * pair,
        };
        Ok(StereoBelief { left, right, calibration })
    }
}

/// A ToF camera as built and as calibrated.
#[derive(Clone, Debug, PartialEq)]
pub struct TofBelief {
    /// The camera as built.
    pub truth: CameraTruth,
    /// What the software is told.
    pub calibration: CameraCalibration,
}

impl TofBelief {
    /// Draws ToF camera `name` on optical link `frame`.
    pub fn draw(
        name: &str,
        frame: &str,
        cfg: &TofConfig,
        mech: &MechanismModel,
        build_cfg: &CameraBuildConfig,
        cal: &CalibrationConfig,
        seed: u64,
    ) -> Result<Self, String> {
        let (truth, calibration) = single(name, &tof_model(cfg, frame), false, mech, build_cfg, cal, seed)?;
        Ok(TofBelief { truth, calibration })
    }
}

/// A single camera (`nominal`, on the optical link `nominal.frame`) as built and as calibrated;
/// `lens`: the real lens's distortion differs from the design too.
fn single(
    name: &str,
    nominal: &CameraModel,
    lens: bool,
    mech: &MechanismModel,
    build_cfg: &CameraBuildConfig,
    cal: &CalibrationConfig,
    seed: u64,
) -> Result<(CameraTruth, CameraCalibration), String> {
    let mut d = Draws::new(seed, &format!("camera:{name}"));
    let truth = build(nominal, build_cfg, lens, &mut d);
    let (mount, mount_optical) = mount_pose(mech, &nominal.frame)?;
    let mounting = d.motion(cal.camera_mount_rotation_deg.to_radians(), cal.camera_mount_translation_m);
    let calibration = CameraCalibration {
        model: calibrate(&truth.model, cal, &mut d),
        mount,
        mount_from_optical: mount_optical * truth.offset * mounting,
    };
    Ok((truth, calibration))
}

/// A single passive camera (the wrist camera) as built and as calibrated.
#[derive(Clone, Debug, PartialEq)]
pub struct MonoBelief {
    /// The camera as built.
    pub truth: CameraTruth,
    /// What the software is told.
    pub calibration: CameraCalibration,
}

impl MonoBelief {
    /// Draws camera `name` of configuration `cfg` on the robot `mech` (the true mechanism).
    pub fn draw(
        name: &str,
        cfg: &MonoConfig,
        mech: &MechanismModel,
        build_cfg: &CameraBuildConfig,
        cal: &CalibrationConfig,
        seed: u64,
    ) -> Result<Self, String> {
        let nominal = nominal_camera(&cfg.as_stereo(), &cfg.frame);
        let (truth, calibration) = single(name, &nominal, true, mech, build_cfg, cal, seed)?;
        Ok(MonoBelief { truth, calibration })
    }
}

/// The locomotor model the software believes: the true one with the wheel radius and track as
/// calibrated.
pub fn believed_locomotor(truth: &LocomotorModel, cal: &CalibrationConfig, seed: u64) -> LocomotorModel {
    let mut d = Draws::new(seed, "locomotor");
    let (r, t) = (1.0 + d.normal(cal.wheel_radius_fraction), 1.0 + d.normal(cal.track_fraction));
    let mut m = truth.clone();
    m.wheel_radius *= r;
    m.track *= t;
    m.wheel_positions = m.wheel_positions.iter().map(|p| Point3::new(p.x, p.y * t, p.z)).collect();
    m
}

/// The mechanism model the software believes: the true one with each arm joint's zero and each arm
/// link's length as calibrated (`arm_joints`: the arm's joint names).
pub fn believed_mechanism(
    truth: &MechanismModel,
    arm_joints: &[&str],
    cal: &CalibrationConfig,
    seed: u64,
) -> Result<MechanismModel, String> {
    let mut m = truth.clone();
    for name in arm_joints {
        let mut d = Draws::new(seed, &format!("joint:{name}"));
        let j = truth.joint(name).map_err(|e| e.to_string())?;
        if j.kind == JointKind::Fixed {
            continue;
        }
        // A zero offset: the software's angle 0 is the joint's angle -delta, which is the same as
        // a model whose joint frame is turned by delta about the axis.
        let zero = UnitQuaternion::from_axis_angle(&j.axis, d.normal(cal.arm_joint_zero_deg.to_radians()));
        let mut origin = j.origin * Isometry3::from_parts(Translation3::identity(), zero);
        let t = origin.translation.vector;
        if t.norm() > 1e-6 {
            origin.translation.vector += t.normalize() * d.normal(cal.arm_link_length_m);
        }
        m.set_joint_origin(name, origin).map_err(|e| e.to_string())?;
    }
    Ok(m)
}
