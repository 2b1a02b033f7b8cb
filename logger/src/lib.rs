//! The run logger (seed 000, 7 and 8: the Logger external module): records a run into a Rerun
//! recording (`run.rrd`, for a person) and an MCAP file (`run.mcap`, for tools), at the rates of the
//! scenario's `[logging]` table.
//!
//! What it records:
//! - ground truth from the twin: every robot link, the canister, the terrain and rocks (once);
//! - blackboard slots whose type it knows (pose estimates, joint states, locomotion state), as soon
//!   as a module publishes them; other slots as plain JSON in the MCAP;
//! - framework events (lifecycle and FSM changes, watchdog isolations, notes), every message and
//!   acknowledgement, and scheduler statistics;
//! - errors over time (estimate vs truth) as plots, and the score at the end.
//!
//! Both files are valid whenever the run ends: [`RunLogger::finish`] writes the MCAP summary and the
//! Rerun footer; dropping the logger (an unwinding panic) does the same.
//!
//! Entity tree of the `.rrd` (timeline `sim_time`): `world/terrain`, `world/rocks`,
//! `world/truth/<link>`, `world/truth/canister`, `world/truth/track`, `world/estimate/base_link`,
//! `world/estimate/uncertainty`, `world/estimate/track`, `plots/...`, `modules/<name>`, `logs/...`,
//! `score`. MCAP topics and schemas are listed in `docs/logging.md`. The MCAP writer and its schemas
//! are in `mcap_writer`, the Rerun layout and helpers in `rerun_view`.

use anyhow::{Context, Result};
use framework::data::{LocomotionState, PoseEstimate, VisualOdometry};
use framework::system::Core;
use framework::{Duration, Time};
use nalgebra::Isometry3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod autonomy;
mod framework_log;
mod header;
mod images;
mod infractions;
mod json_schema;
mod known;
mod live;
mod maps;
mod mcap_writer;
mod rerun_view;
mod scene;
mod tracking;
mod tracks;
mod world;

pub use header::{
    CameraInfo, CriterionRow, GroundTruth, Infraction, LogFiles, LoggingSettings, PhaseRow, RunHeader,
    RunSummary,
};
use known::Known;
pub use live::LiveServer;
use mcap_writer::{Mcap, pose_json, stamp_json, transform_json};
use rerun_view::{blueprint, rr_transform};
use scene::Entity;

/// Colour of the true track, and of estimates' tracks that the header gives no colour.
const TRUTH_TRACK: [u8; 3] = [40, 200, 60];
/// See [`TRUTH_TRACK`].
const ESTIMATE_TRACK: [u8; 3] = [60, 140, 255];
/// Colour of locomotion's goal.
const GOAL: [u8; 3] = [255, 200, 0];

/// Simulated-time timeline of the recording.
pub const TIMELINE: &str = "sim_time";

/// What the run loop hands the logging thread: owned snapshots, cheap to take.
enum Item {
    Truth {
        now: Time,
        poses: Vec<(String, Isometry3<f64>)>,
        canister: Option<Isometry3<f64>>,
        base: Isometry3<f64>,
        collisions: [u64; 2],
    },
    Slots {
        now: Time,
        base: Isometry3<f64>,
        records: Vec<SlotRecord>,
    },
    Events {
        now: Time,
        events: Vec<framework::events::Event>,
        messages: Vec<(String, String, framework::message::Message)>,
    },
    Stats {
        now: Time,
        reports: Vec<framework::system::ModuleReport>,
    },
    Infractions {
        now: Time,
        list: Vec<Infraction>,
    },
    Finish {
        summary: Option<Box<RunSummary>>,
        reply: std::sync::mpsc::Sender<Result<LogFiles>>,
    },
}

/// A blackboard record, with its typed value when the logger knows the type.
struct SlotRecord {
    name: String,
    type_name: &'static str,
    json: Option<serde_json::Value>,
    known: Known,
}

