//! Tracks (where the rover was, by the truth and by each pose estimate) drawn in both files: a
//! Rerun line strip and a Foxglove scene entity on a topic of its own, redrawn whole at the first
//! points, then every fifth, or every twentieth of its length once that is more (so a long track
//! costs the files a size linear in its length, not quadratic), and once more at the end of the run.

use super::mcap_writer::Mcap;
use super::rerun_view::draw_track;
use super::scene;
use anyhow::Result;
use framework::Time;

/// One track and where it is drawn.
pub(super) struct Track {
    points: Vec<[f32; 3]>,
    /// Rerun entity.
    entity: String,
    /// MCAP topic and the entity's id there.
    topic: String,
    id: String,
    frame: String,
    colour: [u8; 3],
    /// Points drawn so far.
    drawn: usize,
}

impl Track {
    pub(super) fn new(entity: String, topic: String, id: String, frame: &str, colour: [u8; 3]) -> Self {
        Track { points: Vec::new(), entity, topic, id, frame: frame.to_string(), colour, drawn: 0 }
    }

    /// The newest point.
    pub(super) fn last(&self) -> Option<&[f32; 3]> {
        self.points.last()
    }

    /// Adds a point 5 cm above `p` and redraws the track when it is due.
    pub(super) fn push(
        &mut self,
        p: [f64; 3],
        stamp: Time,
        rec: Option<&rerun::RecordingStream>,
        mcap: Option<&mut Mcap>,
    ) -> Result<()> {
        self.points.push([p[0] as f32, p[1] as f32, p[2] as f32 + 0.05]);
        let n = self.points.len();
        if n < 5 || n - self.drawn >= (n / 20).max(5) { self.draw(stamp, rec, mcap) } else { Ok(()) }
    }

    /// Draws the whole track if points were added since it was last drawn.
    pub(super) fn flush(
        &mut self,
        stamp: Time,
        rec: Option<&rerun::RecordingStream>,
        mcap: Option<&mut Mcap>,
    ) -> Result<()> {
        if self.drawn < self.points.len() { self.draw(stamp, rec, mcap) } else { Ok(()) }
    }

    fn draw(
        &mut self,
        stamp: Time,
        rec: Option<&rerun::RecordingStream>,
        mcap: Option<&mut Mcap>,
    ) -> Result<()> {
        self.drawn = self.points.len();
        if self.points.len() < 2 {
            return Ok(());
        }
        if let Some(rec) = rec {
            draw_track(rec, &self.entity, &self.points, self.colour)?;
        }
        if let Some(m) = mcap {
            scene::track(m, &self.topic, &self.id, &self.frame, stamp, &self.points, self.colour)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_track_is_redrawn_every_fifth_point_then_every_twentieth_of_its_length_and_whole_at_the_end() {
        let mut t = Track::new("e".into(), "/t".into(), "id".into(), "world", [0, 0, 0]);
        let mut drawn_at = Vec::new();
        let n = 4000;
        for i in 0..n {
            t.push([i as f64, 0.0, 0.0], Time::ZERO, None, None).unwrap();
            if t.drawn == t.points.len() {
                drawn_at.push(t.points.len());
            }
        }
        assert_eq!(drawn_at[..6], [1, 2, 3, 4, 9, 14]);
        // Every fifth point up to 100 points, then gaps of 5 % of the length: the points written
        // in all redraws stay within a constant factor of the track's length (about 20 + 1/0.05
        // times it), where every fifth point would write n^2 / 10 (1.6 M points here).
        let written: usize = drawn_at.iter().sum();
        assert!(written < 25 * n, "{written} points written for a track of {n}");
        assert!(
            drawn_at.windows(2).all(|w| w[1] - w[0] <= (w[1] / 20).max(5)),
            "no gap over 5 % of the track"
        );
        t.flush(Time::ZERO, None, None).unwrap();
        assert_eq!(t.drawn, n, "the end of the run draws what came after the last redraw");
        assert_eq!(t.last(), Some(&[(n - 1) as f32, 0.0, 0.05]));
    }
}
