//! The measures `evaluate` reports, as pure functions of matched (state, truth) sequences, so that
//! each can be checked on cases computed by hand.

use std::f64::consts::{PI, TAU};

use serde::Serialize;

/// `angle` wrapped to (-pi, pi].
pub fn wrap(angle: f64) -> f64 {
    let wrapped = angle.rem_euclid(TAU);
    if wrapped > PI {
        wrapped - TAU
    } else {
        wrapped
    }
}

/// The `q`-quantile (0..=1) of sorted values, linearly interpolated; `None` when empty.
pub fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let position = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let (low, high) = (position.floor() as usize, position.ceil() as usize);
    Some(sorted[low] + (sorted[high] - sorted[low]) * (position - low as f64))
}

fn sorted(values: impl IntoIterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    v
}

/// Absolute angular errors, summarised.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct AngleErrors {
    pub count: usize,
    pub median_deg: Option<f64>,
    pub p90_deg: Option<f64>,
    /// Share of frames whose error exceeds 30 degrees.
    pub over_30_deg: Option<f64>,
    /// Share of frames whose error exceeds 150 degrees (the front/back confusions).
    pub over_150_deg: Option<f64>,
}

/// Summary of `|wrap(estimate - truth)|` over the frames (radians in, degrees out).
pub fn angle_errors(errors_rad: &[f64]) -> AngleErrors {
    let abs = sorted(errors_rad.iter().map(|e| wrap(*e).abs().to_degrees()));
    let share =
        |limit: f64| (!abs.is_empty()).then(|| abs.iter().filter(|e| **e > limit).count() as f64 / abs.len() as f64);
    AngleErrors {
        count: abs.len(),
        median_deg: quantile(&abs, 0.5),
        p90_deg: quantile(&abs, 0.9),
        over_30_deg: share(30.0),
        over_150_deg: share(150.0),
    }
}

/// Distances summarised (metres).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Distances {
    pub count: usize,
    pub median_m: Option<f64>,
    pub p90_m: Option<f64>,
}

pub fn distances(values: &[f64]) -> Distances {
    let v = sorted(values.iter().copied());
    Distances {
        count: v.len(),
        median_m: quantile(&v, 0.5),
        p90_m: quantile(&v, 0.9),
    }
}

/// Identity changes found against the true ones.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Changes {
    /// Frames the counts are over.
    pub frames: usize,
    pub true_changes: usize,
    pub reported: usize,
    /// True changes with a report within the tolerance after them.
    pub found: usize,
    /// Reports that found no true change.
    pub false_changes: usize,
    /// Frames from each found change to its report.
    pub delays_frames: Vec<usize>,
    pub recall: Option<f64>,
    pub false_per_1000_frames: Option<f64>,
    pub median_delay_frames: Option<f64>,
}

impl Changes {
    /// Adds another recording's counts (the ratios are recomputed).
    pub fn add(&mut self, other: &Changes) {
        self.frames += other.frames;
        self.true_changes += other.true_changes;
        self.reported += other.reported;
        self.found += other.found;
        self.false_changes += other.false_changes;
        self.delays_frames.extend(&other.delays_frames);
        self.finish();
    }

    fn finish(&mut self) {
        self.recall = (self.true_changes > 0).then(|| self.found as f64 / self.true_changes as f64);
        self.false_per_1000_frames = (self.frames > 0).then(|| 1000.0 * self.false_changes as f64 / self.frames as f64);
        self.median_delay_frames = quantile(&sorted(self.delays_frames.iter().map(|d| *d as f64)), 0.5);
    }
}

