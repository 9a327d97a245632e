//! A whole MCAP file through what the replay does with it: the bounded scan, the bounded message
//! reader over the sound prefix (chunk decompression included), and the decoders of every
//! message of the kinds the node reads.
#![no_main]

use gdvae_node::sources::mcap::{messages, scan};
use gdvae_node::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(scanned) = scan(data) else { return };
    let mut intrinsics = None;
    for message in messages(&data[..scanned.sound_bytes]).take(10_000) {
        let Ok(message) = message else { break };
        let _ = decode_point_cloud2(&message.data, 100_000);
        if let Ok((_, k)) = decode_camera_info(&message.data) {
            intrinsics = Some(k);
        }
        if let Some(k) = &intrinsics {
            let _ = decode_depth_image(&message.data, k, 2, 100_000);
        }
    }
});
