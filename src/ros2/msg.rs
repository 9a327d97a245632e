//! The ROS 2 messages the node publishes, written as CDR (little endian, with the 4-byte
//! encapsulation header; alignment counted from after it, as Fast-CDR does), and the types it
//! reads and writes with their RIHS01 hashes (Jazzy, Kilted and Rolling agree on these).
//!
//! Only what the node sends is written: PoseStamped, TFMessage, MarkerArray (Jazzy's Marker, with
//! its texture and mesh-file fields left empty), Float32MultiArray and String. The CDR reader for
//! what it receives is `sources::ros2`.

use super::graph::MessageType;

pub const POSE_STAMPED: MessageType = MessageType {
    package: "geometry_msgs",
    name: "PoseStamped",
    hash: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
};
pub const TF_MESSAGE: MessageType = MessageType {
    package: "tf2_msgs",
    name: "TFMessage",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
};
pub const MARKER_ARRAY: MessageType = MessageType {
    package: "visualization_msgs",
    name: "MarkerArray",
    hash: "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
};
pub const FLOAT32_MULTI_ARRAY: MessageType = MessageType {
    package: "std_msgs",
    name: "Float32MultiArray",
    hash: "RIHS01_0599f6f85b4bfca379873a0b4375a0aca022156bd2d7021275d116ed1fa8bfe0",
};
pub const STRING: MessageType = MessageType {
    package: "std_msgs",
    name: "String",
    hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
};
/// vision_msgs 4.1.1 (Jazzy's): the convention of ROS 2 perception nodes for 3D detections.
pub const DETECTION3D_ARRAY: MessageType = MessageType {
    package: "vision_msgs",
    name: "Detection3DArray",
    hash: "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018",
};
pub const POINT_CLOUD2: MessageType = MessageType {
    package: "sensor_msgs",
    name: "PointCloud2",
    hash: "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
};
pub const IMAGE: MessageType = MessageType {
    package: "sensor_msgs",
    name: "Image",
    hash: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
};
pub const CAMERA_INFO: MessageType = MessageType {
    package: "sensor_msgs",
    name: "CameraInfo",
    hash: "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
};

/// A CDR little-endian stream with its encapsulation header.
pub struct CdrWriter {
    bytes: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        Self {
            bytes: vec![0x00, 0x01, 0x00, 0x00],
        }
    }

    fn align(&mut self, n: usize) {
        let position = self.bytes.len() - 4;
        let padding = (n - position % n) % n;
        self.bytes.resize(self.bytes.len() + padding, 0);
    }

    pub fn u8(&mut self, value: u8) {
        self.bytes.push(value);
    }

    pub fn bool(&mut self, value: bool) {
        self.bytes.push(value as u8);
    }

    pub fn u32(&mut self, value: u32) {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn i32(&mut self, value: i32) {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn f32(&mut self, value: f32) {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    pub fn f64(&mut self, value: f64) {
        self.align(8);
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }

    /// A string: its length with the terminating NUL, the bytes, the NUL.
    pub fn string(&mut self, value: &str) {
        self.u32(value.len() as u32 + 1);
        self.bytes.extend_from_slice(value.as_bytes());
        self.bytes.push(0);
    }

    /// A sequence's length (its elements follow).
    pub fn length(&mut self, n: usize) {
        self.u32(n as u32);
    }

    pub fn finish(self) -> Vec<u8> {
        self.bytes
    }
}

/// `std_msgs/Header`: a stamp (ns since the Unix epoch) and a frame id.
#[derive(Debug, Clone, Copy)]
pub struct Header<'a> {
    pub stamp_ns: u64,
    pub frame_id: &'a str,
}

impl Header<'_> {
    fn write(&self, w: &mut CdrWriter) {
        w.i32((self.stamp_ns / 1_000_000_000).min(i32::MAX as u64) as i32);
        w.u32((self.stamp_ns % 1_000_000_000) as u32);
        w.string(self.frame_id);
    }
}

/// A rigid pose: position (metres) and orientation as ROS orders it, [x, y, z, w].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position: [f64; 3],
    pub orientation: [f64; 4],
}

impl Pose {
    fn write(&self, w: &mut CdrWriter) {
        self.position.iter().for_each(|v| w.f64(*v));
        self.orientation.iter().for_each(|v| w.f64(*v));
    }
}

/// `geometry_msgs/msg/PoseStamped`.
pub fn pose_stamped(header: &Header, pose: &Pose) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header.write(&mut w);
    pose.write(&mut w);
    w.finish()
}

/// One object of a `vision_msgs/msg/Detection3DArray`.
pub struct Detection<'a> {
    /// The object's id (a track's, or its identity).
    pub id: &'a str,
    /// Its one hypothesis: a class name and a score in [0, 1].
    pub class_id: &'a str,
    pub score: f64,
    /// The object's pose (the hypothesis' pose and the box's centre).
    pub pose: Pose,
    /// The box's size along the pose's axes (m).
    pub size: [f64; 3],
}

