//! Association: several objects in one stream's view, each with a track that persists while it is
//! visible and gets its id back when it returns (`[track.objects]`; off by default, when the node
//! tracks the largest cluster of each frame as one object).
//!
//! Frame by frame, candidates (one per cluster that could be an object: its centre in the gravity
//! frame and its z_I) are matched to tracks at the least total cost, found exactly (Hungarian
//! method). A pair's cost adds how far the candidate lies from the track's predicted position
//! (constant velocity) on the ground plane, in `gate_m`s (a partly hidden object's centre moves up
//! or down, its legs behind another, more than across), and how far its z_I lies from the track's fused z_I, as a
//! fraction of `shape_scale`; a pair beyond the gate (`gate_m` widened by `max_speed_mps` for the
//! time the track went unseen) cannot match. A cluster near two tracks with the points of both is
//! the two merged (`merge_ratio`): they coast through it. A candidate no track takes starts a
//! tentative track (unless it lies within `fragment_m` of a track's candidate: a piece of that
//! object, which a track unseen in the last update does not take either), confirmed (given an
//! id) after `birth_frames` frames in a row; a confirmed track unseen for `lost_s` (an
//! occlusion) ends and joins a gallery of ended tracks kept `memory_s`. A track confirmed while
//! an ended (or unseen) track's fused z_I lies within `reid_distance` of its own takes that id
//! back: the same animal, returned (one that comes back into view a part at a time may wait
//! `reid_wait_s` for its z_I to come within reach).
//!
//! The gallery is searched linearly: it holds the few tracks of one stream's last seconds, and
//! z_I's size is the bundle's, known only at run time (kiddo's trees fix it at compile time).

use serde::{Deserialize, Serialize};

/// `[track.objects]`: which clusters are candidates, and how candidates become tracks.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct AssociationSettings {
    /// Track every object in view (each cluster within the limits below), not just the largest.
    pub enabled: bool,
    /// At most this many candidates a frame (the largest clusters).
    pub max_objects: usize,
    /// A cluster larger than this (m) on any side is not a candidate (a wall, a table, the floor).
    pub max_extent_m: f32,
    /// Farthest a candidate may lie from a track's predicted position (m, on the ground plane) at
    /// no elapsed time ...
    pub gate_m: f32,
    /// ... plus this speed times the time since the track was last seen (m/s).
    pub max_speed_mps: f32,
    /// Weight of the z_I distance against the position's in a pair's cost.
    pub shape_weight: f32,
    /// The z_I distance (Euclidean, in z_I spreads: the bundle's `calibration.z_I_spread`) that
    /// costs as much as a whole gate.
    pub shape_scale: f32,

    /// Frames in a row a tentative track needs to be confirmed.
    pub birth_frames: usize,
    /// A confirmed track unseen this long (s) ends (shorter gaps are occlusions).
    pub lost_s: f64,
    /// How long (s) an ended track can be re-identified.
    pub memory_s: f64,
    /// Largest z_I distance (in z_I spreads) between a new track and an ended one for it to take
    /// the old id.
    pub reid_distance: f32,
    /// A new track whose z_I is not within `reid_distance` of an ended track's but within
    /// [`REID_WAIT_REACH`] times it (an object coming back into view, seen in part at first)
    /// waits up to this long (s) from its first frame for its fused z_I to come within reach
    /// before it takes a new id (0: it never waits).
    pub reid_wait_s: f64,
    /// A candidate near two confirmed tracks (within a gate more than either's: a merged cluster's
    /// centre lies between its objects) and with at least this many times the points either
    /// usually has is the two merged into one cluster (walking side by side, one behind the
    /// other): neither takes it, both coast on their motion until they part (0: off).
    pub merge_ratio: f32,
    /// A candidate no track takes within this distance (m, on the ground plane) of a confirmed
    /// track's candidate of the same frame is a piece of that object split from it (an arm, a
    /// head past an occluder), not a new one: it starts no track, nor does a track unseen in the
    /// last update take it (0: off).
    pub fragment_m: f32,
}

impl Default for AssociationSettings {
    fn default() -> Self {
        Self {
            enabled: false,
            max_objects: 4,
            max_extent_m: 2.5,
            gate_m: 0.4,
            max_speed_mps: 2.5,
            shape_weight: 1.0,
            shape_scale: 2.93,
            birth_frames: 3,
            lost_s: 1.0,
            memory_s: 10.0,
            reid_distance: 2.93,
            reid_wait_s: 0.5,
            merge_ratio: 1.4,
            fragment_m: 0.5,
        }
    }
}