/// Matches reported changes to true ones. Both are frame indices in one recording, `frames` long.
/// A true change at frame `t` is found by the first unused report in `t ..= t + tolerance` (and
/// before the next true change); every report left unused is a false change.
pub fn match_changes(true_at: &[usize], reported_at: &[usize], tolerance: usize, frames: usize) -> Changes {
    let mut truths = true_at.to_vec();
    truths.sort_unstable();
    let mut reports = reported_at.to_vec();
    reports.sort_unstable();
    let mut used = vec![false; reports.len()];
    let mut delays = Vec::new();
    for (k, &t) in truths.iter().enumerate() {
        let next = truths.get(k + 1).copied().unwrap_or(usize::MAX);
        let end = t.saturating_add(tolerance).min(next.saturating_sub(1));
        if let Some(j) = (0..reports.len()).find(|&j| !used[j] && reports[j] >= t && reports[j] <= end) {
            used[j] = true;
            delays.push(reports[j] - t);
        }
    }
    let mut changes = Changes {
        frames,
        true_changes: truths.len(),
        reported: reports.len(),
        found: delays.len(),
        false_changes: used.iter().filter(|u| !**u).count(),
        delays_frames: delays,
        ..Changes::default()
    };
    changes.finish();
    changes
}

/// One subject's appearance in one recording: its frames' raw z_I Gaussians, in order.
#[derive(Debug, Clone)]
pub struct Segment {
    pub recording: String,
    pub subject: String,
    pub family: String,
    /// (mean, variance) per frame.
    pub frames: Vec<(Vec<f32>, Vec<f32>)>,
}

/// The precision-weighted product of Gaussians (the node's fusion without gate or floor).
pub fn fuse(frames: &[(Vec<f32>, Vec<f32>)]) -> Option<Vec<f64>> {
    let width = frames.first()?.0.len();
    let mut weighted = vec![0.0f64; width];
    let mut precision = vec![0.0f64; width];
    for (mean, variance) in frames {
        for k in 0..width.min(mean.len()).min(variance.len()) {
            let p = 1.0 / (variance[k] as f64).max(1e-12);
            weighted[k] += p * mean[k] as f64;
            precision[k] += p;
        }
    }
    Some(weighted.iter().zip(&precision).map(|(w, p)| w / p).collect())
}

/// Squared Euclidean distance of two fused z_I means.
fn squared_distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum()
}

/// Identity retrieval after `n` frames.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Retrieval {
    pub frames: usize,
    /// Segments long enough to take part (at least 2 n frames).
    pub queries: usize,
    /// Share of queries whose nearest reference (all subjects of the set) is their own.
    pub top1: Option<f64>,
    /// The same among the subjects of the query's family only.
    pub top1_same_family: Option<f64>,
}

/// For every segment of at least `2 n` frames: the reference is the fusion of its first half, the
/// query the fusion of the `n` frames that follow the half. A query is right when its nearest
/// reference (Euclidean distance of the fused means) is its own segment's. References of all long
/// enough segments compete.
pub fn retrieval(segments: &[Segment], n: usize) -> Retrieval {
    let usable: Vec<(&Segment, Vec<f64>, Vec<f64>)> = segments
        .iter()
        .filter(|s| n > 0 && s.frames.len() >= 2 * n)
        .filter_map(|s| {
            let half = s.frames.len() / 2;
            Some((s, fuse(&s.frames[..half])?, fuse(&s.frames[half..half + n])?))
        })
        .collect();
    let (mut right, mut right_family) = (0usize, 0usize);
    for (k, (segment, _, query)) in usable.iter().enumerate() {
        let nearest = |same_family: bool| {
            usable
                .iter()
                .enumerate()
                .filter(|(_, (s, _, _))| !same_family || s.family == segment.family)
                .min_by(|(_, (_, a, _)), (_, (_, b, _))| {
                    squared_distance(a, query).total_cmp(&squared_distance(b, query))
                })
                .map(|(j, _)| j)
        };
        right += usize::from(nearest(false) == Some(k));
        right_family += usize::from(nearest(true) == Some(k));
    }
    let share = |count: usize| (!usable.is_empty()).then(|| count as f64 / usable.len() as f64);
    Retrieval {
        frames: n,
        queries: usable.len(),
        top1: share(right),
        top1_same_family: share(right_family),
    }
}

/// Frame-to-frame steps of an unwrapped angle series (radians in, degrees out): its smoothness,
/// for recordings without ground truth.
pub fn angle_steps(angles_rad: &[f64]) -> AngleErrors {
    let steps: Vec<f64> = angles_rad.windows(2).map(|w| w[1] - w[0]).collect();
    angle_errors(&steps)
}

