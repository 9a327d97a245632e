//! Evaluate: the node's tracking measured against the simulator's ground truth.
//!
//! `gdvae-node evaluate REC...` replays sim recordings through the real pipeline (same stages, same
//! settings, every frame), matches each published state to the recording's `/sim/ground_truth`
//! message by sensor stamp, and reports per recording and overall: heading error of the raw and
//! filtered yaw, position error of `centre_m`, identity changes found against the true ones,
//! identity retrieval from the fused z_I, and the separability of z_I alone (within one subject
//! against across a change), which bounds what any change detector can do with this encoder. A
//! recording without ground truth gets what can be said without it (identity changes reported,
//! heading smoothness).
//!
//! Convention (no offset is fitted): the estimated heading is the yaw about +z of R(q), the
//! rotation that carries the bundle's canonical shape (forward +x, up +z, the sim's rest frame) onto
//! the observed one, in the node's gravity frame. The gravity frame is the recording's world frame:
//! each source's sensor pose is the recording's `world_from_camera` (unless `--keep-sensor-pose`).

pub mod metrics;
pub mod mot;
pub mod objects;
pub mod plot;
pub mod print;
pub mod truth;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::config::SourceSettings;
use crate::state::{Output, State};
use metrics::{
    AngleErrors, Changes, Distances, PoseCodeMotion, PoseFrame, PoseRetrieval, Retrieval, Segment, Separability,
};
use truth::TruthFrame;

pub const CONVENTION: &str =
    "heading error = wrap(yaw of R(q) - true yaw) about +z of the gravity frame; R(q) carries \
the canonical shape (forward +x, up +z, the sim's rest frame) onto the observed one; the gravity frame is the \
recording's world frame (sensor pose = its world_from_camera); no offset fitted";

#[derive(Debug, Clone)]
pub struct EvaluateOptions {
    /// A true identity change is found when the node reports one within this many frames after it.
    pub tolerance_frames: usize,
    /// Identity retrieval after these numbers of frames.
    pub retrieval_frames: Vec<usize>,
    /// Identity separability of the encoder's z_I over windows of these numbers of frames.
    pub separability_frames: Vec<usize>,
    /// Take each source's sensor pose from the recording's ground truth (`world_from_camera`).
    pub pose_from_truth: bool,
    /// How tracks are matched to subjects when the states name tracks (several objects).
    pub objects: objects::ObjectsOptions,
}

impl Default for EvaluateOptions {
    fn default() -> Self {
        Self {
            tolerance_frames: 10,
            retrieval_frames: vec![1, 5, 30],
            separability_frames: vec![1, 10],
            pose_from_truth: true,
            objects: objects::ObjectsOptions::default(),
        }
    }
}

/// One input and what is known of it before the replay.
#[derive(Debug, Clone)]
pub struct Recording {
    /// Its stream in the pipeline.
    pub stream: String,
    pub path: PathBuf,
    pub truth: Vec<TruthFrame>,
}

