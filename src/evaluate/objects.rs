//! Several objects per stream (`[track.objects] enabled`): the published tracks against the sim's
//! per-subject ground truth (`subjects` of each frame's truth). Reports the standard multi-object
//! tracking measures (`mot.rs`), how often a subject that left the scene got its old id back on
//! its return, and the heading error of the tracks matched to subjects.
//!
//! A subject counts in a frame while it is present with at least `min_visible_points` points of
//! the cloud on it; a subject in view with fewer is ignored (as MOT benchmarks ignore heavily
//! occluded objects): a track on it is neither a match nor a false track. Positions are compared
//! on the ground plane (the truth's `translation` is where a subject stands, a state's centre
//! that of its points).

use std::collections::HashMap;

use serde::Serialize;

use super::metrics::{self, AngleErrors};
use super::mot::{mot_counts, Located, MotCounts, MotFrame};
use super::truth::TruthFrame;
use crate::state::State;
use crate::track::association::assign;

#[derive(Debug, Clone, Copy, Serialize)]
pub struct ObjectsOptions {
    /// A track and a subject correspond within this horizontal distance (m).
    pub max_distance_m: f64,
    /// A subject with fewer points on it in a frame is ignored there.
    pub min_visible_points: usize,
}

impl Default for ObjectsOptions {
    fn default() -> Self {
        Self {
            max_distance_m: 0.5,
            min_visible_points: 200,
        }
    }
}

/// Returns of subjects that left the scene: how many got the id they had before.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Returns {
    /// Returns while every other subject in the scene was of another family ...
    pub other_family: usize,
    /// ... and of those, the ones whose first track after the return had the id of the last one
    /// before it.
    pub other_family_same_id: usize,
    /// Returns while a subject of the same family was in the scene, and their same-id share.
    pub same_family: usize,
    pub same_family_same_id: usize,
}