/// How far apart two subjects' z_I are, against how far one subject's z_I wanders, over windows
/// of `frames` frames: what bounds any identity-change detector that sees the encoder's z_I, and
/// so tells the encoder's share of a tracker's misses and false changes from the tracker's own.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Separability {
    pub frames: usize,
    /// True changes with `frames` frames on both sides (consecutive segments of one recording).
    pub changes: usize,
    pub same_family_changes: usize,
    /// Windows within one subject (every position with `frames` frames on both sides).
    pub within_windows: usize,
    /// Distance between the fused z_I of the windows before and after a position, within one subject.
    pub within_median: Option<f64>,
    pub within_p99: Option<f64>,
    pub within_p999: Option<f64>,
    /// The same across a true change.
    pub between_median: Option<f64>,
    pub between_same_family_median: Option<f64>,
    /// P(a change's distance > a within-subject window's): 1 separates, 0.5 is chance.
    pub auc: Option<f64>,
    pub auc_same_family: Option<f64>,
    /// Share of changes whose distance exceeds the within-subject 99.9th percentile: what a
    /// threshold on this distance would find with about one false window per 1,000.
    pub found_at_p999: Option<f64>,
    pub found_at_p999_same_family: Option<f64>,
}

/// The identity separability of `segments` (in recording order) over windows of `frames` frames.
/// A window's z_I is the fusion of its frames; distances are Euclidean, as in [`retrieval`].
pub fn separability(segments: &[Segment], frames: usize) -> Separability {
    let w = frames.max(1);
    let distance = |a: &[f64], b: &[f64]| squared_distance(a, b).sqrt();
    let pair =
        |before: &[(Vec<f32>, Vec<f32>)], after: &[(Vec<f32>, Vec<f32>)]| Some(distance(&fuse(before)?, &fuse(after)?));
    let mut within = Vec::new();
    for segment in segments {
        for t in w..=segment.frames.len().saturating_sub(w) {
            within.extend(pair(&segment.frames[t - w..t], &segment.frames[t..t + w]));
        }
    }
    let (mut between, mut between_same) = (Vec::new(), Vec::new());
    for s in segments.windows(2) {
        let (a, b) = (&s[0], &s[1]);
        if a.recording != b.recording || a.frames.len() < w || b.frames.len() < w {
            continue;
        }
        if let Some(d) = pair(&a.frames[a.frames.len() - w..], &b.frames[..w]) {
            between.push(d);
            if a.family == b.family {
                between_same.push(d);
            }
        }
    }
    let within = sorted(within);
    let p999 = quantile(&within, 0.999);
    let auc = |changes: &[f64]| {
        if changes.is_empty() || within.is_empty() {
            return None;
        }
        let wins: f64 = changes
            .iter()
            .map(|d| {
                let below = within.partition_point(|x| x < d) as f64;
                let ties = within.partition_point(|x| x <= d) as f64 - below;
                below + 0.5 * ties
            })
            .sum();
        Some(wins / (changes.len() * within.len()) as f64)
    };
    let found = |changes: &[f64]| {
        let limit = p999?;
        (!changes.is_empty()).then(|| changes.iter().filter(|d| **d > limit).count() as f64 / changes.len() as f64)
    };
    Separability {
        frames: w,
        changes: between.len(),
        same_family_changes: between_same.len(),
        within_windows: within.len(),
        within_median: quantile(&within, 0.5),
        within_p99: quantile(&within, 0.99),
        within_p999: p999,
        between_median: quantile(&sorted(between.iter().copied()), 0.5),
        between_same_family_median: quantile(&sorted(between_same.iter().copied()), 0.5),
        auc: auc(&between),
        auc_same_family: auc(&between_same),
        found_at_p999: found(&between),
        found_at_p999_same_family: found(&between_same),
    }
}

/// A subject walks when its true position moves faster than this (m/s), and stands when slower
/// than `STANDING_SPEED_M_S`; frames in between (a walk slowing to turn) count as neither.
pub const WALKING_SPEED_M_S: f64 = 0.15;
pub const STANDING_SPEED_M_S: f64 = 0.03;

