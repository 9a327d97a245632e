//! End to end through real parts: the shipped bundle in ONNX Runtime, the sample recording, and
//! zenoh sessions on loopback. Every wait has a timeout.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crossbeam_channel::{unbounded, Receiver};
use gdvae_node::bundle::Bundle;
use gdvae_node::config::{Config, SourceSettings};
use gdvae_node::pipeline::{self, RunOptions, RunSummary};
use gdvae_node::state::{Rejected, State, STATE_SCHEMA};
use gdvae_node::stats::Stats;
use zenoh::bytes::Encoding;
use zenoh::Wait;

use crate::helpers::*;

fn source(toml_text: &str) -> SourceSettings {
    toml::from_str(toml_text).unwrap()
}

/// Subscribes to everything under `key` and forwards (key, payload) pairs.
fn collect(session: &zenoh::Session, key: &str) -> (zenoh::pubsub::Subscriber<()>, Receiver<(String, Vec<u8>)>) {
    let (tx, rx) = unbounded();
    let subscriber = session
        .declare_subscriber(key.to_string())
        .callback(move |sample| {
            let _ = tx.send((sample.key_expr().to_string(), sample.payload().to_bytes().to_vec()));
        })
        .wait()
        .unwrap();
    (subscriber, rx)
}

/// Runs the pipeline on a thread; returns its stop flag, stats and handle.
fn start(
    config: Config,
    session: zenoh::Session,
) -> (Arc<AtomicBool>, Arc<Stats>, std::thread::JoinHandle<RunSummary>) {
    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(Stats::default());
    let (s, st) = (stop.clone(), stats.clone());
    let handle = std::thread::spawn(move || {
        let bundle = Bundle::load(&config.model.bundle).unwrap();
        pipeline::run(
            &config,
            &bundle,
            Some(session),
            s,
            st,
            RunOptions {
                lossless_publish: true,
                ..RunOptions::default()
            },
        )
        .unwrap()
    });
    (stop, stats, handle)
}

fn join_within(handle: std::thread::JoinHandle<RunSummary>, timeout: Duration) -> RunSummary {
    assert!(
        wait_until(timeout, || handle.is_finished()),
        "the pipeline did not finish within {timeout:?}"
    );
    handle.join().unwrap()
}

#[test]
fn replaying_the_sample_publishes_every_frame_in_order_on_zenoh() {
    let endpoint = free_endpoint();
    let mut config = test_config("e2e", &endpoint);
    config.model.threads = 2;
    config.prepare = Config::load(&repo().join("config/replay.toml")).unwrap().prepare;
    config.sources = vec![source(&format!(
        "stream = \"walk\"\nkind = \"mcap\"\npath = {:?}\nspeed = 0.0",
        sample_recording().display().to_string()
    ))];
    let node = gdvae_node::zenoh_session::open_session(&config.zenoh).unwrap();
    let client = client_session(&endpoint);
    let (_subscriber, received) = collect(&client, "gdvae/e2e/**");
    wait_for_subscriber(&node, "gdvae/e2e/walk/state");

    let (_, _, handle) = start(config, node);
    let summary = join_within(handle, Duration::from_secs(120));
    let counters = &summary.snapshot.streams["walk"];
    assert_eq!((counters.received, counters.published, counters.dropped), (150, 150, 0));
    // Every frame's CPU is accounted to its stages (the replay benchmark's CPU table), and the
    // process as a whole spent at least what they did.
    let cpu = &summary.snapshot.cpu;
    let mut stages_ns = 0;
    for stage in gdvae_node::prepare::STEPS
        .into_iter()
        .chain(["decode", "track", "publish"])
    {
        let account = cpu
            .get(stage)
            .unwrap_or_else(|| panic!("no CPU account '{stage}': {cpu:?}"));
        assert_eq!(account.items, 150, "{stage}");
        stages_ns += account.ns;
    }
    for stage in [
        "decode",
        "prepare.transform",
        "prepare.cluster",
        "prepare.sample",
        "encode",
    ] {
        assert!(cpu[stage].ns > 0, "{stage}: {cpu:?}");
    }
    // The encode threads' account: one item a batch.
    assert!((1..=150).contains(&cpu["encode"].items), "{cpu:?}");
    assert!(
        summary.busy_cpu.as_nanos() as f64 > 0.9 * stages_ns as f64,
        "{:?} {cpu:?}",
        summary.busy_cpu
    );

    let mut states = Vec::new();
    assert!(
        wait_until(Duration::from_secs(20), || {
            states.extend(received.try_iter().filter(|(k, _)| k.ends_with("/state")));
            states.len() >= 150
        }),
        "received {} of 150 states",
        states.len()
    );
    let sizes = Bundle::load(shipped_bundle()).unwrap().manifest.sizes;
    let mut identity_changes = Vec::new();
    for (index, (key, payload)) in states.iter().enumerate() {
        assert_eq!(key, "gdvae/e2e/walk/state");
        let state: State = serde_json::from_slice(payload).unwrap();
        assert_eq!(state.schema, STATE_SCHEMA);
        assert_eq!(state.sequence, index as u64, "in order, none missing");
        assert_eq!(
            (state.raw.z_i.len(), state.shape.z_i.len(), state.raw.z_e.len()),
            (sizes.z_i, sizes.z_i, sizes.z_e)
        );
        assert!(state.stamps.sensor_ns.is_some() && state.stamps.publish_ns >= state.stamps.ingest_ns);
        assert!(
            state.points.kept > 500 && state.points.kept < state.points.received,
            "crop keeps the subject"
        );
        let norm: f32 = state.filtered.q.iter().map(|c| c * c).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-3);
        if state.event.is_some() {
            identity_changes.push((state.sequence, state.shape.identity));
        }
    }
    // The recording swaps the quadruped for a biped at frame 75; with the shipped bundle and the
    // default gate that is the one identity change, found within switch_frames plus a few frames.
    let switch_frames = Config::default().track.switch_frames as u64;
    assert!(
        identity_changes.len() == 1 && (75..=75 + 2 * switch_frames).contains(&identity_changes[0].0),
        "identity changes (frame, identity): {identity_changes:?}; expected one, shortly after frame 75"
    );
}