impl AssociationSettings {
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("max_extent_m", self.max_extent_m as f64),
            ("gate_m", self.gate_m as f64),
            ("shape_scale", self.shape_scale as f64),
            ("lost_s", self.lost_s),
        ];
        for (name, value) in positive {
            if !(value > 0.0 && value.is_finite()) {
                return Err(format!("track.objects.{name} must be positive and finite, got {value}"));
            }
        }
        let non_negative = [
            ("max_speed_mps", self.max_speed_mps as f64),
            ("shape_weight", self.shape_weight as f64),
            ("memory_s", self.memory_s),
            ("reid_distance", self.reid_distance as f64),
            ("reid_wait_s", self.reid_wait_s),
            ("merge_ratio", self.merge_ratio as f64),
            ("fragment_m", self.fragment_m as f64),
        ];
        for (name, value) in non_negative {
            if !(value >= 0.0 && value.is_finite()) {
                return Err(format!("track.objects.{name} must be finite and >= 0, got {value}"));
            }
        }
        if self.max_objects == 0 {
            return Err("track.objects.max_objects must be at least 1".into());
        }
        if self.birth_frames == 0 {
            return Err("track.objects.birth_frames must be at least 1".into());
        }
        Ok(())
    }
}

/// One frame's possible object.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// Centre in the gravity frame (m).
    pub centre: [f32; 3],
    pub z_i: Vec<f32>,
    /// Its points (after filtering; 0: unknown, never taken for a merge).
    pub points: usize,
}

/// What happened to a track in a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TrackEvent {
    /// A new object, with a new id.
    Born { id: u64 },
    /// An object seen before took its id back after `away_s` unseen.
    Reidentified { id: u64, away_s: f64 },
    /// Unseen for `lost_s`: the track ended (its id may come back within `memory_s`).
    Ended { id: u64 },
}

/// One frame's association.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Associated {
    /// Per candidate, in order: the id of the confirmed track it belongs to (None: a tentative
    /// track's, not yet an object).
    pub ids: Vec<Option<u64>>,
    pub events: Vec<TrackEvent>,
}

#[derive(Debug, Clone)]
struct Track {
    /// Unique among this associator's tracks, tentative ones included.
    key: u64,
    id: Option<u64>,
    position: [f32; 3],
    velocity: [f32; 3],
    last_seen: f64,
    /// Frames in a row seen while tentative.
    hits: usize,
    z_i_sum: Vec<f32>,
    z_i_count: usize,
    /// Running mean of its candidates' points.
    points_mean: f32,
    /// Coasting last frame through a cluster merged with another track's object.
    merging: bool,
    /// Updates in a row it took no candidate in (0: seen in the last).
    misses: u32,
    /// When it was first seen (s).
    first_seen: f64,
}

impl Track {
    fn fused(&self) -> Vec<f32> {
        let n = self.z_i_count.max(1) as f32;
        self.z_i_sum.iter().map(|v| v / n).collect()
    }

    /// How far from its prediction a candidate may lie at `time` (m): `gate_m`, widened by
    /// `max_speed_mps` for the time it went unseen.
    fn gate(&self, s: &AssociationSettings, time: f64) -> f64 {
        s.gate_m as f64 + s.max_speed_mps as f64 * (time - self.last_seen).max(0.0)
    }

    fn predicted(&self, time: f64) -> [f32; 3] {
        let dt = (time - self.last_seen) as f32;
        std::array::from_fn(|a| self.position[a] + self.velocity[a] * dt)
    }
}

/// How far (in `reid_distance`s) an ended track's z_I may lie from a new track's for the new one to
/// wait for re-identification (`reid_wait_s`).
pub const REID_WAIT_REACH: f64 = 1.5;

/// A merged cluster stays merged while it has this many times the points of each of its tracks.
const MERGE_HOLD_RATIO: f32 = 1.1;

/// An ended track, kept for re-identification.
#[derive(Debug, Clone)]
struct Ended {
    id: u64,
    z_i: Vec<f32>,
    last_seen: f64,
}

/// The tracks of one stream.
#[derive(Debug, Clone)]
pub struct Associator {
    settings: AssociationSettings,
    tracks: Vec<Track>,
    gallery: Vec<Ended>,
    next_id: u64,
    next_key: u64,
}

/// Cost of a pair that cannot match.
const NO_MATCH: f64 = f64::INFINITY;
/// Added to a tentative track's costs, so that a confirmed track wins a tie.
const TENTATIVE_PENALTY: f64 = 0.05;

