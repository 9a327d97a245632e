//! The standard multi-object tracking measures (issue 34, item 5), as pure functions of per-frame
//! ground truth and hypotheses: CLEAR MOT (Bernardin & Stiefelhagen 2008: misses, false
//! positives, identity switches, fragmentations, MOTA) and the identity measures (Ristani et al.
//! 2016: IDTP, IDFP, IDFN, IDF1). An object and a hypothesis correspond in a frame when their
//! centres lie within `max_distance_m`.
//!
//! CLEAR MOT, frame by frame: a correspondence of the previous frame is kept while it stays within
//! the distance; the rest are matched at least total distance (Hungarian). A ground-truth object
//! matched to another hypothesis than at its last match is an identity switch; one whose matching
//! resumes after frames unmatched (while present) is a fragmentation. IDF1 matches whole
//! trajectories once, so that each object has at most one hypothesis id over the sequence.

use std::collections::{BTreeMap, HashMap};

use crate::track::association::assign;

/// One object or hypothesis in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Located {
    pub id: u64,
    pub centre: [f32; 3],
}

/// One frame: the objects present (ground truth) and the tracks the node reported.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MotFrame {
    pub truth: Vec<Located>,
    pub hypotheses: Vec<Located>,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct MotCounts {
    pub frames: usize,
    /// Ground-truth objects over all frames.
    pub objects: usize,
    pub hypotheses: usize,
    pub matches: usize,
    pub misses: usize,
    pub false_positives: usize,
    pub id_switches: usize,
    pub fragmentations: usize,
    /// 1 - (misses + false positives + id switches) / objects.
    pub mota: f64,
    pub idtp: usize,
    pub idfp: usize,
    pub idfn: usize,
    /// 2 IDTP / (2 IDTP + IDFP + IDFN).
    pub idf1: f64,
}

fn distance(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    (0..3).map(|i| ((a[i] - b[i]) as f64).powi(2)).sum::<f64>().sqrt()
}

/// CLEAR MOT and identity measures over `frames`.
pub fn mot_counts(frames: &[MotFrame], max_distance_m: f64) -> MotCounts {
    let mut counts = MotCounts {
        frames: frames.len(),
        ..Default::default()
    };
    // Per object: its hypothesis now (kept while within the distance), its last matched
    // hypothesis, and whether it was unmatched since (for fragmentations).
    let mut current: HashMap<u64, u64> = HashMap::new();
    let mut last_matched: HashMap<u64, u64> = HashMap::new();
    let mut gap_since_match: HashMap<u64, bool> = HashMap::new();
    // Frames in which each (object, hypothesis) pair corresponds, for IDF1.
    let mut overlap: BTreeMap<(u64, u64), usize> = BTreeMap::new();
    let (mut truth_ids, mut hypothesis_ids) = (Vec::new(), Vec::new());
    for frame in frames {
        counts.objects += frame.truth.len();
        counts.hypotheses += frame.hypotheses.len();
        for t in &frame.truth {
            for h in &frame.hypotheses {
                if distance(&t.centre, &h.centre) <= max_distance_m {
                    *overlap.entry((t.id, h.id)).or_default() += 1;
                }
            }
            if !truth_ids.contains(&t.id) {
                truth_ids.push(t.id);
            }
        }
        for h in &frame.hypotheses {
            if !hypothesis_ids.contains(&h.id) {
                hypothesis_ids.push(h.id);
            }
        }

        let mut matched: Vec<(usize, usize)> = Vec::new();
        let (mut truth_taken, mut hypothesis_taken) =
            (vec![false; frame.truth.len()], vec![false; frame.hypotheses.len()]);
        // Correspondences kept from the previous frame.
        for (ti, t) in frame.truth.iter().enumerate() {
            let Some(&hid) = current.get(&t.id) else { continue };
            if let Some(hi) = frame.hypotheses.iter().position(|h| h.id == hid) {
                if !hypothesis_taken[hi] && distance(&t.centre, &frame.hypotheses[hi].centre) <= max_distance_m {
                    matched.push((ti, hi));
                    truth_taken[ti] = true;
                    hypothesis_taken[hi] = true;
                }
            }
        }
        // The rest at least total distance.
        let free_truth: Vec<usize> = (0..frame.truth.len()).filter(|&i| !truth_taken[i]).collect();
        let free_hypotheses: Vec<usize> = (0..frame.hypotheses.len()).filter(|&i| !hypothesis_taken[i]).collect();
        let cost: Vec<Vec<f64>> = free_truth
            .iter()
            .map(|&ti| {
                free_hypotheses
                    .iter()
                    .map(|&hi| {
                        let d = distance(&frame.truth[ti].centre, &frame.hypotheses[hi].centre);
                        if d <= max_distance_m {
                            d
                        } else {
                            f64::INFINITY
                        }
                    })
                    .collect()
            })
            .collect();
        for (r, c) in assign(&cost) {
            matched.push((free_truth[r], free_hypotheses[c]));
        }

        counts.matches += matched.len();
        counts.misses += frame.truth.len() - matched.len();
        counts.false_positives += frame.hypotheses.len() - matched.len();
        let mut matched_now = vec![false; frame.truth.len()];
        for &(ti, hi) in &matched {
            matched_now[ti] = true;
            let (object, hypothesis) = (frame.truth[ti].id, frame.hypotheses[hi].id);
            if last_matched.get(&object).is_some_and(|&h| h != hypothesis) {
                counts.id_switches += 1;
            }
            if gap_since_match.get(&object).copied().unwrap_or(false) {
                counts.fragmentations += 1;
            }
            last_matched.insert(object, hypothesis);
            gap_since_match.insert(object, false);
            current.insert(object, hypothesis);
        }
        for (ti, t) in frame.truth.iter().enumerate() {
            if !matched_now[ti] {
                current.remove(&t.id);
                if last_matched.contains_key(&t.id) {
                    gap_since_match.insert(t.id, true);
                }
            }
        }
        // An object out of the frame keeps no correspondence.
        current.retain(|object, _| frame.truth.iter().any(|t| t.id == *object));
    }
    counts.mota = if counts.objects == 0 {
        f64::NAN
    } else {
        1.0 - (counts.misses + counts.false_positives + counts.id_switches) as f64 / counts.objects as f64
    };

    // IDF1: one hypothesis per object over the whole sequence, the most frames in common.
    let cost: Vec<Vec<f64>> = truth_ids
        .iter()
        .map(|t| {
            hypothesis_ids
                .iter()
                .map(|h| -(overlap.get(&(*t, *h)).copied().unwrap_or(0) as f64))
                .collect()
        })
        .collect();
    counts.idtp = assign(&cost)
        .into_iter()
        .map(|(r, c)| overlap.get(&(truth_ids[r], hypothesis_ids[c])).copied().unwrap_or(0))
        .sum();
    counts.idfn = counts.objects - counts.idtp;
    counts.idfp = counts.hypotheses - counts.idtp;
    let denominator = 2 * counts.idtp + counts.idfp + counts.idfn;
    counts.idf1 = if denominator == 0 {
        f64::NAN
    } else {
        2.0 * counts.idtp as f64 / denominator as f64
    };
    counts
}