#[test]
fn a_single_stream_at_its_own_rate_is_encoded_without_waiting_for_a_batch() {
    // One stream at 30 Hz with a batcher allowed to wait a whole second for 8 frames: waiting
    // would hold every batch's first frame for 7 sensor periods (233 ms). With the stream's frame
    // in the batch and nothing else active, the batch goes at once.
    let endpoint = free_endpoint();
    let mut config = test_config("single", &endpoint);
    config.model.max_batch = 8;
    config.model.max_wait_ms = 1000.0;
    config.prepare = Config::load(&repo().join("config/replay.toml")).unwrap().prepare;
    config.sources = vec![source(&format!(
        "stream = \"walk\"\nkind = \"mcap\"\npath = {:?}\nspeed = 1.0",
        sample_recording().display().to_string()
    ))];
    let node = gdvae_node::zenoh_session::open_session(&config.zenoh).unwrap();
    let client = client_session(&endpoint);
    let (_subscriber, received) = collect(&client, "gdvae/single/walk/state");
    wait_for_subscriber(&node, "gdvae/single/walk/state");
    let (stop, _, handle) = start(config, node);
    let mut queue_ms = Vec::new();
    assert!(
        wait_until(Duration::from_secs(60), || {
            queue_ms.extend(
                received
                    .try_iter()
                    .map(|(_, payload)| serde_json::from_slice::<State>(&payload).unwrap().latency.queue_ms),
            );
            queue_ms.len() >= 24
        }),
        "received {} states",
        queue_ms.len()
    );
    stop.store(true, Ordering::SeqCst);
    join_within(handle, Duration::from_secs(30));
    queue_ms.sort_by(f32::total_cmp);
    let median = queue_ms[queue_ms.len() / 2];
    assert!(
        median < 50.0,
        "median wait for a batch {median} ms (all: {queue_ms:?}); waiting for 8 frames would be 100 ms or more"
    );
}

#[test]
fn stop_drains_the_frames_in_flight_and_status_answers_while_running() {
    let endpoint = free_endpoint();
    let mut config = test_config("drain", &endpoint);
    config.sources = vec![source(&format!(
        "stream = \"meshes\"\nkind = \"files\"\npath = {:?}\nrepeat = true",
        repo().join("sim/samples/meshes").display().to_string()
    ))];
    let node = gdvae_node::zenoh_session::open_session(&config.zenoh).unwrap();
    let client = client_session(&endpoint);
    let (stop, stats, handle) = start(config, node);
    assert!(
        wait_until(Duration::from_secs(60), || stats
            .snapshot()
            .streams
            .get("meshes")
            .is_some_and(|s| s.published >= 10)),
        "states are published"
    );

    let mut status = None;
    assert!(wait_until(Duration::from_secs(20), || {
        let replies = client
            .get("gdvae/drain/status")
            .timeout(Duration::from_secs(2))
            .wait()
            .unwrap();
        if let Ok(reply) = replies.recv() {
            if let Ok(sample) = reply.result() {
                status = serde_json::from_slice::<serde_json::Value>(&sample.payload().to_bytes()).ok();
            }
        }
        status.is_some()
    }));
    let status = status.unwrap();
    assert_eq!(status["schema"], "gdvae.status/1");
    assert!(status["counters"]["streams"]["meshes"]["published"].as_u64().unwrap() >= 10);
    assert!(status["queues"]["prepare"].is_u64() && status["config"]["model"]["max_batch"] == 8);

    stop.store(true, Ordering::SeqCst);
    let summary = join_within(handle, Duration::from_secs(30));
    let counters = &summary.snapshot.streams["meshes"];
    let rejected: u64 = counters.rejected.values().sum();
    assert_eq!(counters.dropped, 0);
    assert_eq!(
        counters.received,
        counters.published + rejected,
        "every frame taken in was finished: {counters:?}"
    );
}

