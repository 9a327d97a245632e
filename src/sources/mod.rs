//! Sources of frames, each feeding one stream: files and folders (`files`), recordings replayed
//! (`recording`: MCAP files and rosbag2 bags, read by `mcap` and `rosbag2`), zenoh subscriptions
//! (`zenoh`), ROS 2 topics by name over rmw_zenoh (`ros2_topic`); `ros2` decodes the ROS 2 messages
//! recordings and subscriptions carry.
//!
//! A source hands its frames to an `Outlet`, its own bounded channel into the pipeline. The outlet
//! applies the stream's policy: a live source never waits (when the pipeline is behind, the oldest
//! queued frame is dropped and counted); a replayed source waits, so nothing is lost. A frame the
//! source cannot decode becomes a counted `Rejection` naming the input and the reason.

pub mod files;
mod outlet;
pub mod recording;
pub mod ros2;
pub mod ros2_topic;
mod settings;
pub mod zenoh;

use std::sync::{Arc, Mutex};

pub use files::file_or_folder;
pub use outlet::{unix_now_ns, Ingest, Intake, Outlet, Rejection};
pub use recording::{mcap, rosbag2};
pub use settings::{Input, SourceKind, SourceSettings};

/// What a source checks before anything runs: that its files exist and hold what it reads (a
/// network source is checked when it subscribes). A line saying what it found, or why it cannot start.
pub fn check(source: &SourceSettings) -> Result<String, String> {
    match &source.input {
        Input::Files(own) => own.check(),
        Input::Mcap(own) => recording::check(own).map_err(|e| e.to_string()),
        Input::Zenoh(own) => Ok(format!("zenoh key {}", own.key)),
        Input::Ros2(own) => Ok(format!("ROS 2 topic {}", own.topic)),
    }
}

/// A started source: a thread of its own (files, recordings) or a subscription, open as long as
/// it is held (zenoh, ROS 2).
pub enum Running {
    Thread(std::thread::JoinHandle<()>),
    Subscription(Box<dyn std::any::Any + Send>),
}

/// What starting a source needs besides its settings.
pub struct StartContext<'a> {
    pub session: Option<&'a ::zenoh::Session>,
    /// The node in ROS 2 domains, and the domain a ROS 2 source uses unless it names one.
    pub participants: Option<&'a crate::ros2::Participants>,
    pub default_domain: u32,
    /// Where a source thread that stops with an error says so: (stream, reason, optional).
    pub errors: Arc<Mutex<Vec<(String, String, bool)>>>,
}

/// Starts a source feeding `outlet`: its module's one way in. Returns it running and a line for
/// the log; an error if it could not start.
pub fn start(source: &SourceSettings, outlet: Outlet, context: &StartContext) -> Result<(Running, String), String> {
    let no_session = || "no zenoh session".to_string();
    match &source.input {
        Input::Files(_) | Input::Mcap(_) => {
            let settings = source.clone();
            let errors = context.errors.clone();
            let handle = std::thread::Builder::new()
                .name(format!("source:{}", source.stream))
                .spawn(move || {
                    let stream = settings.stream.clone();
                    // A panic while decoding ends this source with a logged error; the other
                    // sources and the pipeline go on.
                    let result = crate::contain::contained(&format!("source '{stream}'"), || match &settings.input {
                        Input::Files(own) => files::run(&settings.intake(), own, outlet).map_err(|e| e.to_string()),
                        Input::Mcap(own) => recording::run(&settings.intake(), own, outlet).map_err(|e| e.to_string()),
                        _ => unreachable!("network sources subscribe"),
                    })
                    .and_then(|r| r);
                    match result {
                        Ok(()) => log::info!("source '{stream}': finished"),
                        Err(e) => {
                            log::error!("source '{stream}' stopped: {e}");
                            errors.lock().unwrap_or_else(|e| e.into_inner()).push((
                                stream,
                                format!("stopped: {e}"),
                                settings.optional,
                            ));
                        }
                    }
                })
                .map_err(|e| e.to_string())?;
            Ok((Running::Thread(handle), "started".into()))
        }
        Input::Zenoh(own) => {
            let session = context.session.ok_or_else(no_session)?;
            let subscriber = zenoh::subscribe(session, &source.intake(), own, outlet).map_err(|e| e.to_string())?;
            Ok((
                Running::Subscription(Box::new(subscriber)),
                format!("zenoh subscription to {}", own.key),
            ))
        }
        Input::Ros2(own) => {
            let participants = context.participants.ok_or_else(no_session)?;
            let domain = own.domain_id.unwrap_or(context.default_domain);
            let participant = participants.join(domain).map_err(|e| e.to_string())?;
            let (topic, _) = ros2_topic::topics(&participant, own);
            let subscription =
                ros2_topic::subscribe(participant, &source.intake(), own, outlet).map_err(|e| e.to_string())?;
            Ok((
                Running::Subscription(Box::new(subscription)),
                format!("ROS 2 topic {topic} in domain {domain}"),
            ))
        }
    }
}

/// One replay source per input, named after its file stem (made unique): MCAP and rosbag2 files
/// and folders replay their point clouds, other files and folders are point-cloud files. `speed` as in
/// `[[source]] speed` (0 = as fast as possible).
pub fn replay_sources(inputs: &[std::path::PathBuf], speed: f64) -> Vec<SourceSettings> {
    let mut sources: Vec<SourceSettings> = Vec::new();
    for input in inputs {
        let stem = input
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("input")
            .replace(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_'), "_");
        let mut stream = stem.clone();
        let mut n = 1;
        while sources.iter().any(|s| s.stream == stream) {
            n += 1;
            stream = format!("{stem}_{n}");
        }
        let input = if recording::is_recording(input) {
            Input::Mcap(recording::RecordingSettings::replay(input.clone(), speed))
        } else {
            // Files have no timing of their own: as fast as possible.
            Input::Files(files::FilesSettings {
                path: input.clone(),
                rate_hz: 0.0,
                repeat: false,
            })
        };
        sources.push(SourceSettings::new(stream, input));
    }
    sources
}
