//! Shared helpers: repository paths, bounded waits (every wait in these tests has a timeout), and
//! zenoh sessions on loopback with scouting off (tests never find each other by multicast).

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use gdvae_node::config::Config;
use zenoh::Wait;

pub fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

pub fn shipped_bundle() -> PathBuf {
    repo().join("models/bundles/cpu-fo")
}

pub fn sample_recording() -> PathBuf {
    repo().join("sim/samples/walk_switch.mcap")
}

/// Polls `condition` every 10 ms until it holds or `timeout` passes; returns whether it held.
pub fn wait_until(timeout: Duration, mut condition: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if condition() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    condition()
}

/// A loopback TCP endpoint on a port that was free a moment ago.
pub fn free_endpoint() -> String {
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    format!("tcp/127.0.0.1:{port}")
}

/// A node config for tests: the shipped bundle, one encoder thread, no log summaries, zenoh
/// listening on `endpoint` with multicast scouting off.
pub fn test_config(node: &str, endpoint: &str) -> Config {
    let mut config = Config::default();
    config.node.name = node.into();
    config.model.bundle = shipped_bundle();
    config.model.threads = 1;
    config.pipeline.summary_seconds = 0.0;
    config.zenoh.listen = Some(vec![endpoint.into()]);
    config.zenoh.multicast_scouting = Some(false);
    config
}

/// A second zenoh peer connected to `endpoint`.
pub fn client_session(endpoint: &str) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    config
        .insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))
        .unwrap();
    config.insert_json5("scouting/multicast/enabled", "false").unwrap();
    zenoh::open(config).wait().unwrap()
}

/// Waits until a subscriber for `key` is visible from `session` (so no sample published after
/// this is lost to a subscription still on its way).
pub fn wait_for_subscriber(session: &zenoh::Session, key: &str) {
    let probe = session.declare_publisher(key.to_string()).wait().unwrap();
    let matched = wait_until(Duration::from_secs(10), || {
        probe.matching_status().wait().map(|s| s.matching()).unwrap_or(false)
    });
    assert!(matched, "no subscriber for {key} appeared within 10 s");
}

/// `gdvae-node -q run --config CONFIG` from the repository root, its output piped.
pub fn spawn_run(config: &Path) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
        .current_dir(repo())
        .args(["-q", "run", "--config"])
        .arg(config)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// Sends `signal` (e.g. "-TERM") to `child`.
pub fn send_signal(child: &std::process::Child, signal: &str) {
    let status = std::process::Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

/// Lines written to a JSON-lines file so far (0 before it exists).
pub fn line_count(path: &Path) -> usize {
    std::fs::read_to_string(path).map(|t| t.lines().count()).unwrap_or(0)
}