#[test]
fn zenoh_sources_decode_cdr_and_depthai_and_count_what_they_reject() {
    let endpoint = free_endpoint();
    let mut config = test_config("live", &endpoint);
    config.prepare = Config::load(&repo().join("config/replay.toml")).unwrap().prepare;
    config.sources = vec![
        source("stream = \"ros\"\nkind = \"zenoh\"\nkey = \"test/ros/points\""),
        source("stream = \"oak\"\nkind = \"zenoh\"\nkey = \"test/oak/points\""),
    ];
    // A real PointCloud2 message: the sample recording's first frame.
    let bytes = std::fs::read(sample_recording()).unwrap();
    let cdr = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .find(|m| m.channel.topic == "/camera/depth/points")
        .unwrap()
        .data
        .to_vec();
    let points = gdvae_node::sources::ros2::decode_point_cloud2(&cdr, 1 << 22)
        .unwrap()
        .points;
    let millimetres: Vec<u8> = points
        .iter()
        .flat_map(|p| p.map(|c| c * 1000.0))
        .flat_map(f32::to_le_bytes)
        .collect();

    let node = gdvae_node::zenoh_session::open_session(&config.zenoh).unwrap();
    let client = client_session(&endpoint);
    let (_subscriber, received) = collect(&client, "gdvae/live/**");
    wait_for_subscriber(&node, "gdvae/live/ros/state");
    let (stop, stats, handle) = start(config, node.clone());
    // Block, not zenoh's default Drop: on a loaded machine a burst of large puts would otherwise be
    // dropped on the way, and the node could not count what never reached it.
    let publisher = |key: &'static str| {
        client
            .declare_publisher(key)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .wait()
            .unwrap()
    };
    let (ros, oak) = (publisher("test/ros/points"), publisher("test/oak/points"));
    // Subscriptions are declared by the pipeline: wait until they reach the client.
    assert!(wait_until(Duration::from_secs(20), || ros
        .matching_status()
        .wait()
        .unwrap()
        .matching()
        && oak.matching_status().wait().unwrap().matching()));

    let cdr_encoding = Encoding::APPLICATION_CDR.with_schema("sensor_msgs/msg/PointCloud2");
    ros.put(cdr.clone()).encoding(cdr_encoding.clone()).wait().unwrap();
    oak.put(millimetres.clone())
        .encoding(Encoding::APPLICATION_OCTET_STREAM.with_schema(gdvae_node::sources::zenoh::DEPTHAI_SCHEMA))
        .attachment(br#"{"stamp_nanos": 42}"#.to_vec())
        .wait()
        .unwrap();
    ros.put(b"hello".to_vec())
        .encoding(Encoding::TEXT_PLAIN)
        .wait()
        .unwrap();
    ros.put(cdr[..cdr.len() / 2].to_vec())
        .encoding(cdr_encoding)
        .wait()
        .unwrap();
    oak.put(millimetres[..millimetres.len() - 5].to_vec())
        .encoding(Encoding::APPLICATION_OCTET_STREAM.with_schema(gdvae_node::sources::zenoh::DEPTHAI_SCHEMA))
        .wait()
        .unwrap();

    let done = |s: &gdvae_node::stats::Snapshot, name: &str, n: u64| {
        s.streams
            .get(name)
            .is_some_and(|c| c.published + c.rejected.values().sum::<u64>() >= n)
    };
    assert!(
        wait_until(Duration::from_secs(30), || {
            let s = stats.snapshot();
            done(&s, "ros", 3) && done(&s, "oak", 2)
        }),
        "{:?}",
        stats.snapshot().streams
    );
    stop.store(true, Ordering::SeqCst);
    let summary = join_within(handle, Duration::from_secs(30));
    let streams = &summary.snapshot.streams;
    assert_eq!(streams["ros"].published, 1);
    assert_eq!(streams["ros"].rejected, BTreeMap::from([("source".to_string(), 2)]));
    assert_eq!(streams["oak"].published, 1);
    assert_eq!(streams["oak"].rejected, BTreeMap::from([("source".to_string(), 1)]));

    let mut messages = Vec::new();
    assert!(wait_until(Duration::from_secs(10), || {
        messages.extend(received.try_iter());
        messages.len() >= 5
    }));
    let oak_state: State = messages
        .iter()
        .find(|(k, _)| k == "gdvae/live/oak/state")
        .map(|(_, p)| serde_json::from_slice(p).unwrap())
        .unwrap();
    let ros_state: State = messages
        .iter()
        .find(|(k, _)| k == "gdvae/live/ros/state")
        .map(|(_, p)| serde_json::from_slice(p).unwrap())
        .unwrap();
    assert_eq!(oak_state.stamps.sensor_ns, Some(42));
    // Millimetres are converted: the same frame gives the same prepared cloud and codes.
    assert_eq!(oak_state.points.kept, ros_state.points.kept);
    for (a, b) in oak_state.raw.z_i.iter().zip(&ros_state.raw.z_i) {
        assert!((a - b).abs() < 1e-3, "{a} vs {b}");
    }
    let reasons: Vec<Rejected> = messages
        .iter()
        .filter(|(k, _)| k.ends_with("/rejected"))
        .map(|(_, p)| serde_json::from_slice(p).unwrap())
        .collect();
    assert!(
        reasons
            .iter()
            .any(|r| r.stream == "ros" && r.reason.contains("unknown encoding")),
        "{reasons:?}"
    );
    assert!(
        reasons
            .iter()
            .any(|r| r.stream == "oak" && r.reason.contains("triplets")),
        "{reasons:?}"
    );
}