impl Associator {
    pub fn new(settings: AssociationSettings) -> Self {
        Self {
            settings,
            tracks: Vec::new(),
            gallery: Vec::new(),
            next_id: 1,
            next_key: 0,
        }
    }

    /// The confirmed tracks' ids, in no particular order.
    pub fn confirmed(&self) -> Vec<u64> {
        self.tracks.iter().filter_map(|t| t.id).collect()
    }

    /// Associates one frame's candidates at `time` (s, increasing).
    pub fn update(&mut self, time: f64, candidates: &[Candidate]) -> Associated {
        let s = &self.settings;
        let (merged, merging) = self.merged(time, candidates);
        self.tracks.iter_mut().zip(merging).for_each(|(t, m)| t.merging = m);
        let cost: Vec<Vec<f64>> = self
            .tracks
            .iter()
            .map(|track| {
                let predicted = track.predicted(time);
                let gate = track.gate(s, time);
                let fused = (track.z_i_count > 0).then(|| track.fused());
                candidates
                    .iter()
                    .enumerate()
                    .map(|(k, c)| {
                        let d = ground_distance(&predicted, &c.centre);
                        if d > gate || merged[k] {
                            return NO_MATCH;
                        }
                        let shape = fused
                            .as_ref()
                            .map_or(0.0, |f| distance(f, &c.z_i) / s.shape_scale as f64);
                        let penalty = if track.id.is_none() { TENTATIVE_PENALTY } else { 0.0 };
                        // Distance in base gates: a track unseen for a while may match farther,
                        // but never more cheaply than one seen a frame ago at the same distance.
                        d / s.gate_m as f64 + s.shape_weight as f64 * shape + penalty
                    })
                    .collect()
            })
            .collect();
        let pairs = self.without_pieces(assign(&cost), candidates);

        let mut result = Associated {
            ids: vec![None; candidates.len()],
            events: Vec::new(),
        };
        // Each candidate's track, by key (indices move as tracks end and merge).
        let mut key_of: Vec<Option<u64>> = vec![None; candidates.len()];
        let mut seen = vec![false; self.tracks.len()];
        for (t, c) in pairs {
            key_of[c] = Some(self.tracks[t].key);
            seen[t] = true;
            let candidate = &candidates[c];
            let track = &mut self.tracks[t];
            let dt = (time - track.last_seen) as f32;
            if dt > 0.0 {
                for a in 0..3 {
                    let observed = (candidate.centre[a] - track.position[a]) / dt;
                    track.velocity[a] = 0.5 * track.velocity[a] + 0.5 * observed;
                }
            }
            track.position = candidate.centre;
            track.last_seen = time;
            track.hits += 1;
            if track.z_i_sum.len() != candidate.z_i.len() {
                track.z_i_sum = vec![0.0; candidate.z_i.len()];
                track.z_i_count = 0;
            }
            track.z_i_sum.iter_mut().zip(&candidate.z_i).for_each(|(s, v)| *s += v);
            track.z_i_count += 1;
            track.points_mean = if track.points_mean > 0.0 {
                0.8 * track.points_mean + 0.2 * candidate.points as f32
            } else {
                candidate.points as f32
            };
        }
        for (track, seen) in self.tracks.iter_mut().zip(&seen) {
            track.misses = if *seen { 0 } else { track.misses.saturating_add(1) };
        }
        // Tentative tracks need frames in a row: one missed, they go.
        let mut index = 0;
        self.tracks.retain(|track| {
            let keep = seen[index] || track.id.is_some();
            index += 1;
            keep
        });
        // Confirmations (re-identified from the gallery or an unseen track, else new ids).
        let due: Vec<u64> = self
            .tracks
            .iter()
            .filter(|t| t.id.is_none() && t.last_seen == time && t.hits >= self.settings.birth_frames)
            .map(|t| t.key)
            .collect();
        for key in due {
            if let Some(event) = self.confirm(key, time) {
                result.events.push(event);
            }
        }
        // Ended: confirmed tracks unseen for lost_s.
        let (lost_s, mut ended) = (self.settings.lost_s, Vec::new());
        self.tracks.retain(|track| {
            let over = time - track.last_seen > lost_s;
            if over {
                if let Some(id) = track.id {
                    ended.push(Ended {
                        id,
                        z_i: track.fused(),
                        last_seen: track.last_seen,
                    });
                }
            }
            !over
        });
        for e in ended {
            result.events.push(TrackEvent::Ended { id: e.id });
            self.gallery.push(e);
        }
        let memory_s = self.settings.memory_s;
        self.gallery.retain(|e| time - e.last_seen <= memory_s);
        // New tentative tracks for what no track took, unless it is a piece of an object a
        // confirmed track took this frame.
        let taken: Vec<[f32; 3]> = self
            .tracks
            .iter()
            .filter(|t| t.id.is_some() && t.last_seen == time)
            .map(|t| t.position)
            .collect();
        let fragment_m = self.settings.fragment_m as f64;
        for (c, candidate) in candidates.iter().enumerate() {
            // On the ground plane: a piece may lie above the body (a head, a raised arm).
            let fragment = taken.iter().any(|p| ground_distance(p, &candidate.centre) < fragment_m);
            if key_of[c].is_none() && !merged[c] && !fragment {
                let key = self.next_key;
                self.next_key += 1;
                key_of[c] = Some(key);
                self.tracks.push(Track {
                    key,
                    id: None,
                    position: candidate.centre,
                    velocity: [0.0; 3],
                    last_seen: time,
                    hits: 1,
                    z_i_sum: candidate.z_i.clone(),
                    z_i_count: 1,
                    points_mean: candidate.points as f32,
                    merging: false,
                    misses: 0,
                    first_seen: time,
                });
                if self.settings.birth_frames <= 1 {
                    if let Some(event) = self.confirm(key, time) {
                        result.events.push(event);
                    }
                }
            }
        }
        for (id, key) in result.ids.iter_mut().zip(&key_of) {
            *id = self.tracks.iter().find(|t| Some(t.key) == *key).and_then(|t| t.id);
        }
        result
    }