/// `vision_msgs/msg/Detection3DArray`: each detection with the array's header, one
/// `ObjectHypothesisWithPose` (covariance left zero: unknown) and its box.
pub fn detection3d_array(header: &Header, detections: &[Detection]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header.write(&mut w);
    w.length(detections.len());
    for d in detections {
        header.write(&mut w);
        w.length(1);
        w.string(d.class_id);
        w.f64(d.score);
        d.pose.write(&mut w);
        (0..36).for_each(|_| w.f64(0.0));
        d.pose.write(&mut w);
        d.size.iter().for_each(|v| w.f64(*v));
        w.string(d.id);
    }
    w.finish()
}

/// `tf2_msgs/msg/TFMessage` with one `TransformStamped` per (header, child frame, pose).
pub fn tf_message(transforms: &[(Header, &str, Pose)]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.length(transforms.len());
    for (header, child, pose) in transforms {
        header.write(&mut w);
        w.string(child);
        pose.write(&mut w);
    }
    w.finish()
}

/// `std_msgs/msg/Float32MultiArray`: one dimension named `label`.
pub fn float32_multi_array(label: &str, data: &[f32]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.length(1);
    w.string(label);
    w.u32(data.len() as u32);
    w.u32(data.len() as u32);
    w.u32(0);
    w.length(data.len());
    data.iter().for_each(|v| w.f32(*v));
    w.finish()
}

/// `std_msgs/msg/String`.
pub fn string(text: &str) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.string(text);
    w.finish()
}

/// Marker types the node draws.
pub const MARKER_ARROW: i32 = 0;
pub const MARKER_POINTS: i32 = 8;
pub const MARKER_TEXT: i32 = 9;

/// One `visualization_msgs/msg/Marker` (action ADD).
#[derive(Debug, Clone)]
pub struct Marker<'a> {
    pub header: Header<'a>,
    pub namespace: &'a str,
    pub id: i32,
    pub kind: i32,
    pub pose: Pose,
    pub scale: [f64; 3],
    /// r, g, b, a in 0..=1.
    pub color: [f32; 4],
    /// How long rviz keeps it without an update (ns; 0: forever).
    pub lifetime_ns: u64,
    /// POINTS: the points, in the marker's pose.
    pub points: &'a [[f32; 3]],
    /// TEXT_VIEW_FACING: the text.
    pub text: &'a str,
}

/// `visualization_msgs/msg/MarkerArray`.
pub fn marker_array(markers: &[Marker]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.length(markers.len());
    for m in markers {
        m.header.write(&mut w);
        w.string(m.namespace);
        w.i32(m.id);
        w.i32(m.kind);
        w.i32(0); // action: ADD
        m.pose.write(&mut w);
        m.scale.iter().for_each(|v| w.f64(*v));
        m.color.iter().for_each(|v| w.f32(*v));
        w.i32((m.lifetime_ns / 1_000_000_000).min(i32::MAX as u64) as i32);
        w.u32((m.lifetime_ns % 1_000_000_000) as u32);
        w.bool(false); // frame_locked
        w.length(m.points.len());
        for p in m.points {
            p.iter().for_each(|v| w.f64(*v as f64));
        }
        w.length(0); // colors
        w.string(""); // texture_resource
        Header {
            stamp_ns: 0,
            frame_id: "",
        }
        .write(&mut w); // texture: CompressedImage header
        w.string(""); // texture.format
        w.length(0); // texture.data
        w.length(0); // uv_coordinates
        w.string(m.text);
        w.string(""); // mesh_resource
        w.string(""); // mesh_file.filename
        w.length(0); // mesh_file.data
        w.bool(false); // mesh_use_embedded_materials
    }
    w.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pose_stamped_is_laid_out_as_cdr() {
        let bytes = pose_stamped(
            &Header {
                stamp_ns: 1_500_000_001,
                frame_id: "map",
            },
            &Pose {
                position: [1.0, 2.0, 3.0],
                orientation: [0.0, 0.0, 0.0, 1.0],
            },
        );
        // header 4 | sec 4 | nanosec 4 | len 4 | "map\0" 4 | pad to 8 (position 16 -> 16) | 7 f64
        assert_eq!(&bytes[..4], &[0, 1, 0, 0]);
        assert_eq!(i32::from_le_bytes(bytes[4..8].try_into().unwrap()), 1);
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 500_000_001);
        assert_eq!(u32::from_le_bytes(bytes[12..16].try_into().unwrap()), 4);
        assert_eq!(&bytes[16..20], b"map\0");
        assert_eq!(bytes.len(), 20 + 7 * 8);
        assert_eq!(f64::from_le_bytes(bytes[20..28].try_into().unwrap()), 1.0);
    }
}
