//! The published state of one encoded frame: the encoder's own output for this frame (`raw`) and
//! what the stream's filters make of it (`filtered`, `shape`).

use super::pose::confidence_from_log_variance;
use super::stream::StreamTracker;
use crate::encoding::Encoding;
use crate::state::{self, State};

/// One encoded frame, as the track stage receives it.
pub struct Observed<'a> {
    pub stream: &'a str,
    pub sequence: u64,
    pub sensor_stamp_ns: Option<u64>,
    pub ingest_unix_ns: u64,
    pub points_received: usize,
    pub points_kept: usize,
    /// The centre prepare subtracted (metres, gravity frame).
    pub centre_m: [f32; 3],
    pub encoding: &'a Encoding,
    /// The stages' times so far (`total_ms` is the publisher's to measure).
    pub latency: state::StageLatency,
}

fn variances(log_variance: &[f32]) -> Vec<f32> {
    log_variance.iter().map(|lv| lv.clamp(-20.0, 20.0).exp()).collect()
}

impl StreamTracker {
    /// Updates the stream's filters with `frame` (`dt` seconds after the previous one) and builds
    /// its published state.
    pub fn state(&mut self, node: &str, frame: &Observed, dt: f32) -> State {
        let e = frame.encoding;
        let tracked = self.update_coded(
            (&e.z_i_mean, &e.z_i_logvar),
            &e.x_c,
            (e.q, e.yaw_spread),
            &e.z_e_mean,
            frame.centre_m,
            dt,
        );
        let update = tracked.shape;
        if let Some(change) = update.change {
            log::info!(
                "stream '{}' frame {}: identity changed ({} -> {})",
                frame.stream,
                frame.sequence,
                change.previous,
                change.identity
            );
        }
        let pose = tracked.pose;
        State {
            schema: state::STATE_SCHEMA.into(),
            node: node.to_string(),
            stream: frame.stream.to_string(),
            sequence: frame.sequence,
            track: None,
            stamps: state::Stamps {
                sensor_ns: frame.sensor_stamp_ns,
                ingest_ns: frame.ingest_unix_ns,
                publish_ns: 0, // stamped by the publisher
            },
            latency: frame.latency.clone(),
            points: state::Points {
                received: frame.points_received,
                kept: frame.points_kept,
            },
            centre_m: frame.centre_m,
            raw: state::Raw {
                q: pose.q_raw,
                yaw: pose.yaw_raw,
                q_confidence: confidence_from_log_variance(&e.z_r_logvar),
                yaw_spread: e.yaw_spread,
                z_e: e.z_e_mean.clone(),
                z_e_var: variances(&e.z_e_logvar),
                z_i: e.z_i_mean.clone(),
                z_i_var: variances(&e.z_i_logvar),
            },
            filtered: state::Filtered {
                q: pose.q,
                yaw: pose.yaw,
                yaw_std: tracked.heading.map(|h| h.yaw_std as f32),
                z_e: pose.z_e,
                z_e_confidence: confidence_from_log_variance(&e.z_e_logvar),
            },
            shape: state::Shape {
                identity: self.shape.identity(),
                z_i: self.shape.mean().to_vec(),
                z_i_var: self.shape.variance(),
                frames_fused: self.shape.frames_fused(),
                inlier: update.inlier,
                distance: update.distance,
                confidence: self.shape.confidence(),
                change_statistic: update.statistic,
            },
            event: update.change.map(|c| state::IdentityEvent {
                kind: "identity_change".into(),
                previous: c.previous,
                identity: c.identity,
            }),
            prepared: None,
            input: None,
            sensor_frame: None,
            of_frame: None,
            x_c: Some(e.x_c.as_slice().into()),
        }
    }
}
