//! `rover-twin snapshot`: what the rover's cameras see, as PNG files for people (the README's
//! pictures in `docs/images/` are made by `rover-twin snapshot --out docs/images`). The rover stands
//! at the canister mission's start on the Mars-like yard with its head looking at the ground ahead;
//! the images come through the Dry-Run devices (cameras as built, lens, photometric model), as the
//! software gets them: the head camera's left image, the localization camera's left image, and the
//! left ToF camera's depth (near bright, far dark, no return black).

use anyhow::{Context, Result, anyhow};
use framework::camera::{DepthImage, GreyImage};
use framework::hal::DeviceMap;
use framework::time::Duration;
use std::path::{Path, PathBuf};
use twin::{Fidelity, StartPose, Twin};

/// Where the rover stands and where its head looks.
const START: StartPose = StartPose { x: -12.0, y: -12.0, yaw: std::f64::consts::FRAC_PI_4 };
const HEAD: [f64; 2] = [0.0, 0.45];

/// Renders the three images into `out`; the files written.
pub fn run(world: &Path, out: &Path) -> Result<Vec<PathBuf>> {
    let mut w = worlds::World::load(world)?;
    // As the canister mission's runner does: no rock where the rover stands.
    w.keep_clear(START.x, START.y, crate::runner::START_CLEARANCE_M);
    let mut t = Twin::with_defaults(w, START, Fidelity::Kinematic)?;
    let id = t.start_move("ptu", &HEAD, 1.0).map_err(|e| anyhow!(e))?;
    t.run_until(Duration::from_secs(5), |t| t.move_status(id).is_over());
    let twin = twin::devices::share(t);
    let map = twin::devices::DryRunDeviceMap::new(twin.clone(), framework::resources::Resources::new(), 1);
    let mut head = map.stereo_camera("head_stereo")?;
    let mut loc = map.stereo_camera("loc_stereo")?;
    let mut tof = map.tof_camera("tof_left")?;
    let (mut h, mut l, mut d) = (None, None, None);
    // Poll every step until each camera has delivered a frame (after its latency); auto-exposure
    // settles over the first frames, so keep the fifth of each.
    let mut counts = [0usize; 3];
    for _ in 0..4000 {
        twin.lock().step();
        if let Some((left, _)) = head.capture()? {
            counts[0] += 1;
            h = Some(left);
        }
        if let Some((left, _)) = loc.capture()? {
            counts[1] += 1;
            l = Some(left);
        }
        if let Some(f) = tof.capture()? {
            counts[2] += 1;
            d = Some(f.depth);
        }
        if counts.iter().all(|c| *c >= 5) {
            break;
        }
    }
    let (Some(h), Some(l), Some(d)) = (h, l, d) else { return Err(anyhow!("a camera delivered no frame")) };
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let files = vec![out.join("head_left.png"), out.join("loc_left.png"), out.join("tof_depth.png")];
    write_grey(&files[0], &h)?;
    write_grey(&files[1], &l)?;
    write_depth(&files[2], &d, tof.range_limits())?;
    Ok(files)
}

fn write_grey(path: &Path, img: &GreyImage) -> Result<()> {
    image::GrayImage::from_raw(img.width, img.height, img.data.clone())
        .ok_or_else(|| anyhow!("image size"))?
        .save(path)
        .with_context(|| format!("writing {}", path.display()))
}

fn write_depth(path: &Path, img: &DepthImage, (near, far): (f64, f64)) -> Result<()> {
    let data = img
        .data
        .iter()
        .map(|z| {
            if z.is_finite() {
                (255.0 * (1.0 - (*z as f64 - near) / (far - near))).clamp(16.0, 255.0) as u8
            } else {
                0
            }
        })
        .collect();
    image::GrayImage::from_raw(img.width, img.height, data)
        .ok_or_else(|| anyhow!("image size"))?
        .save(path)
        .with_context(|| format!("writing {}", path.display()))
}
