//! Sources of frames: files and folders (`files`), ROS 2 messages in CDR (`ros2`), MCAP replay and
//! zenoh subscriptions (to come). Each source produces `cloud::Frame`s tagged with its stream id.

pub mod files;
pub mod ros2;
