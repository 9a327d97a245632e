//! ROS 2 messages the sim emits, encoded as CDR (little-endian XCDR1, as rmw and rosbag2 write
//! them) with their `.msg` schema text for MCAP's `ros2msg` schema encoding.
//!
//! Only what the recordings and feeds need: `sensor_msgs/msg/PointCloud2` (x, y, z as float32),
//! `sensor_msgs/msg/Image` (16UC1 depth) and `sensor_msgs/msg/CameraInfo`. Written by hand because
//! the three layouts are small and fixed, and a ROS 2 installation cannot be assumed here.

use crate::camera::{DepthImage, Intrinsics};

/// A ROS 2 `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stamp {
    pub sec: i32,
    pub nanosec: u32,
}

impl Stamp {
    pub fn from_nanos(nanos: u64) -> Self {
        Self {
            sec: (nanos / 1_000_000_000) as i32,
            nanosec: (nanos % 1_000_000_000) as u32,
        }
    }
}

/// CDR serialisation with alignment measured from the end of the 4-byte encapsulation header.
struct CdrWriter {
    buffer: Vec<u8>,
}

impl CdrWriter {
    /// Representation identifier CDR_LE, options 0.
    fn new(capacity: usize) -> Self {
        let mut buffer = Vec::with_capacity(capacity + 4);
        buffer.extend_from_slice(&[0x00, 0x01, 0x00, 0x00]);
        Self { buffer }
    }

    fn align(&mut self, alignment: usize) {
        let offset = self.buffer.len() - 4;
        let padding = (alignment - offset % alignment) % alignment;
        self.buffer.extend(std::iter::repeat_n(0u8, padding));
    }

    fn u8(&mut self, value: u8) {
        self.buffer.push(value);
    }

    fn u32(&mut self, value: u32) {
        self.align(4);
        self.buffer.extend_from_slice(&value.to_le_bytes());
    }

    fn i32(&mut self, value: i32) {
        self.align(4);
        self.buffer.extend_from_slice(&value.to_le_bytes());
    }

    fn f64(&mut self, value: f64) {
        self.align(8);
        self.buffer.extend_from_slice(&value.to_le_bytes());
    }

    fn string(&mut self, value: &str) {
        self.u32(value.len() as u32 + 1);
        self.buffer.extend_from_slice(value.as_bytes());
        self.buffer.push(0);
    }

    fn bytes(&mut self, value: &[u8]) {
        self.u32(value.len() as u32);
        self.buffer.extend_from_slice(value);
    }

    fn header(&mut self, stamp: Stamp, frame_id: &str) {
        self.i32(stamp.sec);
        self.u32(stamp.nanosec);
        self.string(frame_id);
    }

    fn finish(self) -> Vec<u8> {
        self.buffer
    }
}

/// `sensor_msgs/msg/PointField` datatype code for float32.
const FLOAT32: u8 = 7;

/// An unorganised cloud (height 1) of float32 x, y, z, 12 bytes per point.
pub fn point_cloud2(stamp: Stamp, frame_id: &str, points: &[[f32; 3]]) -> Vec<u8> {
    let mut cdr = CdrWriter::new(points.len() * 12 + 128);
    cdr.header(stamp, frame_id);
    cdr.u32(1);
    cdr.u32(points.len() as u32);
    cdr.u32(3);
    for (index, name) in ["x", "y", "z"].into_iter().enumerate() {
        cdr.string(name);
        cdr.u32(4 * index as u32);
        cdr.u8(FLOAT32);
        cdr.u32(1);
    }
    cdr.u8(0); // is_bigendian
    cdr.u32(12); // point_step
    cdr.u32(12 * points.len() as u32); // row_step
    let mut data = Vec::with_capacity(points.len() * 12);
    for point in points {
        for coordinate in point {
            data.extend_from_slice(&coordinate.to_le_bytes());
        }
    }
    cdr.bytes(&data);
    cdr.u8(1); // is_dense: invalid pixels were left out
    cdr.finish()
}

/// A 16UC1 depth image in millimetres (0 = no measurement), as the OAK-D driver publishes.
pub fn depth_image(stamp: Stamp, frame_id: &str, image: &DepthImage) -> Vec<u8> {
    let mut cdr = CdrWriter::new(image.millimetres.len() * 2 + 128);
    cdr.header(stamp, frame_id);
    cdr.u32(image.height);
    cdr.u32(image.width);
    cdr.string("16UC1");
    cdr.u8(0);
    cdr.u32(2 * image.width);
    let data: Vec<u8> = image.millimetres.iter().flat_map(|d| d.to_le_bytes()).collect();
    cdr.bytes(&data);
    cdr.finish()
}

/// Calibration of a rectified, distortion-free depth image.
pub fn camera_info(stamp: Stamp, frame_id: &str, intrinsics: &Intrinsics) -> Vec<u8> {
    let mut cdr = CdrWriter::new(512);
    cdr.header(stamp, frame_id);
    cdr.u32(intrinsics.height);
    cdr.u32(intrinsics.width);
    cdr.string("plumb_bob");
    cdr.u32(5);
    for _ in 0..5 {
        cdr.f64(0.0);
    }
    for value in intrinsics.matrix() {
        cdr.f64(value);
    }
    for value in [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
        cdr.f64(value);
    }
    let i = intrinsics;
    for value in [i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0] {
        cdr.f64(value);
    }
    cdr.u32(0); // binning_x
    cdr.u32(0); // binning_y
    for _ in 0..4 {
        cdr.u32(0); // roi x_offset, y_offset, height, width
    }
    cdr.u8(0); // roi do_rectify
    cdr.finish()
}

const SEPARATOR: &str = "================================================================================\n";

const HEADER_MSG: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const TIME_MSG: &str = "int32 sec\nuint32 nanosec\n";

fn with_dependencies(main: &str, dependencies: &[(&str, &str)]) -> String {
    let mut text = main.to_string();
    for (name, definition) in dependencies {
        text.push_str(SEPARATOR);
        text.push_str(&format!("MSG: {name}\n"));
        text.push_str(definition);
    }
    text
}

/// `ros2msg` schema text of `sensor_msgs/msg/PointCloud2`, with its dependencies.
pub fn point_cloud2_schema() -> String {
    with_dependencies(
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n\
         uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
        &[
            ("std_msgs/Header", HEADER_MSG),
            ("builtin_interfaces/Time", TIME_MSG),
            (
                "sensor_msgs/PointField",
                "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n\
                 uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
            ),
        ],
    )
}

/// `ros2msg` schema text of `sensor_msgs/msg/Image`.
pub fn image_schema() -> String {
    with_dependencies(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n\
         uint32 step\nuint8[] data\n",
        &[("std_msgs/Header", HEADER_MSG), ("builtin_interfaces/Time", TIME_MSG)],
    )
}

/// `ros2msg` schema text of `sensor_msgs/msg/CameraInfo`.
pub fn camera_info_schema() -> String {
    with_dependencies(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n\
         float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n\
         RegionOfInterest roi\n",
        &[
            ("std_msgs/Header", HEADER_MSG),
            ("builtin_interfaces/Time", TIME_MSG),
            (
                "sensor_msgs/RegionOfInterest",
                "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
            ),
        ],
    )
}