/// The logging thread's side: owns the files and does all the encoding.
struct Writer {
    header: RunHeader,
    downsample: u32,
    mcap: Option<Mcap>,
    rrd: Option<rerun::RecordingStream>,
    rrd_path: PathBuf,
    mcap_path: PathBuf,
    truth_track: tracks::Track,
    /// Each pose estimate's track, by slot.
    est_track: BTreeMap<String, tracks::Track>,
    next_track: Time,
    last_stats: BTreeMap<String, (u64, i64)>,
    /// A moving target's velocity arrow is drawn (cleared once it is static again).
    target_arrow: bool,
    /// The stretch of the line of sight where an unlocated target of known size is, drawn.
    sight_shown: bool,
    /// The places ruled out for the target, as last drawn.
    excluded_shown: Vec<framework::data::ExcludedPlace>,
    /// Autonomy's faults logged so far.
    autonomy_faults_seen: usize,
    /// Infractions drawn so far (each its own entity).
    infractions_logged: usize,
    /// Locomotion's goal as last drawn in the MCAP's scene (position, manoeuvre).
    goal_shown: Option<([f64; 3], String)>,
    /// The canister's entity is in the MCAP's scene.
    canister_drawn: bool,
    /// The canister's visuals (from its description; empty: drawn as a box).
    canister_visuals: Vec<world::Visual>,
}

/// Records one run. The run loop only takes snapshots (link poses, new blackboard records, new
/// events) at the configured rates and hands them to a logging thread, which encodes and writes
/// them, so logging costs the simulation little wall time on a machine with a spare core.
pub struct RunLogger {
    settings: LoggingSettings,
    tx: Option<std::sync::mpsc::SyncSender<Item>>,
    thread: Option<std::thread::JoinHandle<()>>,
    failed: std::sync::Arc<parking_lot::Mutex<Option<String>>>,
    next_truth: Time,
    next_slots: Time,
    next_stats: Time,
    slot_seq: BTreeMap<String, u64>,
    /// Next time each image or map slot may be logged (`images_hz`, `maps_hz`).
    next_image: BTreeMap<String, Time>,
    events_seen: usize,
    /// The world, for the ground heights under goals and paths.
    world: std::sync::Arc<worlds::World>,
}

/// The entity (Rerun) and topic (MCAP, with a leading `/`) of camera `camera`'s image that
/// overlays are drawn on: a stereo pair's left image, a single camera's image.
pub fn image_entity(camera: &str, mono_cameras: &[String]) -> String {
    if mono_cameras.iter().any(|c| c == camera) {
        format!("sensors/{camera}/image")
    } else {
        format!("sensors/{camera}/left")
    }
}

fn period(hz: f64) -> Option<Duration> {
    (hz > 0.0).then(|| Duration::from_hz(hz))
}