/// Frames per window of `window_spreads`: one second of the sim's 30 Hz camera.
pub const SPREAD_WINDOW_FRAMES: usize = 30;

/// Whether the pose code z_E follows the body (issue 32), two ways:
/// - its frame-to-frame steps while the subject walks against while it stands: at 30 Hz a gait
///   moves the pose little from one frame to the next, so this mostly compares per-frame noise;
/// - its spread over one-second windows (`window_spreads`) while walking against while standing: a
///   gait sweeps the pose through its cycle within a second, a standing subject's code only jitters.
///
/// A z_E that carries nothing moves alike in both, and its ratios are about 1; a dead one (every
/// step zero) has none.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PoseCodeMotion {
    pub walking_steps: usize,
    pub standing_steps: usize,
    /// Median Euclidean distance between the z_E of consecutive frames of one subject.
    pub walking_step_median: Option<f64>,
    pub standing_step_median: Option<f64>,
    /// walking median over standing median.
    pub ratio: Option<f64>,
    pub walking_windows: usize,
    pub standing_windows: usize,
    /// Median over windows of z_E's root-mean-square distance from the window's mean.
    pub walking_spread_median: Option<f64>,
    pub standing_spread_median: Option<f64>,
    /// walking spread median over standing spread median.
    pub spread_ratio: Option<f64>,
}

/// `steps`: per pair of consecutive frames of one subject, the z_E step and the subject's true
/// horizontal speed (m/s); `spreads`: per window, z_E's spread and the window's mean true speed.
pub fn pose_code_motion(steps: &[(f64, f64)], spreads: &[(f64, f64)]) -> PoseCodeMotion {
    let (walking, standing) = by_motion(steps);
    let (walking_spread, standing_spread) = by_motion(spreads);
    let median = |v: &[f64]| quantile(v, 0.5);
    PoseCodeMotion {
        walking_steps: walking.len(),
        standing_steps: standing.len(),
        walking_step_median: median(&walking),
        standing_step_median: median(&standing),
        ratio: ratio(median(&walking), median(&standing)),
        walking_windows: walking_spread.len(),
        standing_windows: standing_spread.len(),
        walking_spread_median: median(&walking_spread),
        standing_spread_median: median(&standing_spread),
        spread_ratio: ratio(median(&walking_spread), median(&standing_spread)),
    }
}

/// The values of (value, speed) pairs taken while walking, and while standing, each sorted.
fn by_motion(values: &[(f64, f64)]) -> (Vec<f64>, Vec<f64>) {
    (
        sorted(values.iter().filter(|(_, v)| *v > WALKING_SPEED_M_S).map(|(s, _)| *s)),
        sorted(values.iter().filter(|(_, v)| *v < STANDING_SPEED_M_S).map(|(s, _)| *s)),
    )
}

fn ratio(numerator: Option<f64>, denominator: Option<f64>) -> Option<f64> {
    numerator.zip(denominator).and_then(|(n, d)| (d > 0.0).then(|| n / d))
}

/// One subject's consecutive frames (code, true speed in m/s) cut into non-overlapping windows of
/// `window` frames (a shorter tail is left out): per window, the codes' root-mean-square Euclidean
/// distance from their mean, and the mean speed.
pub fn window_spreads(run: &[(Vec<f32>, f64)], window: usize) -> Vec<(f64, f64)> {
    if window == 0 {
        return Vec::new();
    }
    run.chunks_exact(window)
        .map(|frames| {
            let dimensions = frames[0].0.len();
            let mean: Vec<f64> = (0..dimensions)
                .map(|d| frames.iter().map(|(z, _)| z[d] as f64).sum::<f64>() / window as f64)
                .collect();
            let squared: f64 = frames
                .iter()
                .map(|(z, _)| z.iter().zip(&mean).map(|(x, m)| (*x as f64 - m).powi(2)).sum::<f64>())
                .sum();
            let speed = frames.iter().map(|(_, v)| v).sum::<f64>() / window as f64;
            ((squared / window as f64).sqrt(), speed)
        })
        .collect()
}

