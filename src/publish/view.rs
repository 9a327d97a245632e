//! What a viewer draws of one state, as Foxglove's schemas say it (`[publish.view]`): the object's
//! frame in the gravity frame, the input cloud (decimated), the N_p points the encoder saw, the
//! decoded canonical shape placed at the estimated pose, and a scene with the heading arrow and a
//! label with the identity and its confidence. The Foxglove live view sends these messages and the
//! MCAP recording writes them, on the same topics under the same schemas, so that a recorded run
//! looks in Foxglove as the live one did.

use foxglove::messages::packed_element_field::NumericType;
use foxglove::messages::{
    ArrowPrimitive, Color, FrameTransform, PackedElementField, PointCloud, Pose, Quaternion, SceneEntity, SceneUpdate,
    TextPrimitive, Timestamp, Vector3,
};
use serde::{Deserialize, Serialize};

use crate::state::State;

/// `[publish.view]`: what the Foxglove view and the MCAP recording show.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ViewSettings {
    /// The input cloud, decimated to at most this many points (every k-th point); 0: not shown.
    pub input_points: usize,
    /// How often a stream's decoded shape is renewed (per second); 0: no decoded shape.
    pub shape_rate_hz: f64,
    /// The gravity frame's name (the parent of each stream's object frame).
    pub frame_id: String,
}

impl Default for ViewSettings {
    fn default() -> Self {
        Self {
            input_points: 2048,
            shape_rate_hz: 5.0,
            frame_id: "gravity".into(),
        }
    }
}

impl ViewSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.frame_id.is_empty() {
            return Err("publish.view.frame_id must be set".into());
        }
        if !(self.shape_rate_hz >= 0.0 && self.shape_rate_hz.is_finite()) {
            return Err("publish.view.shape_rate_hz must be finite and >= 0".into());
        }
        Ok(())
    }
}

/// The view's topics of one stream, as the Foxglove server and the MCAP file name them.
pub fn topic(stream: &str, what: &str) -> String {
    format!("/gdvae/{stream}/{what}")
}

/// The messages of one state.
pub struct Scene {
    pub transform: FrameTransform,
    /// The N_p points the encoder saw, in metres in the gravity frame.
    pub points: Option<PointCloud>,
    /// The input cloud (decimated), in metres in the gravity frame.
    pub input: Option<PointCloud>,
    /// The decoded canonical shape at the estimated centre and rotation.
    pub shape: Option<PointCloud>,
    pub scene: SceneUpdate,
}

/// The scene of `state` (`shape`: its stream's latest decoded shape, metres; `metres_per_unit`:
/// the bundle's model units back to metres).
pub fn scene(state: &State, shape: Option<&[[f32; 3]]>, frame_id: &str, metres_per_unit: f32) -> Scene {
    let stamp = state.stamps.sensor_ns.unwrap_or(state.stamps.ingest_ns);
    let timestamp = Some(Timestamp::new(
        (stamp / 1_000_000_000) as u32,
        (stamp % 1_000_000_000) as u32,
    ));
    let c = state.centre_m;
    let centre = Vector3 {
        x: c[0] as f64,
        y: c[1] as f64,
        z: c[2] as f64,
    };
    let cloud = |points: &mut dyn Iterator<Item = [f32; 3]>, pose: Option<Pose>| PointCloud {
        timestamp,
        frame_id: frame_id.to_string(),
        pose,
        point_stride: 12,
        fields: ["x", "y", "z"]
            .iter()
            .zip([0, 4, 8])
            .map(|(name, offset)| PackedElementField {
                name: (*name).into(),
                offset,
                r#type: NumericType::Float32 as i32,
            })
            .collect(),
        data: points
            .flat_map(|p| p.into_iter().flat_map(f32::to_le_bytes))
            .collect::<Vec<u8>>()
            .into(),
    };
    let points = state.prepared.as_deref().map(|points| {
        cloud(
            &mut points
                .iter()
                .map(|p| std::array::from_fn(|a| p[a] * metres_per_unit + c[a])),
            None,
        )
    });
    let input = state
        .input
        .as_deref()
        .map(|points| cloud(&mut points.iter().copied(), None));
    let [w, x, y, z] = state.filtered.q.map(f64::from);
    let shape = shape.map(|points| {
        cloud(
            &mut points.iter().copied(),
            Some(Pose {
                position: Some(centre.clone()),
                orientation: Some(Quaternion { x, y, z, w }),
            }),
        )
    });
    let object_frame = format!("gdvae/{}", state.object_name());
    let half = 0.5 * state.filtered.yaw as f64;
    let transform = FrameTransform {
        timestamp,
        parent_frame_id: frame_id.to_string(),
        child_frame_id: object_frame.clone(),
        translation: Some(centre),
        rotation: Some(Quaternion {
            x: 0.0,
            y: 0.0,
            z: half.sin(),
            w: half.cos(),
        }),
    };
    Scene {
        transform,
        points,
        input,
        shape,
        scene: label_and_arrow(state, object_frame, timestamp),
    }
}

/// The heading arrow along the object frame's x axis and the label above it: green while the
/// frame agrees with the fused shape, orange when it is an outlier.
fn label_and_arrow(state: &State, object_frame: String, timestamp: Option<Timestamp>) -> SceneUpdate {
    let at = |x: f64, z: f64| {
        Some(Pose {
            position: Some(Vector3 { x, y: 0.0, z }),
            orientation: Some(Quaternion {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 1.0,
            }),
        })
    };
    let (r, g, b) = if state.shape.inlier {
        (0.1, 0.8, 0.3)
    } else {
        (0.9, 0.5, 0.1)
    };
    let colour = Some(Color { r, g, b, a: 1.0 });
    SceneUpdate {
        deletions: vec![],
        entities: vec![SceneEntity {
            timestamp,
            frame_id: object_frame,
            id: state.object_name().into_owned(),
            frame_locked: true,
            arrows: vec![ArrowPrimitive {
                pose: at(0.0, 0.0),
                shaft_length: 0.4,
                shaft_diameter: 0.03,
                head_length: 0.12,
                head_diameter: 0.08,
                color: colour.clone(),
            }],
            texts: vec![TextPrimitive {
                pose: at(0.0, 0.5),
                billboard: true,
                font_size: 14.0,
                scale_invariant: true,
                color: colour,
                text: format!(
                    "{} identity {} ({}conf {:.2})",
                    state.object_name(),
                    state.shape.identity,
                    if state.shape.inlier { "" } else { "outlier, " },
                    state.shape.confidence
                ),
            }],
            ..Default::default()
        }],
    }
}