impl RunLogger {
    /// Opens `out/run.rrd` and `out/run.mcap` (as `settings` ask) and starts the logging thread,
    /// which first logs what never changes: the terrain, the rocks, the robot's link geometry.
    /// With `live`, everything the MCAP gets is also streamed to it as it is written.
    pub fn create(
        out: &Path,
        header: RunHeader,
        settings: &LoggingSettings,
        live: Option<LiveServer>,
    ) -> Result<Self> {
        let rrd_path = out.join("run.rrd");
        let mcap_path = out.join("run.mcap");
        let rrd = if settings.rrd {
            let rec = rerun::RecordingStreamBuilder::new("rover-twin")
                .recording_name(header.name.clone())
                .with_blueprint(blueprint())
                .save(&rrd_path)
                .with_context(|| format!("creating {}", rrd_path.display()))?;
            rec.set_log_time_enabled(false);
            Some(rec)
        } else {
            None
        };
        let mcap = if settings.mcap || live.is_some() {
            Some(Mcap::create(settings.mcap.then_some(mcap_path.as_path()), live)?)
        } else {
            None
        };
        let world = header.world.clone();
        let mut w = Writer {
            header,
            downsample: settings.image_downsample.max(1),
            mcap,
            rrd,
            rrd_path,
            mcap_path,
            truth_track: tracks::Track::new(
                "world/truth/track".into(),
                "/scene/tracks/truth".into(),
                "track/truth".into(),
                "world",
                TRUTH_TRACK,
            ),
            est_track: BTreeMap::new(),
            next_track: Time::ZERO,
            last_stats: BTreeMap::new(),
            target_arrow: false,
            sight_shown: false,
            excluded_shown: Vec::new(),
            autonomy_faults_seen: 0,
            infractions_logged: 0,
            goal_shown: None,
            canister_drawn: false,
            canister_visuals: Vec::new(),
        };
        let failed = std::sync::Arc::new(parking_lot::Mutex::new(None));
        let fail = failed.clone();
        // Bounded: if encoding ever falls behind the simulation, the simulation waits.
        let (tx, rx) = std::sync::mpsc::sync_channel::<Item>(256);
        let thread = std::thread::Builder::new().name("run-logger".into()).spawn(move || {
            let record = |r: Result<()>| {
                if let Err(e) = r {
                    fail.lock().get_or_insert_with(|| format!("{e:#}"));
                }
            };
            record(w.statics());
            for item in rx {
                if let Item::Truth { now, .. }
                | Item::Slots { now, .. }
                | Item::Events { now, .. }
                | Item::Stats { now, .. }
                | Item::Infractions { now, .. } = &item
                {
                    w.set_time(*now);
                }
                match item {
                    Item::Truth { now, poses, canister, base, collisions } => {
                        record(w.truth(now, &poses, canister, base, collisions))
                    }
                    Item::Slots { now, base, records } => record(w.slots(now, base, records)),
                    Item::Events { now, events, messages } => record(w.events(now, events, messages)),
                    Item::Stats { now, reports } => record(w.stats(now, reports)),
                    Item::Infractions { now, list } => record(w.infractions(now, list)),
                    Item::Finish { summary, reply } => {
                        let _ = reply.send(w.finish(summary.as_deref()));
                        return;
                    }
                }
            }
            // The run loop went away without finishing (a panic): finalize what was written.
            let _ = w.finish(None);
        })?;
        Ok(RunLogger {
            settings: settings.clone(),
            tx: Some(tx),
            thread: Some(thread),
            failed,
            next_truth: Time::ZERO,
            next_slots: Time::ZERO,
            next_stats: Time::ZERO,
            slot_seq: BTreeMap::new(),
            next_image: BTreeMap::new(),
            events_seen: 0,
            world,
        })
    }

    fn send(&self, item: Item) -> Result<()> {
        if let Some(e) = self.failed.lock().as_ref() {
            anyhow::bail!("{e}");
        }
        self.tx
            .as_ref()
            .expect("open until finish")
            .send(item)
            .map_err(|_| anyhow::anyhow!("the logging thread stopped"))
    }

    /// Takes the snapshots due at `now` and hands them to the logging thread.
    pub fn tick(&mut self, now: Time, truth: &dyn GroundTruth, core: &Core) -> Result<()> {
        if let Some(p) = period(self.settings.truth_hz)
            && now >= self.next_truth
        {
            self.next_truth = now + p;
            self.send(Item::Truth {
                now,
                poses: truth.link_poses(),
                canister: truth.canister(),
                base: truth.base(),
                collisions: truth.collisions(),
            })?;
        }
        if let Some(p) = period(self.settings.slots_hz)
            && now >= self.next_slots
        {
            self.next_slots = now + p;
            let records = self.new_records(now, core);
            if !records.is_empty() {
                self.send(Item::Slots { now, base: truth.base(), records })?;
            }
        }
        if self.settings.events {
            let (events, count) = core.events.since(self.events_seen);
            self.events_seen = count;
            let messages: Vec<_> = core
                .post
                .take_trace()
                .into_iter()
                .map(|m| (core.post.name(m.sender).to_string(), core.post.name(m.recipient).to_string(), m))
                .collect();
            if !events.is_empty() || !messages.is_empty() {
                self.send(Item::Events { now, events, messages })?;
            }
        }
        if let Some(p) = period(self.settings.stats_hz)
            && now >= self.next_stats
        {
            self.next_stats = now + p;
            self.send(Item::Stats { now, reports: framework::system::module_reports(core) })?;
        }
        Ok(())
    }