/// One matched frame, as `pose_retrieval` reads it: who is seen, the code, and the true pose.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseFrame {
    pub family: String,
    pub subject: String,
    pub code: Vec<f32>,
    /// The sim's joint angles (axis-angle per non-root joint, rad): one layout per family.
    pub theta: Vec<f32>,
}

/// Whether a pose code names the body's pose across individuals (issue 32), free of what the walk
/// and stand motions of the recordings happen to do: for each frame, the frame of **another
/// subject of the same family** whose code is nearest, and the true pose distance to it over the
/// median true pose distance to all that family's other subjects' frames (per frame, then the
/// median over frames). About 1: the code says nothing of the pose (a dead code, or one that
/// follows the view or the subject); 0: it finds the same pose on another body. The truth's own
/// nearest neighbour gives the floor that the recordings' poses allow.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PoseRetrieval {
    /// Frames that had another subject of their family to search.
    pub frames: usize,
    /// Median over frames of (true distance to the code's nearest) / (median true distance).
    pub code_ratio: Option<f64>,
    /// The same with the nearest true pose: the best any code can do here.
    pub truth_floor: Option<f64>,
    /// The same per family, by name (a family's code can read the pose while another's cannot:
    /// a quadruped's thin legs, a biped's arms).
    pub families: std::collections::BTreeMap<String, FamilyPoseRetrieval>,
}

/// [`PoseRetrieval`]'s figures for one family.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct FamilyPoseRetrieval {
    pub frames: usize,
    pub code_ratio: Option<f64>,
    pub truth_floor: Option<f64>,
}

/// At most this many frames per family are searched (evenly strided): consecutive frames of a
/// 30 Hz recording are nearly alike, and the search is quadratic.
pub const POSE_RETRIEVAL_MAX_FRAMES: usize = 3000;

pub fn pose_retrieval(frames: &[PoseFrame]) -> PoseRetrieval {
    let mut families: Vec<&str> = frames.iter().map(|f| f.family.as_str()).collect();
    families.sort_unstable();
    families.dedup();
    let (mut code_ratios, mut truth_ratios) = (Vec::new(), Vec::new());
    let mut by_family = std::collections::BTreeMap::new();
    for family in families {
        let (mut family_codes, mut family_truths) = (Vec::new(), Vec::new());
        let all: Vec<&PoseFrame> = frames
            .iter()
            .filter(|f| f.family == family && !f.theta.is_empty() && !f.code.is_empty())
            .collect();
        let stride = all.len().div_ceil(POSE_RETRIEVAL_MAX_FRAMES).max(1);
        let members: Vec<&PoseFrame> = all.into_iter().step_by(stride).collect();
        for query in &members {
            let others = members.iter().filter(|o| {
                o.subject != query.subject && o.theta.len() == query.theta.len() && o.code.len() == query.code.len()
            });
            let (mut truth_distances, mut nearest_code, mut nearest_truth) =
                (Vec::new(), (f64::INFINITY, 0.0), f64::INFINITY);
            for other in others {
                let truth = code_step(&query.theta, &other.theta);
                let code = code_step(&query.code, &other.code);
                truth_distances.push(truth);
                if code < nearest_code.0 {
                    nearest_code = (code, truth);
                }
                nearest_truth = nearest_truth.min(truth);
            }
            let Some(median) = quantile(&sorted(truth_distances), 0.5).filter(|m| *m > 0.0) else {
                continue;
            };
            family_codes.push(nearest_code.1 / median);
            family_truths.push(nearest_truth / median);
        }
        if !family_codes.is_empty() {
            code_ratios.extend_from_slice(&family_codes);
            truth_ratios.extend_from_slice(&family_truths);
            let figures = FamilyPoseRetrieval {
                frames: family_codes.len(),
                code_ratio: quantile(&sorted(family_codes), 0.5),
                truth_floor: quantile(&sorted(family_truths), 0.5),
            };
            by_family.insert(family.to_string(), figures);
        }
    }
    PoseRetrieval {
        frames: code_ratios.len(),
        code_ratio: quantile(&sorted(code_ratios), 0.5),
        truth_floor: quantile(&sorted(truth_ratios), 0.5),
        families: by_family,
    }
}

/// The Euclidean distance between two codes.
pub fn code_step(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}
