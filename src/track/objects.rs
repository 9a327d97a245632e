//! Several objects in one stream (`[track.objects] enabled`): the associator's tracks, each with
//! the three filters a stream has when it tracks one object (`StreamTracker`), so that every track
//! keeps its fused z_I, identity changes, heading and pose smoothing. A track that ends keeps its
//! filters for the associator's memory window: when it is re-identified, it goes on from them.

use std::collections::HashMap;

use super::association::{Associated, Associator, Candidate, TrackEvent};
use super::settings::TrackSettings;
use super::stream::{step_dt, StreamTracker};

/// One track's filters and when they last saw their object.
struct Filters {
    tracker: StreamTracker,
    last_time: f64,
}

/// The tracks of one stream.
pub struct ObjectTracks {
    associator: Associator,
    filters: HashMap<u64, Filters>,
    settings: TrackSettings,
}

/// A candidate that belongs to a confirmed track in this frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedCandidate {
    /// Its index among the frame's candidates.
    pub candidate: usize,
    pub id: u64,
    /// Seconds since the track's previous frame (the nominal period after a gap of a second or
    /// more, or for a new track).
    pub dt: f32,
}

impl ObjectTracks {
    pub fn new(settings: &TrackSettings) -> Self {
        Self {
            associator: Associator::new(settings.objects.clone()),
            filters: HashMap::new(),
            settings: settings.clone(),
        }
    }

    /// Associates one frame's candidates at `time` (s): the candidates of confirmed tracks, in
    /// candidate order, and what happened to the tracks.
    pub fn associate(&mut self, time: f64, candidates: &[Candidate]) -> (Vec<TrackedCandidate>, Vec<TrackEvent>) {
        let Associated { ids, events } = self.associator.update(time, candidates);
        for event in &events {
            if let TrackEvent::Born { id } = event {
                // A new object: filters of its own (an id is never given twice).
                self.filters.insert(*id, self.fresh(time));
            }
        }
        let nominal_dt = 1.0 / self.settings.nominal_rate_hz;
        let tracked = ids
            .iter()
            .enumerate()
            .filter_map(|(candidate, id)| id.map(|id| (candidate, id)))
            .map(|(candidate, id)| {
                let fresh = self.fresh(time);
                let filters = self.filters.entry(id).or_insert(fresh);
                let dt = step_dt(Some((time - filters.last_time) as f32), nominal_dt);
                filters.last_time = time;
                TrackedCandidate { candidate, id, dt }
            })
            .collect();
        // Filters of tracks that can no longer come back.
        let keep_s = self.settings.objects.lost_s + self.settings.objects.memory_s;
        self.filters.retain(|_, f| time - f.last_time <= keep_s);
        (tracked, events)
    }

    /// The filters of track `id` (new ones if it has none).
    pub fn filters(&mut self, id: u64) -> &mut StreamTracker {
        let fresh = self.fresh(f64::NEG_INFINITY);
        &mut self.filters.entry(id).or_insert(fresh).tracker
    }

    /// Starts track `id`'s filters afresh (after a failure left them half updated).
    pub fn restart(&mut self, id: u64) {
        if let Some(filters) = self.filters.get_mut(&id) {
            filters.tracker = StreamTracker::new(&self.settings);
        }
    }

    fn fresh(&self, time: f64) -> Filters {
        Filters {
            tracker: StreamTracker::new(&self.settings),
            last_time: time,
        }
    }
}