#[derive(Debug, thiserror::Error)]
pub enum EvaluateError {
    #[error(transparent)]
    Truth(#[from] truth::TruthError),
}

/// Reads each recording's ground truth and names its stream.
pub fn recordings(inputs: &[PathBuf]) -> Result<Vec<Recording>, EvaluateError> {
    let sources = crate::sources::replay_sources(inputs, 0.0);
    sources
        .into_iter()
        .zip(inputs)
        .map(|(source, path)| {
            Ok(Recording {
                stream: source.stream,
                path: path.clone(),
                truth: truth::read_truth(path)?,
            })
        })
        .collect()
}

/// The replay sources of `recordings` (as fast as possible, every frame), each with the sensor
/// pose its ground truth gives when `pose_from_truth` is set.
pub fn sources(recordings: &[Recording], options: &EvaluateOptions) -> Vec<SourceSettings> {
    let paths: Vec<PathBuf> = recordings.iter().map(|r| r.path.clone()).collect();
    let mut sources = crate::sources::replay_sources(&paths, 0.0);
    for (source, recording) in sources.iter_mut().zip(recordings) {
        source.stream = recording.stream.clone();
        let pose = recording.truth.first().and_then(|t| t.world_from_camera);
        if let (true, Some(pose)) = (options.pose_from_truth, pose) {
            source.sensor_to_gravity_rotation = Some(pose.rotation_rows());
            source.sensor_to_gravity_translation = Some(pose.translation.map(|v| v as f32));
        }
    }
    sources
}

/// One matched frame, what the plots draw.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub frame: usize,
    pub true_yaw: f64,
    pub raw_yaw: f64,
    pub filtered_yaw: f64,
    pub filtered_yaw_std: Option<f64>,
    /// Horizontal distance of `centre_m` to the true position (m).
    pub position_m: f64,
    /// Index of the true subject in order of appearance.
    pub subject: usize,
    pub identity: u64,
    pub distance: f64,
    pub change_statistic: f64,
    pub change_reported: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct RecordingReport {
    pub stream: String,
    pub path: String,
    pub has_truth: bool,
    pub truth_frames: usize,
    pub states: usize,
    pub rejected: usize,
    /// States matched to a ground-truth message by sensor stamp.
    pub matched: usize,
    pub states_without_truth: usize,
    /// Ground-truth frames with no state (rejected or never published).
    pub truth_without_state: usize,
    pub subjects: Vec<String>,
    pub families: Vec<String>,
    pub heading_raw: Option<AngleErrors>,
    pub heading_filtered: Option<AngleErrors>,
    /// Horizontal distance of `centre_m` to the subject's true position.
    pub position: Option<Distances>,
    pub changes: Option<Changes>,
    pub changes_reported: usize,
    /// Frame-to-frame steps of the filtered yaw: its smoothness, with or without truth.
    pub filtered_yaw_steps: AngleErrors,
    /// The raw z_E's frame-to-frame steps while the subject walks and while it stands.
    pub pose_code: Option<PoseCodeMotion>,
    /// The same for the published (filtered) z_E, what a subscriber sees.
    pub pose_code_published: Option<PoseCodeMotion>,
    /// The same for the true pose (the sim's joint angles): what the walks and stands of this
    /// recording ask of a pose code (None where the truth has no joint angles).
    pub true_pose: Option<PoseCodeMotion>,
    /// With several objects (states that name tracks): the tracks against every subject.
    pub objects: Option<objects::ObjectsReport>,
    #[serde(skip)]
    pub rows: Vec<Row>,
    /// What `pose_code` and `pose_code_published` were computed from, pooled by `Overall`.
    #[serde(skip)]
    pub raw_pose_samples: PoseCodeSamples,
    #[serde(skip)]
    pub published_pose_samples: PoseCodeSamples,
    #[serde(skip)]
    pub true_pose_samples: PoseCodeSamples,
    /// Per matched frame with joint angles: the raw and the published z_E with the true pose, for
    /// `Overall`'s pose retrieval.
    #[serde(skip)]
    pub pose_frames: Vec<(PoseFrame, PoseFrame)>,
}

/// What `metrics::pose_code_motion` reads of one z_E signal (raw or published) of a recording: the
/// frame-to-frame steps and the one-second windows' spreads, each with the true speed, built
/// from runs of consecutive frames of one subject.
#[derive(Debug, Clone, Default)]
pub struct PoseCodeSamples {
    pub steps: Vec<(f64, f64)>,
    pub spreads: Vec<(f64, f64)>,
    run: Vec<(Vec<f32>, f64)>,
}

impl PoseCodeSamples {
    /// The next frame of the subject's run: its code, the frame before's, and the true speed.
    fn push(&mut self, code: &[f32], earlier: &[f32], speed: f64) {
        self.steps.push((metrics::code_step(code, earlier), speed));
        self.run.push((code.to_vec(), speed));
    }