#[test]
fn a_live_feed_that_goes_silent_and_returns_resumes_and_the_gap_is_counted() {
    let endpoint = free_endpoint();
    let mut config = test_config("gap", &endpoint);
    config.prepare = Config::load(&repo().join("config/replay.toml")).unwrap().prepare;
    config.pipeline.feed_gap_s = 1.0;
    config.sources = vec![source("stream = \"cam\"\nkind = \"zenoh\"\nkey = \"test/gap/points\"")];
    let bytes = std::fs::read(sample_recording()).unwrap();
    let clouds: Vec<Vec<u8>> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .filter(|m| m.channel.topic == "/camera/depth/points")
        .take(8)
        .map(|m| m.data.to_vec())
        .collect();
    let node = gdvae_node::zenoh_session::open_session(&config.zenoh).unwrap();
    let client = client_session(&endpoint);
    let (stop, stats, handle) = start(config, node);
    let publisher = client
        .declare_publisher("test/gap/points")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .unwrap();
    assert!(wait_until(Duration::from_secs(20), || publisher
        .matching_status()
        .wait()
        .unwrap()
        .matching()));
    let published = || stats.snapshot().streams.get("cam").map(|c| c.published).unwrap_or(0);
    // Four frames at 10 Hz, 2.5 s of silence (the sensor unplugged), four more.
    for cloud in &clouds[..4] {
        publisher.put(cloud.clone()).wait().unwrap();
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(wait_until(Duration::from_secs(30), || published() == 4));
    // Halfway through, one sample that is not a cloud: a rejection, not the feed resuming.
    std::thread::sleep(Duration::from_millis(1500));
    publisher.put(b"not a point cloud".to_vec()).wait().unwrap();
    std::thread::sleep(Duration::from_millis(1000));
    for cloud in &clouds[4..] {
        publisher.put(cloud.clone()).wait().unwrap();
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(
        wait_until(Duration::from_secs(30), || published() == 8),
        "states resume after the gap: {:?}",
        stats.snapshot().streams
    );
    stop.store(true, Ordering::SeqCst);
    let summary = join_within(handle, Duration::from_secs(30));
    let counters = &summary.snapshot.streams["cam"];
    assert_eq!(counters.feed_gaps, 1, "{counters:?}");
    assert!(counters.feed_gap_s >= 2.4 && counters.feed_gap_s < 10.0, "{counters:?}");
    assert_eq!((counters.received, counters.dropped), (9, 0));
    assert_eq!(counters.rejected, BTreeMap::from([("source".to_string(), 1)]));
}

#[test]
fn host_cpu_steal_is_read_from_the_aggregate_cpu_line_of_proc_stat() {
    use gdvae_node::stats::parse_cpu_steal;
    // user nice system idle iowait irq softirq steal guest guest_nice, in USER_HZ (1/100 s)
    let stat = "cpu  238667 9007 11848 2058769 1347 0 492 1882 0 0\n\
                cpu0 119000 4500 5900 1029000 600 0 250 950 0 0\n\
                intr 1 2 3\n";
    assert_eq!(parse_cpu_steal(stat), Some(18.82));
    assert_eq!(
        parse_cpu_steal("cpu  1 2 3 4\n"),
        None,
        "a kernel without the steal field"
    );
    assert_eq!(
        parse_cpu_steal("cpu0 1 2 3 4 5 6 7 8\n"),
        None,
        "only the aggregate line counts"
    );
    if std::path::Path::new("/proc/stat").exists() {
        let now = gdvae_node::stats::cpu_steal_seconds().expect("this Linux reports steal");
        assert!(now >= 0.0 && now.is_finite());
    }
}