    /// Blackboard records written since the last look.
    fn new_records(&mut self, now: Time, core: &Core) -> Vec<SlotRecord> {
        let mut out = Vec::new();
        for name in core.board.names() {
            let Some(slot) = core.board.slot(&name) else { continue };
            let seq = slot.seq();
            if seq == 0 || self.slot_seq.get(&name) == Some(&seq) {
                continue;
            }
            self.slot_seq.insert(name.clone(), seq);
            let known = known::classify(slot.as_any(), &self.world);
            if matches!(known, Known::Elevation(..) | Known::Navigation(..)) {
                // Maps: at their own rate, never as JSON (a global map is megabytes of it). One
                // skipped for the rate stays unseen, so the newest is logged when the rate allows.
                let Some(p) = period(self.settings.maps_hz) else { continue };
                if self.next_image.get(&name).is_some_and(|t| now < *t) {
                    self.slot_seq.remove(&name);
                    continue;
                }
                self.next_image.insert(name.clone(), now + p);
                out.push(SlotRecord { name, type_name: slot.type_name(), json: None, known });
                continue;
            }
            if matches!(known, Known::Stereo(_) | Known::Mono(_) | Known::Tof(_)) {
                // Images: at their own rate, never as JSON.
                let Some(p) = period(self.settings.images_hz) else { continue };
                if self.next_image.get(&name).is_some_and(|t| now < *t) {
                    continue;
                }
                self.next_image.insert(name.clone(), now + p);
                out.push(SlotRecord { name, type_name: slot.type_name(), json: None, known });
                continue;
            }
            out.push(SlotRecord { name, type_name: slot.type_name(), json: slot.to_json(), known });
        }
        out
    }

    /// Logs infractions as they happen (from the scorer: ground truth, never read by the GNC).
    pub fn infractions(&mut self, now: Time, list: Vec<Infraction>) -> Result<()> {
        self.send(Item::Infractions { now, list })
    }

    /// Logs how the run ended (if it got that far) and finalizes both files; returns where they are.
    pub fn finish(mut self, summary: Option<RunSummary>) -> Result<LogFiles> {
        let (reply, rx) = std::sync::mpsc::channel();
        let sent =
            self.tx.take().map(|tx| tx.send(Item::Finish { summary: summary.map(Box::new), reply }).is_ok());
        let files = match sent {
            Some(true) => rx.recv().map_err(|_| anyhow::anyhow!("the logging thread stopped"))?,
            _ => Err(anyhow::anyhow!("the logging thread stopped")),
        };
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        if let Some(e) = self.failed.lock().take() {
            anyhow::bail!("logging failed: {e}");
        }
        files
    }
}

