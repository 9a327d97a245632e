//! How `gdvae-node evaluate` prints its report on the terminal, and writes its matched states:
//! the report's own presentation, beside the report (`mod.rs`) it presents.

use std::path::Path;

use anyhow::Context;

use super::{MatchedState, Report};
use crate::pipeline::RunSummary;

/// The report as `gdvae-node evaluate` prints it: per recording, then overall (docs/tracking.md "Tracking
/// benchmark" says how to read each line); `summary` is the replay's own.
pub fn print(report: &Report, summary: &RunSummary) {
    println!("convention: {}", report.convention);
    println!(
        "{:<22} {:>6} {:>5} | {:>23} | {:>23} | {:>10} | {:>14} {:>5} {:>6}",
        "recording",
        "frames",
        "rej",
        "yaw raw med/p90/>30%",
        "yaw filt med/p90/>30%",
        "pos med m",
        "changes found",
        "false",
        "delay"
    );
    let angles = |a: &Option<super::metrics::AngleErrors>| match a {
        Some(a) => format!(
            "{:>6}/{:>6}/{:>5}%",
            fmt_opt(a.median_deg, 1.0, 1),
            fmt_opt(a.p90_deg, 1.0, 1),
            fmt_opt(a.over_30_deg, 100.0, 0)
        ),
        None => "no ground truth".into(),
    };
    for r in &report.recordings {
        let changes = r
            .changes
            .as_ref()
            .map(|c| {
                (
                    format!("{}/{}", c.found, c.true_changes),
                    c.false_changes.to_string(),
                    fmt_opt(c.median_delay_frames, 1.0, 0),
                )
            })
            .unwrap_or((format!("{} reported", r.changes_reported), "-".into(), "-".into()));
        println!(
            "{:<22} {:>6} {:>5} | {:>23} | {:>23} | {:>10} | {:>14} {:>5} {:>6}",
            r.stream,
            r.states,
            r.rejected,
            angles(&r.heading_raw),
            angles(&r.heading_filtered),
            fmt_opt(r.position.as_ref().and_then(|p| p.median_m), 1.0, 3),
            changes.0,
            changes.1,
            changes.2
        );
        if !r.has_truth {
            println!(
                "{:<22} filtered yaw steps: median {} deg, p90 {} deg per frame",
                "",
                fmt_opt(r.filtered_yaw_steps.median_deg, 1.0, 2),
                fmt_opt(r.filtered_yaw_steps.p90_deg, 1.0, 2)
            );
        }
        if r.truth_without_state > 0 || r.states_without_truth > 0 {
            println!(
                "{:<22} unmatched: {} truth frames without a state, {} states without truth",
                "", r.truth_without_state, r.states_without_truth
            );
        }
    }
    let o = &report.overall;
    println!(
        "overall ({} recordings, {} matched frames): heading raw {}, filtered {} (median/p90/>30%)",
        o.recordings,
        o.matched,
        angles(&Some(o.heading_raw.clone())),
        angles(&Some(o.heading_filtered.clone()))
    );
    for (family, a) in &o.heading_filtered_by_family {
        let raw = o.heading_raw_by_family.get(family).cloned();
        println!(
            "  {family:<10} heading raw {} (>150: {}%), filtered {} (>150: {}%)",
            angles(&raw),
            fmt_opt(raw.as_ref().and_then(|r| r.over_150_deg), 100.0, 0),
            angles(&Some(a.clone())),
            fmt_opt(a.over_150_deg, 100.0, 0)
        );
    }
    let c = &o.changes;
    println!(
        "  identity changes: {}/{} found within {} frames (recall {}), {} false = {} per 1000 frames, median delay {} frames",
        c.found,
        c.true_changes,
        report.tolerance_frames,
        fmt_opt(c.recall, 1.0, 3),
        c.false_changes,
        fmt_opt(c.false_per_1000_frames, 1.0, 2),
        fmt_opt(c.median_delay_frames, 1.0, 0)
    );
    println!(
        "  position (centre_m vs truth, horizontal): median {} m, p90 {} m",
        fmt_opt(o.position.median_m, 1.0, 3),
        fmt_opt(o.position.p90_m, 1.0, 3)
    );
    for r in &o.retrieval {
        println!(
            "  identity retrieval after {:>2} frames: top-1 {} (same family {}) over {} subjects",
            r.frames,
            fmt_opt(r.top1, 1.0, 3),
            fmt_opt(r.top1_same_family, 1.0, 3),
            r.queries
        );
    }
    for s in &o.separability {
        println!(
            "  z_I separability over {:>2} frames: AUC {} (same family {}), {} of {} changes above the within-subject p99.9 (same family {} of {})",
            s.frames,
            fmt_opt(s.auc, 1.0, 3),
            fmt_opt(s.auc_same_family, 1.0, 3),
            fmt_opt(s.found_at_p999, 1.0, 2),
            s.changes,
            fmt_opt(s.found_at_p999_same_family, 1.0, 2),
            s.same_family_changes
        );
    }
    for (label, p) in [("raw", &o.pose_code), ("published", &o.pose_code_published)] {
        println!(
            "  pose code z_E ({label}): frame-to-frame step walking {} / standing {}, ratio {} ({} / {} steps); \
             spread over 1 s walking {} / standing {}, ratio {} ({} / {} windows)",
            fmt_opt(p.walking_step_median, 1.0, 4),
            fmt_opt(p.standing_step_median, 1.0, 4),
            fmt_opt(p.ratio, 1.0, 2),
            p.walking_steps,
            p.standing_steps,
            fmt_opt(p.walking_spread_median, 1.0, 4),
            fmt_opt(p.standing_spread_median, 1.0, 4),
            fmt_opt(p.spread_ratio, 1.0, 2),
            p.walking_windows,
            p.standing_windows,
        );
    }
    let t = &o.true_pose;
    if t.walking_windows + t.standing_windows > 0 {
        println!(
            "  true pose (the sim's joint angles, rad): spread over 1 s walking {} / standing {}, ratio {} \
             (what a code that is exactly the pose would show on these recordings)",
            fmt_opt(t.walking_spread_median, 1.0, 3),
            fmt_opt(t.standing_spread_median, 1.0, 3),
            fmt_opt(t.spread_ratio, 1.0, 2),
        );
    }
    for (label, r) in [("raw", &o.pose_retrieval), ("published", &o.pose_retrieval_published)] {
        if r.frames > 0 {
            let families: Vec<String> = r
                .families
                .iter()
                .map(|(name, f)| format!("{name} {}", fmt_opt(f.code_ratio, 1.0, 2)))
                .collect();
            println!(
                "  pose retrieval by z_E ({label}): the nearest code among the family's other subjects is {} of the \
                 median true-pose distance away in pose (1: z_E says nothing of the pose; the nearest true pose: {}; {} frames; {})",
                fmt_opt(r.code_ratio, 1.0, 2),
                fmt_opt(r.truth_floor, 1.0, 2),
                r.frames,
                families.join(", "),
            );
        }
    }
    if let Some(pooled) = &o.objects {
        println!(
            "several objects (a track matches a subject within {} m; subjects with fewer than {} visible points ignored):",
            report.objects_options.max_distance_m, report.objects_options.min_visible_points
        );
        println!(
            "  {:<22} {:>6} {:>7} {:>6} {:>6} {:>5} {:>5} {:>6} {:>5} {:>6} {:>12} {:>13}",
            "recording",
            "frames",
            "objects",
            "MOTA",
            "IDF1",
            "IDsw",
            "frag",
            "misses",
            "FP",
            "tracks",
            "returns same",
            "yaw med/p90"
        );
        let line = |name: &str, r: &super::objects::ObjectsReport| {
            let m = &r.mot;
            let returns = &r.returns;
            println!(
                "  {:<22} {:>6} {:>7} {:>6} {:>6} {:>5} {:>5} {:>6} {:>5} {:>6} {:>12} {:>13}",
                name,
                m.frames,
                m.objects,
                fmt_opt(Some(m.mota), 1.0, 3),
                fmt_opt(Some(m.idf1), 1.0, 3),
                m.id_switches,
                m.fragmentations,
                m.misses,
                m.false_positives,
                r.tracks,
                format!(
                    "{}/{}, {}/{}",
                    returns.other_family_same_id,
                    returns.other_family,
                    returns.same_family_same_id,
                    returns.same_family
                ),
                format!(
                    "{}/{}",
                    fmt_opt(r.heading_filtered.median_deg, 1.0, 1),
                    fmt_opt(r.heading_filtered.p90_deg, 1.0, 1)
                )
            );
        };
        for r in &report.recordings {
            if let Some(objects) = &r.objects {
                line(&r.stream, objects);
            }
        }
        line("all", pooled);
        println!(
            "  ID switches per 1000 frames: {}; returns that got their id back: {}/{} with only the other family \
             in the scene, {}/{} with the same family",
            fmt_opt(Some(pooled.id_switches_per_1000_frames), 1.0, 2),
            pooled.returns.other_family_same_id,
            pooled.returns.other_family,
            pooled.returns.same_family_same_id,
            pooled.returns.same_family
        );
        let c = summary.snapshot.streams.values();
        let (born, back, ended, untracked) = c.fold((0, 0, 0, 0), |a, c| {
            (
                a.0 + c.tracks_born,
                a.1 + c.tracks_reidentified,
                a.2 + c.tracks_ended,
                a.3 + c.frames_untracked,
            )
        });
        println!(
            "  tracks: {born} born, {back} re-identified, {ended} ended; {untracked} frames had no confirmed track"
        );
    }
    let states: u64 = summary.snapshot.streams.values().map(|c| c.published).sum();
    println!(
        "  replay: {states} states in {:.1} s ({:.1} frames/s)",
        summary.busy.as_secs_f64(),
        states as f64 / summary.busy.as_secs_f64().max(1e-9)
    );
}