impl Returns {
    pub fn add(&mut self, other: &Returns) {
        self.other_family += other.other_family;
        self.other_family_same_id += other.other_family_same_id;
        self.same_family += other.same_family;
        self.same_family_same_id += other.same_family_same_id;
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ObjectsReport {
    pub mot: MotCounts,
    /// Identity switches per 1,000 frames.
    pub id_switches_per_1000_frames: f64,
    pub returns: Returns,
    /// Filtered heading of the tracks matched to subjects, against each subject's true yaw.
    pub heading_filtered: AngleErrors,
    /// Distinct track ids published.
    pub tracks: usize,
    /// The heading errors (rad), pooled over recordings.
    #[serde(skip)]
    pub heading_errors_rad: Vec<f64>,
}

/// Per frame: the states matched to each counted subject (subject id -> state).
pub type Matches<'a> = Vec<HashMap<u64, &'a State>>;

/// One recording's multi-object report, and per truth frame the states matched to its subjects.
pub fn objects_report<'a>(
    truth: &[TruthFrame],
    states: &[&'a State],
    options: &ObjectsOptions,
) -> (ObjectsReport, Matches<'a>) {
    let mut by_stamp: HashMap<u64, Vec<&State>> = HashMap::new();
    for state in states {
        if let Some(stamp) = state.stamps.sensor_ns {
            by_stamp.entry(stamp).or_default().push(state);
        }
    }
    let ground = |p: [f64; 3]| [p[0] as f32, p[1] as f32, 0.0];
    let mut frames = Vec::with_capacity(truth.len());
    let mut matches: Matches = Vec::with_capacity(truth.len());
    let mut heading_errors = Vec::new();
    let mut track_ids: Vec<u64> = Vec::new();
    for t in truth {
        let here = by_stamp.get(&t.stamp_nanos).map(Vec::as_slice).unwrap_or(&[]);
        let counted: Vec<_> = t
            .subjects
            .iter()
            .filter(|s| s.present && s.visible_points >= options.min_visible_points)
            .collect();
        let ignored: Vec<_> = t
            .subjects
            .iter()
            .filter(|s| s.present && s.visible_points > 0 && s.visible_points < options.min_visible_points)
            .collect();
        let centre = |s: &State| ground(s.centre_m.map(f64::from));
        let cost: Vec<Vec<f64>> = counted
            .iter()
            .map(|subject| {
                here.iter()
                    .map(|state| {
                        let d = planar(&ground(subject.translation), &centre(state));
                        if d <= options.max_distance_m {
                            d
                        } else {
                            f64::INFINITY
                        }
                    })
                    .collect()
            })
            .collect();
        let pairs = assign(&cost);
        let mut matched_here = HashMap::new();
        for &(si, hi) in &pairs {
            let (subject, state) = (counted[si], here[hi]);
            matched_here.insert(subject.id, state);
            heading_errors.push(state.filtered.yaw as f64 - subject.yaw);
        }
        let taken: Vec<usize> = pairs.iter().map(|&(_, hi)| hi).collect();
        let hypotheses = here
            .iter()
            .enumerate()
            .filter(|(hi, state)| {
                taken.contains(hi)
                    || !ignored
                        .iter()
                        .any(|s| planar(&ground(s.translation), &centre(state)) <= options.max_distance_m)
            })
            .filter_map(|(_, state)| {
                let id = state.track?;
                if !track_ids.contains(&id) {
                    track_ids.push(id);
                }
                Some(Located {
                    id,
                    centre: centre(state),
                })
            })
            .collect();
        frames.push(MotFrame {
            truth: counted
                .iter()
                .map(|s| Located {
                    id: s.id,
                    centre: ground(s.translation),
                })
                .collect(),
            hypotheses,
        });
        matches.push(matched_here);
    }
    let mot = mot_counts(&frames, options.max_distance_m);
    let report = ObjectsReport {
        id_switches_per_1000_frames: if mot.frames == 0 {
            f64::NAN
        } else {
            1000.0 * mot.id_switches as f64 / mot.frames as f64
        },
        mot,
        returns: returns(truth, &matches),
        heading_filtered: metrics::angle_errors(&heading_errors),
        tracks: track_ids.len(),
        heading_errors_rad: heading_errors,
    };
    (report, matches)
}

fn planar(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    ((a[0] - b[0]) as f64).hypot((a[1] - b[1]) as f64)
}

/// Every return of a subject to the scene after it was tracked: whether its first matched track
/// after the return has the id of its last one before it (no track after the return: not).
fn returns(truth: &[TruthFrame], matches: &Matches) -> Returns {
    let mut out = Returns::default();
    let ids: Vec<u64> = truth
        .iter()
        .flat_map(|t| t.subjects.iter().map(|s| s.id))
        .fold(Vec::new(), |mut ids, id| {
            if !ids.contains(&id) {
                ids.push(id);
            }
            ids
        });
    for id in ids {
        let present = |f: usize| truth[f].subjects.iter().any(|s| s.id == id && s.present);
        let mut last_track: Option<u64> = None;
        let mut f = 0;
        while f < truth.len() {
            if present(f) {
                if let Some(state) = matches[f].get(&id) {
                    last_track = state.track;
                }
                f += 1;
                continue;
            }
            // Away from frame f: where it comes back, if it does.
            let Some(back) = (f..truth.len()).find(|&g| present(g)) else {
                break;
            };
            if let Some(before) = last_track {
                let family = truth[back]
                    .subjects
                    .iter()
                    .find(|s| s.id == id)
                    .map(|s| s.family.clone());
                let same_family_near = truth[back]
                    .subjects
                    .iter()
                    .any(|s| s.id != id && s.present && Some(&s.family) == family.as_ref());
                let after = (back..truth.len())
                    .take_while(|&g| present(g))
                    .find_map(|g| matches[g].get(&id).and_then(|s| s.track));
                let same = after == Some(before);
                if same_family_near {
                    out.same_family += 1;
                    out.same_family_same_id += same as usize;
                } else {
                    out.other_family += 1;
                    out.other_family_same_id += same as usize;
                }
            }
            f = back;
        }
    }
    out
}

/// Pooled counts of several recordings (MOTA and IDF1 recomputed from the sums).
pub fn pooled(reports: &[&ObjectsReport]) -> ObjectsReport {
    let mut mot = MotCounts::default();
    let mut returns = Returns::default();
    let heading_errors: Vec<f64> = reports
        .iter()
        .flat_map(|r| r.heading_errors_rad.iter().copied())
        .collect();
    for r in reports {
        let m = &r.mot;
        mot.frames += m.frames;
        mot.objects += m.objects;
        mot.hypotheses += m.hypotheses;
        mot.matches += m.matches;
        mot.misses += m.misses;
        mot.false_positives += m.false_positives;
        mot.id_switches += m.id_switches;
        mot.fragmentations += m.fragmentations;
        mot.idtp += m.idtp;
        mot.idfp += m.idfp;
        mot.idfn += m.idfn;
        returns.add(&r.returns);
    }
    mot.mota = 1.0 - (mot.misses + mot.false_positives + mot.id_switches) as f64 / mot.objects.max(1) as f64;
    mot.idf1 = 2.0 * mot.idtp as f64 / (2 * mot.idtp + mot.idfp + mot.idfn).max(1) as f64;
    ObjectsReport {
        id_switches_per_1000_frames: 1000.0 * mot.id_switches as f64 / mot.frames.max(1) as f64,
        mot,
        returns,
        heading_filtered: metrics::angle_errors(&heading_errors),
        tracks: reports.iter().map(|r| r.tracks).sum(),
        heading_errors_rad: heading_errors,
    }
}
