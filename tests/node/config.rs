//! The shipped configs parse and validate; typos and bad values are refused with the key named.

use gdvae_node::config::{Config, Input};

use crate::helpers::repo;

#[test]
fn every_shipped_config_parses_and_validates() {
    let mut checked = 0;
    for entry in std::fs::read_dir(repo().join("config")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let config = Config::load(&path).unwrap_or_else(|e| panic!("{e}"));
            assert!(!config.sources.is_empty(), "{}: no sources", path.display());
            checked += 1;
        }
    }
    assert!(checked >= 4, "default + replay, zenoh and DepthAI examples");
}

#[test]
fn the_default_config_replays_the_sample_with_the_shipped_bundle() {
    let config = Config::load(&repo().join("config/default.toml")).unwrap();
    assert!(config.model.bundle.join("manifest.json").is_file());
    let source = &config.sources[0];
    let Input::Mcap(recording) = &source.input else {
        panic!("the default source replays the sample recording")
    };
    assert!(
        recording.path.is_file(),
        "relative paths resolve against the config's folder"
    );
    assert!(config.publish.zenoh && config.zenoh.mode.is_none() && config.zenoh.connect.is_none());
}

#[test]
fn an_empty_config_is_the_documented_defaults() {
    let empty = Config::parse("").unwrap();
    empty.validate().unwrap();
    let documented = Config::load(&repo().join("config/default.toml")).unwrap();
    // The file documents the defaults; where it deliberately differs (the sample's camera pose,
    // crop and source, and a path relative to config/) it says so in its comments.
    assert_eq!(empty.track.shape_gate, documented.track.shape_gate);
    assert_eq!(empty.track.switch_frames, documented.track.switch_frames);
    assert_eq!(empty.track.change_detector, documented.track.change_detector);
    assert_eq!(
        empty.track.use_identity_projection,
        documented.track.use_identity_projection
    );
    assert_eq!(
        (empty.track.step_window, empty.track.step_reference),
        (documented.track.step_window, documented.track.step_reference)
    );
    assert_eq!(
        [
            empty.track.step_threshold,
            empty.track.step_min_variance,
            empty.track.step_clip
        ],
        [
            documented.track.step_threshold,
            documented.track.step_min_variance,
            documented.track.step_clip
        ]
    );
    assert_eq!(empty.model.max_batch, documented.model.max_batch);
    assert_eq!(empty.pipeline.queue, documented.pipeline.queue);
    assert_eq!(empty.prepare.min_points, documented.prepare.min_points);
    assert_eq!(empty.prepare.outliers.method, documented.prepare.outliers.method);
}

#[test]
fn unknown_keys_are_refused() {
    let error = Config::parse("[model]\nmax_batchh = 4\n").unwrap_err();
    assert!(error.contains("max_batchh"), "{error}");
    let error = Config::parse("[[source]]\nstream = \"a\"\nkind = \"files\"\npaht = \"x\"\n").unwrap_err();
    assert!(error.contains("paht"), "{error}");
}

#[test]
fn bad_values_are_refused_with_the_key_named() {
    let cases = [
        ("[model]\nmax_batch = 0\n", "max_batch"),
        ("[prepare]\ncrop = [1.0, 0.0, 0.0, 0.0, 1.0, 1.0]\n", "crop"),
        ("[prepare]\ncluster_join_m = -0.1\n", "prepare.cluster_join_m"),
        ("[track]\nmotion_min_travel_m = -0.5\n", "track.motion_min_travel_m"),
        ("[track]\nstep_reference = 3\n", "track.step_reference"),
        ("[track]\nstep_window = 0\n", "track.step_window"),
        ("[track]\nstep_clip = 0.0\n", "track.step_clip"),
        ("[track]\nstep_min_variance = -1.0\n", "track.step_min_variance"),
        ("[prepare]\ncluster_join_m = nan\n", "prepare.cluster_join_m"),
        (
            "[prepare]\nsensor_to_gravity_rotation = [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n",
            "sensor_to_gravity_rotation",
        ),
        ("[zenoh]\nmode = \"router\"\n", "zenoh.mode"),
        ("[zenoh]\nmode = \"client\"\n", "connect"),
        ("[[source]]\nstream = \"a\"\nkind = \"mcap\"\n", "path"),
        ("[[source]]\nstream = \"a/b*\"\nkind = \"zenoh\"\nkey = \"k\"\n", "stream"),
        (
            "[[source]]\nstream = \"a\"\nkind = \"zenoh\"\nkey = \"k\"\n[[source]]\nstream = \"a\"\nkind = \"zenoh\"\nkey = \"j\"\n",
            "two sources",
        ),
        ("[node]\nname = \"\"\n", "node.name"),
        (
            "[[source]]\nstream = \"a\"\nkind = \"files\"\npath = \"x\"\nsensor_to_gravity_rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]\n",
            "source[0] ('a') sensor_to_gravity_rotation",
        ),
        ("[publish.ros2]\nnamespace = \"gdvae\"\n", "publish.ros2.namespace"),
        ("[publish.ros2]\nnamespace = \"/a//b\"\n", "publish.ros2.namespace"),
        ("[publish.ros2]\nnode_name = \"edge-node\"\n", "publish.ros2.node_name"),
        ("[publish.ros2]\ndomain_id = 300\n", "publish.ros2.domain_id"),
        ("[publish.ros2]\nframe_id = \"\"\n", "publish.ros2.frame_id"),
        ("[[source]]\nstream = \"a\"\nkind = \"ros2\"\n", "source 'a' (ros2): missing field `topic`"),
        (
            "[[source]]\nstream = \"a\"\nkind = \"ros2\"\ntopic = \"/camera/points*\"\n",
            "not a ROS 2 topic name",
        ),
        (
            "[[source]]\nstream = \"a\"\nkind = \"files\"\npath = \"x\"\nkey = \"k\"\n",
            "source 'a' (files): unknown field `key`",
        ),
        ("[[source]]\nstream = \"a\"\nkind = \"zenoh\"\nkey = \"a//b\"\n", "not a zenoh key expression"),
    ];
    for (text, expected) in cases {
        // A key a kind lacks is refused when parsed; a bad value when validated.
        let error = match Config::parse(text) {
            Ok(config) => config.validate().unwrap_err(),
            Err(error) => error,
        };
        assert!(
            error.contains(expected),
            "{text:?}: '{error}' should mention {expected}"
        );
    }
}

#[test]
fn a_missing_config_file_is_named() {
    let error = Config::load(std::path::Path::new("/nonexistent/node.toml")).unwrap_err();
    assert!(error.to_string().contains("/nonexistent/node.toml"));
}