/// An optional figure, scaled, or "-".
fn fmt_opt(value: Option<f64>, scale: f64, decimals: usize) -> String {
    value
        .map(|v| format!("{:.*}", decimals, v * scale))
        .unwrap_or_else(|| "-".into())
}

/// `--states`: every published state as a JSON line with the ground truth it was matched to.
pub fn write_matched_states(path: &Path, states: &[MatchedState]) -> anyhow::Result<()> {
    use std::io::Write;
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    for state in states {
        serde_json::to_writer(&mut out, state)?;
        out.write_all(b"\n")?;
    }
    out.flush().with_context(|| format!("writing {}", path.display()))?;
    eprintln!("evaluate: {} state(s) in {}", states.len(), path.display());
    Ok(())
}

/// `--clouds`: the encoder's input of every state (in `states`' order) as a NumPy `.npy` array
/// [states, N_p, 3] of little-endian float32. A state without its cloud is an error (every state
/// the pipeline publishes carries it).
pub fn write_clouds(path: &Path, states: &[MatchedState]) -> anyhow::Result<()> {
    use std::io::Write;
    let clouds: Vec<&[[f32; 3]]> = states
        .iter()
        .enumerate()
        .map(|(i, s)| {
            s.state
                .prepared
                .as_deref()
                .map(Vec::as_slice)
                .ok_or_else(|| anyhow::anyhow!("state {i} (stream '{}') carries no encoder input", s.state.stream))
        })
        .collect::<anyhow::Result<_>>()?;
    let points = clouds.first().map_or(0, |c| c.len());
    if let Some((i, c)) = clouds.iter().enumerate().find(|(_, c)| c.len() != points) {
        anyhow::bail!(
            "state {i} has {} points, the first {points}: one .npy array needs one N_p",
            c.len()
        );
    }
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    out.write_all(&npy_header(&[clouds.len(), points, 3]))?;
    for point in clouds.iter().flat_map(|c| c.iter()) {
        for v in point {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush().with_context(|| format!("writing {}", path.display()))?;
    eprintln!(
        "evaluate: {} cloud(s) of {points} points in {}",
        clouds.len(),
        path.display()
    );
    Ok(())
}

/// A version 1.0 `.npy` header for a C-ordered little-endian float32 array of `shape`, padded so
/// that the data starts at a multiple of 64 bytes (the format's rule).
fn npy_header(shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat(unpadded.next_multiple_of(64) - unpadded));
    dict.push('\n');
    let mut header = b"\x93NUMPY\x01\x00".to_vec();
    header.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    header.extend_from_slice(dict.as_bytes());
    header
}