    /// `pairs` (track, candidate) less those in which a track that went unseen takes a piece of
    /// an object another confirmed track, seen in the last update, takes in this one: a
    /// candidate within `fragment_m` of that one's on the ground plane (legs split from a body;
    /// the track coasting after its own object left would otherwise take them, and follow that
    /// object from then on).
    fn without_pieces(&self, pairs: Vec<(usize, usize)>, candidates: &[Candidate]) -> Vec<(usize, usize)> {
        let fragment_m = self.settings.fragment_m as f64;
        if fragment_m <= 0.0 {
            return pairs;
        }
        let held: Vec<usize> = pairs
            .iter()
            .filter(|&&(t, _)| self.tracks[t].id.is_some() && self.tracks[t].misses == 0)
            .map(|&(_, c)| c)
            .collect();
        pairs
            .into_iter()
            .filter(|&(t, c)| {
                let track = &self.tracks[t];
                track.misses == 0
                    || track.id.is_none()
                    || !held
                        .iter()
                        .any(|&h| h != c && ground_distance(&candidates[h].centre, &candidates[c].centre) < fragment_m)
            })
            .collect()
    }

    /// Per candidate, whether it is two confirmed tracks' objects merged into one cluster: within
    /// both their gates, with `merge_ratio` times the points either has had (once merged, with
    /// [`MERGE_HOLD_RATIO`] times: a cluster loses points as one object passes behind the other,
    /// and taking it then moves the track that does by half the objects' spacing). Per track,
    /// whether it coasts through such a cluster.
    fn merged(&self, time: f64, candidates: &[Candidate]) -> (Vec<bool>, Vec<bool>) {
        let s = &self.settings;
        let mut merging = vec![false; self.tracks.len()];
        let merged = candidates
            .iter()
            .map(|c| {
                if s.merge_ratio <= 0.0 || c.points == 0 {
                    return false;
                }
                let near: Vec<usize> = (0..self.tracks.len())
                    .filter(|&t| {
                        let t = &self.tracks[t];
                        let gate = t.gate(s, time);
                        // A merged cluster's centre lies between its objects: half their spacing
                        // from each, beyond one gate.
                        t.id.is_some()
                            && t.points_mean > 0.0
                            && ground_distance(&t.predicted(time), &c.centre) <= gate + s.gate_m as f64
                    })
                    .collect();
                let ratio = if near.iter().all(|&t| self.tracks[t].merging) {
                    MERGE_HOLD_RATIO.min(s.merge_ratio)
                } else {
                    s.merge_ratio
                };
                let is_merged = near.len() >= 2
                    && near
                        .iter()
                        .all(|&t| c.points as f32 >= ratio * self.tracks[t].points_mean);
                if is_merged {
                    near.iter().for_each(|&t| merging[t] = true);
                }
                is_merged
            })
            .collect();
        (merged, merging)
    }

