//! ROS 2 on the wire, as rmw_zenoh carries it: graph conventions (keys, liveliness tokens, QoS,
//! attachments; `graph`) and the messages the node writes (`msg`). Shared by the ROS 2 sink
//! (`publish::ros2`) and the ROS 2 source (`sources::zenoh` with `kind = "ros2"`); the CDR reader
//! for incoming messages is `sources::ros2`.

pub mod graph;
pub mod msg;