impl Drop for RunLogger {
    /// Unwinding past the logger (a panic in the runner) still finalizes the files.
    fn drop(&mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Writer {
    /// Sets the recording's `sim_time` for what the thread logs next.
    fn set_time(&self, t: Time) {
        if let Some(rec) = &self.rrd {
            rec.set_time(TIMELINE, std::time::Duration::from_nanos(t.as_nanos().max(0) as u64));
        }
    }

    fn truth(
        &mut self,
        now: Time,
        poses: &[(String, Isometry3<f64>)],
        canister: Option<Isometry3<f64>>,
        b: Isometry3<f64>,
        [collisions, self_collisions]: [u64; 2],
    ) -> Result<()> {
        if let Some(rec) = &self.rrd {
            for (name, pose) in poses {
                rec.log(format!("world/truth/{name}"), &rr_transform(pose))?;
            }
            if let Some(c) = &canister {
                rec.log("world/truth/canister", &rr_transform(c))?;
            }
            let tilt = framework::angle::tilt_deg(&b);
            rec.log("plots/motion/tilt_deg", &rerun::Scalars::single(tilt))?;
            rec.log("plots/motion/collisions", &rerun::Scalars::single(collisions as f64))?;
            rec.log("plots/motion/self_collisions", &rerun::Scalars::single(self_collisions as f64))?;
        }
        if now >= self.next_track {
            self.next_track = now + Duration::from_secs(1);
            let t = b.translation;
            self.truth_track.push([t.x, t.y, t.z], now, self.rrd.as_ref(), self.mcap.as_mut())?;
        }
        if let Some(m) = &mut self.mcap {
            m.time(now);
            for (name, pose) in poses {
                m.foxglove("/tf", "foxglove.FrameTransform", now, &transform_json(now, "world", name, pose))?;
            }
            if let Some(c) = &canister {
                // The canister's frame, which its scene entity is locked to.
                m.foxglove(
                    "/tf",
                    "foxglove.FrameTransform",
                    now,
                    &transform_json(now, "world", "canister", c),
                )?;
                if !self.canister_drawn {
                    self.canister_drawn = true;
                    m.latching = true;
                    let e = world::canister_entity(&self.canister_visuals, now);
                    scene::update(m, "/scene/canister", now, vec![e], &[])?;
                    m.latching = false;
                }
                m.foxglove(
                    "/truth/canister",
                    "foxglove.PoseInFrame",
                    now,
                    &serde_json::json!({ "timestamp": stamp_json(now), "frame_id": "world", "pose": pose_json(c) }),
                )?;
            }
        }
        Ok(())
    }

    fn slots(&mut self, now: Time, base: Isometry3<f64>, records: Vec<SlotRecord>) -> Result<()> {
        for r in records {
            match &r.known {
                Known::Pose(stamp, e) => self.pose_estimate(&r.name, *stamp, e, &base)?,
                Known::Joints(j) => {
                    if let Some(rec) = &self.rrd {
                        for s in &j.joints {
                            rec.log(
                                format!("plots/joints/{}/{}", j.group, s.name),
                                &rerun::Scalars::single(s.position),
                            )?;
                        }
                    }
                }
                Known::Locomotion(l, goal_z) => {
                    if let Some(rec) = &self.rrd {
                        rec.log("plots/motion/commanded_speed_m_s", &rerun::Scalars::single(l.command.v))?;
                        rec.log(
                            "plots/motion/commanded_yaw_rate_rad_s",
                            &rerun::Scalars::single(l.command.omega),
                        )?;
                        if let (Some([x, y]), Some(z)) = (l.goal, goal_z) {
                            rec.log(
                                "world/estimate/goal",
                                &rerun::Points3D::new([[x as f32, y as f32, *z as f32 + 0.1]])
                                    .with_radii([0.12_f32])
                                    .with_colors([GOAL])
                                    .with_labels([l.mode.clone()]),
                            )?;
                        }
                    }
                    self.goal(now, l, *goal_z)?;
                }
                Known::Stereo(img) => {
                    let name = r.name.trim_start_matches("cameras/").to_string();
                    self.grey(&format!("sensors/{name}/left"), &img.value.left)?;
                    self.grey(&format!("sensors/{name}/right"), &img.value.right)?;
                }
                Known::Mono(img) => {
                    let name = r.name.trim_start_matches("cameras/");
                    self.grey(&image_entity(name, &self.header.mono_cameras), &img.value)?;
                }
                Known::Tof(f) => {
                    let name = r.name.trim_start_matches("cameras/").to_string();
                    self.tof(&name, &f.value)?;
                }
                Known::Target(t) => {
                    if let Some(rec) = &self.rrd {
                        // Drawn over the (downsampled) left image it was selected in.
                        let k = self.downsample as f32;
                        let [u0, v0, u1, v1] = t.bbox.map(|x| x as f32 / k);
                        rec.log(
                            format!("sensors/{}/left/target", t.camera),
                            &rerun::Boxes2D::from_mins_and_sizes([[u0, v0]], [[u1 - u0, v1 - v0]])
                                .with_labels([format!("{} ({})", t.target, t.source)])
                                .with_colors([[255u8, 200, 0]]),
                        )?;
                    }
                }
                Known::Elevation(stamp, m) => {
                    maps::elevation(self.rrd.as_ref(), self.mcap.as_mut(), &r.name, *stamp, &m.value)?
                }
                Known::Navigation(stamp, m) => {
                    maps::navigation(self.rrd.as_ref(), self.mcap.as_mut(), &r.name, *stamp, &m.value)?
                }
                Known::Path(stamp, p, z) => {
                    maps::path(self.rrd.as_ref(), self.mcap.as_mut(), &r.name, *stamp, p, z)?
                }
                Known::Visual(v) => self.visual_odometry(&r.name, &v.value)?,
                Known::Markers(m) => self.markers(&m.value)?,
                Known::Objects(o) => self.objects(&o.value)?,
                Known::Track(t) => self.target(&t.value)?,
                Known::Manipulation(m) => self.manipulation(m.stamp, &m.value)?,
                Known::Autonomy(a) => self.autonomy(a.stamp, &a.value)?,
                Known::Other => {}
            }
            // Every slot, known type or not, goes to the MCAP as JSON with its stamp and sequence.
            if let (Some(m), Some(json)) = (&mut self.mcap, &r.json) {
                let type_name = r.type_name;
                m.write(
                    &format!("/slots/{}", r.name),
                    &format!("rover_twin.Slot<{type_name}>"),
                    || {
                        json_schema::inferred(
                            &format!("rover_twin.Slot<{type_name}>"),
                            "A blackboard record: the value with its clock stamp (ns) and sequence number",
                            json,
                        )
                    },
                    now,
                    json,
                )?;
            }
        }
        Ok(())
    }

    /// Locomotion's goal in the 3D scene (frame `map`), labelled with the manoeuvre; deleted when
    /// the manoeuvre has none. Published only when it changes.
    fn goal(&mut self, now: Time, l: &LocomotionState, z: Option<f64>) -> Result<()> {
        let Some(m) = &mut self.mcap else { return Ok(()) };
        let goal = l.goal.zip(z).map(|([x, y], z)| ([x, y, z + 0.1], l.mode.clone()));
        if goal == self.goal_shown {
            return Ok(());
        }
        match &goal {
            Some((p, mode)) => {
                let e = Entity::new("goal", "map", now)
                    .sphere(&Isometry3::translation(p[0], p[1], p[2]), [0.24; 3], GOAL, 0.9)
                    .text([p[0], p[1], p[2] + 0.3], mode, GOAL);
                scene::update(m, "/scene/goals", now, vec![e], &[])?;
            }
            None => scene::update(m, "/scene/goals", now, vec![], &["goal"])?,
        }
        self.goal_shown = goal;
        Ok(())
    }

    /// A visual odometry frame in Rerun: its counts and reprojection error as plots, the inliers as
    /// points in the rectified left image's coordinates, a loss as a text log. (The MCAP gets the
    /// frame as its slot's JSON record.)
    fn visual_odometry(&mut self, slot: &str, v: &VisualOdometry) -> Result<()> {
        let Some(rec) = &self.rrd else { return Ok(()) };
        rec.log(format!("plots/{slot}/inliers"), &rerun::Scalars::single(v.inliers as f64))?;
        rec.log(format!("plots/{slot}/tracked"), &rerun::Scalars::single(v.tracked as f64))?;
        if v.rmse_px.is_finite() {
            rec.log(format!("plots/{slot}/rmse_px"), &rerun::Scalars::single(v.rmse_px))?;
        }
        rec.log(
            format!("{slot}/inliers"),
            &rerun::Points2D::new(v.inlier_pixels.iter().map(|p| [p[0], p[1]])).with_radii([2.0_f32]),
        )?;
        if let Some(why) = &v.reason {
            rec.log(
                format!("{slot}/events"),
                &rerun::TextLog::new(format!("lost: {why}")).with_level(rerun::TextLogLevel::WARN),
            )?;
        }
        Ok(())
    }

    fn pose_estimate(
        &mut self,
        slot: &str,
        stamp: Time,
        e: &PoseEstimate,
        truth: &Isometry3<f64>,
    ) -> Result<()> {
        let err =
            (e.pose.translation.x - truth.translation.x).hypot(e.pose.translation.y - truth.translation.y);
        let sig = e.position_sigma();
        if let Some(rec) = &self.rrd {
            let base = format!("world/estimate/{}", slot.replace('/', "_"));
            rec.log(base.as_str(), &rr_transform(&e.pose))?;
            rec.log(
                format!("{base}/uncertainty"),
                &rerun::Ellipsoids3D::from_half_sizes([[3.0 * sig.x as f32, 3.0 * sig.y as f32, 0.05_f32]])
                    .with_colors([[60u8, 140, 255]]),
            )?;
            rec.log(
                format!("{base}/heading"),
                &rerun::Arrows3D::from_vectors([[0.5f32, 0.0, 0.0]]).with_colors([[60u8, 140, 255]]),
            )?;
            rec.log(format!("plots/errors/{slot}/position_error_m"), &rerun::Scalars::single(err))?;
            rec.log(
                format!("plots/errors/{slot}/sigma_3_m"),
                &rerun::Scalars::single(3.0 * sig.x.hypot(sig.y)),
            )?;
            let yaw_err = framework::angle::wrap(e.yaw() - truth.rotation.euler_angles().2);
            rec.log(
                format!("plots/errors/{slot}/yaw_error_deg"),
                &rerun::Scalars::single(yaw_err.to_degrees()),
            )?;
        }
        let p = e.pose.translation;
        // Each source its own colour: the fused estimate blue, the wheels orange, vision green.
        let colour =
            self.header.estimate_colours.iter().find(|(s, _)| s == slot).map_or(ESTIMATE_TRACK, |(_, c)| *c);
        let track = self.est_track.entry(slot.to_string()).or_insert_with(|| {
            let entity = format!("world/estimate/{}/track", slot.replace('/', "_"));
            let topic = format!("/scene/tracks/estimate/{slot}");
            tracks::Track::new(entity, topic, format!("track/estimate/{slot}"), &e.frame, colour)
        });
        if track
            .last()
            .is_none_or(|l| ((l[0] - p.x as f32).powi(2) + (l[1] - p.y as f32).powi(2)).sqrt() > 0.25)
        {
            track.push([p.x, p.y, p.z], stamp, self.rrd.as_ref(), self.mcap.as_mut())?;
        }
        if let Some(m) = &mut self.mcap {
            m.foxglove(
                &format!("/estimate/{slot}"),
                "foxglove.PoseInFrame",
                stamp,
                &serde_json::json!({ "timestamp": stamp_json(stamp), "frame_id": e.frame, "pose": pose_json(&e.pose) }),
            )?;
        }
        Ok(())
    }

    /// Logs how the run ended (if it got that far) and finalizes both files; returns where they are.
    fn finish(&mut self, summary: Option<&RunSummary>) -> Result<LogFiles> {
        let mut files = LogFiles::default();
        // The tracks as they ended (what came after their last redraw).
        let end = Time::from_nanos(self.mcap.as_ref().map_or(0, |m| m.last_log_time()) as i64);
        self.truth_track.flush(end, self.rrd.as_ref(), self.mcap.as_mut())?;
        for t in self.est_track.values_mut() {
            t.flush(end, self.rrd.as_ref(), self.mcap.as_mut())?;
        }
        if let Some(s) = summary {
            let t = Time::from_secs_f64(s.sim_time_s);
            self.set_time(t);
            if let Some(rec) = &self.rrd {
                let mut md = format!(
                    "# {}: {}\n\n| phase | status | start (s) | end (s) | reason |\n|---|---|---|---|---|\n",
                    s.scenario, s.outcome
                );
                for p in &s.phases {
                    let f = |v: Option<f64>| v.map(|v| format!("{v:.1}")).unwrap_or_default();
                    md += &format!(
                        "| {} | {} | {} | {} | {} |\n",
                        p.name,
                        p.status,
                        f(p.start_s),
                        f(p.end_s),
                        p.reason.as_deref().unwrap_or("")
                    );
                }
                md += "\n| criterion | passed | value | limit |\n|---|---|---|---|\n";
                for c in &s.criteria {
                    md += &format!("| {} | {} | {} | {} |\n", c.name, c.passed, c.value, c.limit);
                }
                rec.log("score", &rerun::TextDocument::from_markdown(md))?;
            }
            if let Some(m) = &mut self.mcap {
                // What made the file, for a viewer's file info and for tools that sort logs.
                let mut pairs = s.metadata.clone();
                pairs.push(("version".into(), self.header.version.clone()));
                pairs.push(("git_commit".into(), self.header.git_commit.clone()));
                m.metadata("rover_twin", pairs)?;
                m.write(
                    "/score",
                    "rover_twin.Score",
                    || json_schema::inferred("rover_twin.Score", "The run's score (score.json)", &s.json),
                    t,
                    &s.json,
                )?;
            }
        }
        if let Some(m) = self.mcap.take()
            && m.finish()?
        {
            files.mcap = Some(self.mcap_path.display().to_string());
        }
        if let Some(rec) = self.rrd.take() {
            rec.flush_blocking().map_err(|e| anyhow::anyhow!("flushing {}: {e}", self.rrd_path.display()))?;
            drop(rec); // the last handle: the file sink writes its footer
            files.rrd = Some(self.rrd_path.display().to_string());
        }
        Ok(files)
    }
}