    /// Gives the track of `key` an id: an ended or unseen track's whose fused z_I is nearest
    /// within `reid_distance`, else a new one.
    /// Confirms a tentative track: the id of the ended (or unseen) track whose fused z_I is
    /// nearest its own within `reid_distance`, else a new id; none yet while it waits for a z_I
    /// that might come within reach (`reid_wait_s`).
    fn confirm(&mut self, key: u64, time: f64) -> Option<TrackEvent> {
        let t = self
            .tracks
            .iter()
            .position(|t| t.key == key)
            .expect("a track to confirm exists");
        let z_i = self.tracks[t].fused();
        let limit = self.settings.reid_distance as f64;
        let from_gallery = self
            .gallery
            .iter()
            .enumerate()
            .map(|(g, e)| (distance(&e.z_i, &z_i), e.last_seen, Some(g), None));
        let unseen = self
            .tracks
            .iter()
            .enumerate()
            .filter(|(u, other)| *u != t && other.id.is_some() && other.last_seen < time)
            .map(|(u, other)| (distance(&other.fused(), &z_i), other.last_seen, None, Some(u)));
        let nearest = from_gallery.chain(unseen).min_by(|a, b| a.0.total_cmp(&b.0));
        let waiting = time - self.tracks[t].first_seen < self.settings.reid_wait_s;
        if nearest.is_some_and(|(d, ..)| d > limit && d <= REID_WAIT_REACH * limit) && waiting {
            return None;
        }
        Some(self.confirm_as(t, nearest.filter(|(d, ..)| *d <= limit), time))
    }

    /// Gives tentative track `t` the id of `best` (an ended track, by its gallery index, or an
    /// unseen one, by its index) or else a new one.
    fn confirm_as(
        &mut self,
        t: usize,
        best: Option<(f64, f64, Option<usize>, Option<usize>)>,
        time: f64,
    ) -> TrackEvent {
        match best {
            Some((_, last_seen, Some(g), _)) => {
                let ended = self.gallery.swap_remove(g);
                self.tracks[t].id = Some(ended.id);
                TrackEvent::Reidentified {
                    id: ended.id,
                    away_s: time - last_seen,
                }
            }
            Some((_, last_seen, None, Some(u))) => {
                // The unseen track was this object: its id moves here, the old track goes.
                let id = self.tracks[u].id.take();
                self.tracks[t].id = id;
                self.tracks.swap_remove(u);
                TrackEvent::Reidentified {
                    id: id.unwrap_or_default(),
                    away_s: time - last_seen,
                }
            }
            _ => {
                let id = self.next_id;
                self.next_id += 1;
                self.tracks[t].id = Some(id);
                TrackEvent::Born { id }
            }
        }
    }
}

/// Distance between two positions on the ground plane (x, y of the gravity frame).
fn ground_distance(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    distance(&a[..2], &b[..2])
}

fn distance(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The pairs (row, column) of least total cost, each row and column at most once, no pair of
/// infinite cost (the Hungarian method on the matrix padded square, infinite costs replaced by
/// one more than any finite total).
pub fn assign(cost: &[Vec<f64>]) -> Vec<(usize, usize)> {
    let rows = cost.len();
    let columns = cost.first().map_or(0, Vec::len);
    if rows == 0 || columns == 0 {
        return Vec::new();
    }
    let n = rows.max(columns);
    let finite: f64 = cost.iter().flatten().filter(|c| c.is_finite()).map(|c| c.abs()).sum();
    let big = finite + 1.0;
    let at = |i: usize, j: usize| -> f64 {
        match cost.get(i).and_then(|r| r.get(j)) {
            Some(c) if c.is_finite() => *c,
            Some(_) => big,
            None => 0.0, // padding
        }
    };
    // e-maxx's O(n^3) formulation, 1-based with a virtual row and column 0.
    let (mut u, mut v) = (vec![0.0; n + 1], vec![0.0; n + 1]);
    let (mut p, mut way) = (vec![0usize; n + 1], vec![0usize; n + 1]);
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0;
        let mut min_v = vec![f64::INFINITY; n + 1];
        let mut used = vec![false; n + 1];
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let (mut delta, mut j1) = (f64::INFINITY, 0);
            for j in 1..=n {
                if !used[j] {
                    let current = at(i0 - 1, j - 1) - u[i0] - v[j];
                    if current < min_v[j] {
                        min_v[j] = current;
                        way[j] = j0;
                    }
                    if min_v[j] < delta {
                        delta = min_v[j];
                        j1 = j;
                    }
                }
            }
            for j in 0..=n {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    min_v[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        loop {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    (1..=n)
        .filter_map(|j| {
            let (i, j) = (p[j].checked_sub(1)?, j - 1);
            (i < rows && j < columns && cost[i][j].is_finite()).then_some((i, j))
        })
        .collect()
}
