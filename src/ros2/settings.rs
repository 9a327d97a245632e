//! `[publish.ros2]`: how the node names itself in a ROS 2 graph (domain, namespace, node name,
//! enclave, frames, QoS). Read by the ROS 2 participants here, and through them by both the ROS 2
//! sink and the ROS 2 source, so it lives below both.

use serde::{Deserialize, Serialize};

/// `[publish.ros2]`: the node in a ROS 2 graph.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Ros2Settings {
    /// Publish to ROS 2 (rmw_zenoh). Join a graph by connecting `[zenoh]` to its router
    /// (`rmw_zenohd`, `tcp/localhost:7447`).
    pub enabled: bool,
    /// ROS_DOMAIN_ID.
    pub domain_id: u32,
    /// The node's namespace; its topics are `<namespace>/<stream>/...`.
    pub namespace: String,
    pub node_name: String,
    /// The security enclave ("/" unless SROS 2 is used).
    pub enclave: String,
    /// The gravity-aligned frame poses are given in (the parent of every object frame on /tf).
    pub frame_id: String,
    /// An object's frame on /tf is this prefix followed by its stream name.
    pub object_frame_prefix: String,
    /// QoS of the data topics as advertised to the graph: reliable (else best effort), keep last
    /// `depth`, volatile. (On the wire, live runs drop under congestion, replays block.)
    pub reliable: bool,
    pub depth: usize,
    /// Also publish on /tf (reliable, keep last 100, as tf2 broadcasters do).
    pub tf: bool,
    /// Also publish each stream's sensor pose on /tf_static (`frame_id` -> the frame its clouds
    /// name), as tf2's static broadcaster does (reliable, transient local, keep last 1): rviz2
    /// then shows the input clouds and the markers together.
    pub tf_static: bool,
    /// Publish markers for rviz2.
    pub markers: bool,
    /// Publish `<ns>/<stream>/detections` (vision_msgs/msg/Detection3DArray, as ROS 2 perception
    /// nodes do): the object's id, score, pose and box.
    pub detections: bool,
    /// How often per stream the decoded canonical shape is refreshed (Hz; 0: no shape marker).
    pub shape_rate_hz: f64,
}

impl Default for Ros2Settings {
    fn default() -> Self {
        Self {
            enabled: false,
            domain_id: 0,
            namespace: "/gdvae".into(),
            node_name: "gdvae_node".into(),
            enclave: "/".into(),
            frame_id: "gravity".into(),
            object_frame_prefix: String::new(),
            reliable: true,
            depth: 10,
            tf: true,
            tf_static: true,
            markers: true,
            detections: true,
            shape_rate_hz: 1.0,
        }
    }
}

/// A ROS 2 name segment: a letter or underscore, then letters, digits, underscores.
fn is_name(segment: &str) -> bool {
    let mut chars = segment.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

impl Ros2Settings {
    /// Checks every value; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        let namespace_ok =
            self.namespace == "/" || (self.namespace.starts_with('/') && self.namespace[1..].split('/').all(is_name));
        if !namespace_ok {
            return Err(format!(
                "publish.ros2.namespace '{}' must be \"/\" or absolute, like \"/robot/gdvae\" (letters, digits, underscores)",
                self.namespace
            ));
        }
        if !is_name(&self.node_name) {
            return Err(format!(
                "publish.ros2.node_name '{}' must be a ROS 2 name (letters, digits, underscores)",
                self.node_name
            ));
        }
        if !self.enclave.starts_with('/') {
            return Err(format!("publish.ros2.enclave '{}' must start with '/'", self.enclave));
        }
        if self.frame_id.is_empty() {
            return Err("publish.ros2.frame_id must not be empty".into());
        }
        if self.domain_id > 232 {
            return Err(format!(
                "publish.ros2.domain_id {} must be within 0..=232",
                self.domain_id
            ));
        }
        if self.depth == 0 {
            return Err("publish.ros2.depth must be at least 1".into());
        }
        if !(self.shape_rate_hz >= 0.0 && self.shape_rate_hz.is_finite()) {
            return Err("publish.ros2.shape_rate_hz must be finite and >= 0".into());
        }
        Ok(())
    }

    /// The topic a stream's `what` is published on.
    pub fn topic(&self, stream: &str, what: &str) -> String {
        format!("{}/{stream}/{what}", self.namespace.trim_end_matches('/'))
    }
}