    /// The run of consecutive frames ended (a change of subject, a frame missing, the end).
    fn end_run(&mut self) {
        self.spreads
            .extend(metrics::window_spreads(&self.run, metrics::SPREAD_WINDOW_FRAMES));
        self.run.clear();
    }

    fn extend(&mut self, other: &Self) {
        self.steps.extend_from_slice(&other.steps);
        self.spreads.extend_from_slice(&other.spreads);
    }

    fn motion(&self) -> PoseCodeMotion {
        metrics::pose_code_motion(&self.steps, &self.spreads)
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Overall {
    pub recordings: usize,
    pub with_truth: usize,
    pub matched: usize,
    pub heading_raw: AngleErrors,
    pub heading_filtered: AngleErrors,
    pub heading_raw_by_family: BTreeMap<String, AngleErrors>,
    pub heading_filtered_by_family: BTreeMap<String, AngleErrors>,
    pub position: Distances,
    pub changes: Changes,
    pub retrieval: Vec<Retrieval>,
    /// How well the encoder's z_I alone tells subjects apart: the bound on change detection.
    pub separability: Vec<Separability>,
    /// Whether z_E follows the gait: its steps while walking against while standing.
    pub pose_code: PoseCodeMotion,
    /// The same for the published (filtered) z_E.
    pub pose_code_published: PoseCodeMotion,
    /// The same for the true pose: the ratios a code that is exactly the pose would show.
    pub true_pose: PoseCodeMotion,
    /// Whether z_E finds the same pose on another subject of the family (raw, published).
    pub pose_retrieval: PoseRetrieval,
    pub pose_retrieval_published: PoseRetrieval,
    /// With several objects: the multi-object figures pooled over the recordings.
    pub objects: Option<objects::ObjectsReport>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub convention: &'static str,
    pub tolerance_frames: usize,
    pub objects_options: objects::ObjectsOptions,
    pub overall: Overall,
    pub recordings: Vec<RecordingReport>,
}

/// Matches the published outputs to the recordings' ground truth and measures.
pub fn report(recordings: &[Recording], outputs: &[Output], options: &EvaluateOptions) -> Report {
    let mut states: HashMap<&str, Vec<&State>> = HashMap::new();
    let mut rejected: HashMap<&str, usize> = HashMap::new();
    for output in outputs {
        match output {
            Output::State(s) => states.entry(s.stream.as_str()).or_default().push(s),
            Output::Rejected(r) => *rejected.entry(r.stream.as_str()).or_default() += 1,
        }
    }
    let mut reports = Vec::new();
    let mut segments = Vec::new();
    let (mut raw_all, mut filtered_all, mut position_all) = (Vec::new(), Vec::new(), Vec::new());
    let mut raw_family: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut filtered_family: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut changes_all = Changes::default();
    let mut raw_pose_all = PoseCodeSamples::default();
    let mut published_pose_all = PoseCodeSamples::default();
    let mut true_pose_all = PoseCodeSamples::default();
    let (mut raw_pose_frames, mut published_pose_frames) = (Vec::new(), Vec::new());
    for recording in recordings {
        let mut own = states.get(recording.stream.as_str()).cloned().unwrap_or_default();
        // Several objects: the tracks against every subject; the single-object figures below
        // then measure the tracks matched to the primary subject.
        let several = own.iter().any(|s| s.track.is_some()) && !recording.truth.is_empty();
        let objects = several.then(|| {
            let truth = with_subjects(&recording.truth);
            let (report, matches) = objects::objects_report(&truth, &own, &options.objects);
            own = matches.iter().filter_map(|m| m.get(&0).copied()).collect();
            report
        });
        let (mut report, own_segments) = recording_report(
            recording,
            &own,
            rejected.get(recording.stream.as_str()).copied(),
            options,
        );
        // Pooled figures over the matched frames.
        for row in &report.rows {
            let family = &recording.truth[row.frame].family;
            raw_all.push(row.raw_yaw - row.true_yaw);
            filtered_all.push(row.filtered_yaw - row.true_yaw);
            raw_family
                .entry(family.clone())
                .or_default()
                .push(row.raw_yaw - row.true_yaw);
            filtered_family
                .entry(family.clone())
                .or_default()
                .push(row.filtered_yaw - row.true_yaw);
            position_all.push(row.position_m);
        }
        report.objects = objects;
        segments.extend(own_segments);
        raw_pose_all.extend(&report.raw_pose_samples);
        published_pose_all.extend(&report.published_pose_samples);
        true_pose_all.extend(&report.true_pose_samples);
        for (raw, published) in report.pose_frames.drain(..) {
            raw_pose_frames.push(raw);
            published_pose_frames.push(published);
        }
        if let Some(changes) = &report.changes {
            changes_all.add(changes);
        }
        reports.push(report);
    }
    let by_family = |m: BTreeMap<String, Vec<f64>>| {
        m.into_iter()
            .map(|(family, errors)| (family, metrics::angle_errors(&errors)))
            .collect()
    };
    let overall = Overall {
        recordings: reports.len(),
        with_truth: reports.iter().filter(|r| r.has_truth).count(),
        matched: reports.iter().map(|r| r.matched).sum(),
        heading_raw: metrics::angle_errors(&raw_all),
        heading_filtered: metrics::angle_errors(&filtered_all),
        heading_raw_by_family: by_family(raw_family),
        heading_filtered_by_family: by_family(filtered_family),
        position: metrics::distances(&position_all),
        changes: changes_all,
        retrieval: options
            .retrieval_frames
            .iter()
            .map(|n| metrics::retrieval(&segments, *n))
            .collect(),
        separability: options
            .separability_frames
            .iter()
            .map(|n| metrics::separability(&segments, *n))
            .collect(),
        pose_code: raw_pose_all.motion(),
        pose_code_published: published_pose_all.motion(),
        true_pose: true_pose_all.motion(),
        pose_retrieval: metrics::pose_retrieval(&raw_pose_frames),
        pose_retrieval_published: metrics::pose_retrieval(&published_pose_frames),
        objects: {
            let several: Vec<&objects::ObjectsReport> = reports.iter().filter_map(|r| r.objects.as_ref()).collect();
            (!several.is_empty()).then(|| objects::pooled(&several))
        },
    };
    Report {
        schema: "gdvae.evaluate/1",
        convention: CONVENTION,
        tolerance_frames: options.tolerance_frames,
        objects_options: options.objects,
        overall,
        recordings: reports,
    }
}

/// `truth` with every frame's `subjects` (a recording of one subject lists none: its primary).
fn with_subjects(truth: &[TruthFrame]) -> Vec<TruthFrame> {
    truth
        .iter()
        .map(|t| {
            let mut t = t.clone();
            if t.subjects.is_empty() {
                t.subjects.push(truth::SubjectTruth {
                    id: 0,
                    present: true,
                    visible_points: usize::MAX,
                    subject: t.subject.clone(),
                    family: t.family.clone(),
                    yaw: t.yaw,
                    translation: t.translation,
                });
            }
            t
        })
        .collect()
}

fn as_f32(values: &[f64]) -> Vec<f32> {
    values.iter().map(|v| *v as f32).collect()
}

fn horizontal_distance(state: &State, truth: &TruthFrame) -> f64 {
    let dx = state.centre_m[0] as f64 - truth.translation[0];
    let dy = state.centre_m[1] as f64 - truth.translation[1];
    dx.hypot(dy)
}

/// One recording's report, and its subjects' identity segments (raw z_I per matched frame).
fn recording_report(
    recording: &Recording,
    states: &[&State],
    rejected: Option<usize>,
    options: &EvaluateOptions,
) -> (RecordingReport, Vec<Segment>) {
    let truth = &recording.truth;
    let by_stamp: HashMap<u64, (usize, &TruthFrame)> =
        truth.iter().enumerate().map(|(i, t)| (t.stamp_nanos, (i, t))).collect();
    let mut subjects: Vec<String> = Vec::new();
    let mut families: Vec<String> = Vec::new();
    for t in truth {
        if !subjects.contains(&t.subject) {
            subjects.push(t.subject.clone());
        }
        if !families.contains(&t.family) {
            families.push(t.family.clone());
        }
    }
    let mut rows = Vec::new();
    let mut segments: Vec<Segment> = Vec::new();
    let mut matched_truth = vec![false; truth.len()];
    let mut reported_at = Vec::new();
    let mut raw_pose = PoseCodeSamples::default();
    let mut published_pose = PoseCodeSamples::default();
    let mut true_pose = PoseCodeSamples::default();
    let mut pose_frames = Vec::new();
    let mut previous: Option<(usize, &State)> = None;
    for state in states {
        let Some(&(index, t)) = state.stamps.sensor_ns.and_then(|s| by_stamp.get(&s)) else {
            continue;
        };
        if let Some((before, earlier)) = previous.filter(|(i, _)| *i + 1 == index && truth[*i].subject == t.subject) {
            let seconds = t.stamp_nanos.saturating_sub(truth[before].stamp_nanos) as f64 * 1e-9;
            let moved = (t.translation[0] - truth[before].translation[0])
                .hypot(t.translation[1] - truth[before].translation[1]);
            if seconds > 0.0 {
                let speed = moved / seconds;
                raw_pose.push(&state.raw.z_e, &earlier.raw.z_e, speed);
                published_pose.push(&state.filtered.z_e, &earlier.filtered.z_e, speed);
                if !t.theta.is_empty() && t.theta.len() == truth[before].theta.len() {
                    true_pose.push(&as_f32(&t.theta), &as_f32(&truth[before].theta), speed);
                }
            }
        } else {
            raw_pose.end_run();
            published_pose.end_run();
            true_pose.end_run();
        }
        if !t.theta.is_empty() {
            let frame = |code: &[f32]| PoseFrame {
                family: t.family.clone(),
                subject: t.subject.clone(),
                code: code.to_vec(),
                theta: as_f32(&t.theta),
            };
            pose_frames.push((frame(&state.raw.z_e), frame(&state.filtered.z_e)));
        }
        previous = Some((index, state));
        matched_truth[index] = true;
        if state.event.is_some() {
            reported_at.push(index);
        }
        if segments.last().is_none_or(|s| s.subject != t.subject) {
            segments.push(Segment {
                recording: recording.stream.clone(),
                subject: t.subject.clone(),
                family: t.family.clone(),
                frames: Vec::new(),
            });
        }
        if let Some(segment) = segments.last_mut() {
            segment.frames.push((state.raw.z_i.clone(), state.raw.z_i_var.clone()));
        }
        rows.push(Row {
            frame: index,
            true_yaw: t.yaw,
            raw_yaw: state.raw.yaw as f64,
            filtered_yaw: state.filtered.yaw as f64,
            filtered_yaw_std: state.filtered.yaw_std.map(|s| s as f64),
            position_m: horizontal_distance(state, t),
            subject: subjects.iter().position(|s| *s == t.subject).unwrap_or(0),
            identity: state.shape.identity,
            distance: state.shape.distance as f64,
            change_statistic: state.shape.change_statistic as f64,
            change_reported: state.event.is_some(),
        });
    }
    raw_pose.end_run();
    published_pose.end_run();
    true_pose.end_run();
    // True changes: frames whose subject differs from the frame before.
    let true_at: Vec<usize> = (1..truth.len())
        .filter(|&i| truth[i].subject != truth[i - 1].subject)
        .collect();
    let has_truth = !truth.is_empty();
    let matched = rows.len();
    let yaws: Vec<f64> = states.iter().map(|s| s.filtered.yaw as f64).collect();
    let raw: Vec<f64> = rows.iter().map(|r| r.raw_yaw - r.true_yaw).collect();
    let filtered: Vec<f64> = rows.iter().map(|r| r.filtered_yaw - r.true_yaw).collect();
    let position: Vec<f64> = rows.iter().map(|r| r.position_m).collect();
    let report = RecordingReport {
        stream: recording.stream.clone(),
        path: recording.path.display().to_string(),
        has_truth,
        truth_frames: truth.len(),
        states: states.len(),
        rejected: rejected.unwrap_or(0),
        matched,
        states_without_truth: states.len() - matched,
        truth_without_state: matched_truth.iter().filter(|m| !**m).count(),
        subjects,
        families,
        heading_raw: has_truth.then(|| metrics::angle_errors(&raw)),
        heading_filtered: has_truth.then(|| metrics::angle_errors(&filtered)),
        position: has_truth.then(|| metrics::distances(&position)),
        changes: has_truth
            .then(|| metrics::match_changes(&true_at, &reported_at, options.tolerance_frames, truth.len())),
        changes_reported: states.iter().filter(|s| s.event.is_some()).count(),
        filtered_yaw_steps: metrics::angle_steps(&yaws),
        pose_code: has_truth.then(|| raw_pose.motion()),
        pose_code_published: has_truth.then(|| published_pose.motion()),
        true_pose: (!true_pose.steps.is_empty()).then(|| true_pose.motion()),
        rows,
        raw_pose_samples: raw_pose,
        published_pose_samples: published_pose,
        true_pose_samples: true_pose,
        pose_frames,
        objects: None,
    };
    (report, segments)
}

/// A published state with the ground truth it was matched to (`None`: no frame of its recording has
/// its sensor stamp): one line of `evaluate --states`, for scripts that study the raw streams.
#[derive(Debug, Serialize)]
pub struct MatchedState<'a> {
    pub state: &'a State,
    pub truth: Option<&'a TruthFrame>,
    /// The encoder's x_c for this frame (what `python -m gdvae fit-identity` fits on).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x_c: Option<&'a [f32]>,
}

/// Every published state of `outputs`, in publishing order, with its ground truth.
pub fn matched_states<'a>(recordings: &'a [Recording], outputs: &'a [Output]) -> Vec<MatchedState<'a>> {
    let by_stamp: HashMap<(&str, u64), &TruthFrame> = recordings
        .iter()
        .flat_map(|r| r.truth.iter().map(move |t| ((r.stream.as_str(), t.stamp_nanos), t)))
        .collect();
    outputs
        .iter()
        .filter_map(|output| match output {
            Output::State(state) => Some(MatchedState {
                state,
                x_c: state.x_c.as_deref(),
                truth: state
                    .stamps
                    .sensor_ns
                    .and_then(|stamp| by_stamp.get(&(state.stream.as_str(), stamp)).copied()),
            }),
            Output::Rejected(_) => None,
        })
        .collect()
}

/// Writes one PNG per recording with ground truth into `folder`; returns the files written.
pub fn write_plots(
    report: &Report,
    folder: &Path,
    gate: f64,
    threshold: Option<f64>,
) -> Result<Vec<PathBuf>, plot::PlotError> {
    std::fs::create_dir_all(folder).map_err(|e| plot::PlotError(format!("{}: {e}", folder.display())))?;
    let mut written = Vec::new();
    for recording in report.recordings.iter().filter(|r| r.has_truth && !r.rows.is_empty()) {
        let path = folder.join(format!("{}.png", recording.stream));
        plot::recording(&path, recording, gate, threshold)?;
        written.push(path);
    }
    Ok(written)
}
