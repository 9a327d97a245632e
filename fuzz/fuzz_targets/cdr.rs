//! One network sample through every payload decoder: CDR PointCloud2, CameraInfo, a depth Image
//! with the intrinsics the same bytes give (or a fixed camera), and the DepthAI float32 payload.
#![no_main]

use gdvae_node::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2, CameraIntrinsics};
use gdvae_node::sources::zenoh::decode_depthai;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = decode_point_cloud2(data, 100_000);
    let _ = decode_depthai(data, 100_000);
    let fixed = CameraIntrinsics {
        width: 64,
        height: 40,
        fx: 50.0,
        fy: 50.0,
        cx: 32.0,
        cy: 20.0,
    };
    let _ = decode_depth_image(data, &fixed, 1, 100_000);
    if let Ok((_, k)) = decode_camera_info(data) {
        let _ = decode_depth_image(data, &k, 1, 100_000);
    }
});
