//! The decoded canonical shape of each stream (each object, with several per stream), for the sinks that draw it (ROS 2 markers, the
//! Foxglove view, the MCAP recording): the bundle's `decoder.onnx` on a thread of its own, asked at
//! most `rate_hz` per stream and never waited for, so that decoding stays off the pipeline's hot
//! path. A stream's first states go without a shape until the first decode is done (a few
//! milliseconds), then each state carries the latest one.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::sink::PublishError;
use crate::bundle::Bundle;
use crate::state::State;

/// A canonical shape in metres (the object's frame, before the estimated rotation).
pub type Shape = Arc<Vec<[f32; 3]>>;

struct Request {
    /// The state's object (`State::object_name`).
    object: String,
    z_e: Vec<f32>,
    z_i: Vec<f32>,
}

#[derive(Default)]
struct Latest {
    shapes: HashMap<String, Shape>,
    asked: HashMap<String, Instant>,
}

/// The decoder on its own thread: requests in (at most one waiting), the latest shape per stream
/// out. Shared by every sink that draws shapes.
pub struct ShapeWorker {
    requests: crossbeam_channel::Sender<Request>,
    latest: Arc<Mutex<Latest>>,
    rate_hz: f64,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ShapeWorker {
    /// Loads the bundle's decoder; shapes are decoded at most `rate_hz` times a second per stream.
    pub fn start(bundle: &Bundle, library: Option<&std::path::Path>, rate_hz: f64) -> Result<Self, PublishError> {
        let mut decoder = crate::runtime::ShapeDecoder::load(bundle, library).map_err(|e| {
            PublishError::Shape(format!(
                "{e} (drawing the decoded shape needs the bundle's decoder; set publish.ros2.shape_rate_hz \
                 and publish.view.shape_rate_hz to 0 to go without)"
            ))
        })?;
        let metres_per_unit = 1.0 / bundle.manifest.units.model_units_per_metre as f32;
        let (requests, received) = crossbeam_channel::bounded::<Request>(1);
        let latest: Arc<Mutex<Latest>> = Arc::default();
        let thread = {
            let latest = latest.clone();
            std::thread::Builder::new()
                .name("publish:shapes".into())
                .spawn(move || {
                    let mut failures = 0u64;
                    for request in received {
                        match decoder.decode(&request.z_e, &request.z_i) {
                            Ok(points) => {
                                let points: Vec<[f32; 3]> =
                                    points.iter().map(|p| p.map(|v| v * metres_per_unit)).collect();
                                lock(&latest).shapes.insert(request.object, Arc::new(points));
                            }
                            Err(e) => {
                                failures += 1;
                                if failures <= 3 || failures % 100 == 0 {
                                    log::warn!("decoded shape: decoding failed ({failures} so far): {e}");
                                }
                            }
                        }
                    }
                })
                .map_err(|e| PublishError::Shape(e.to_string()))?
        };
        Ok(Self {
            requests,
            latest,
            rate_hz,
            thread: Some(thread),
        })
    }

    /// The latest shape of `state`'s stream (None before the first is decoded), asking for the
    /// state's own when one is due. Any number of sinks may call it for one state: it asks once.
    pub fn shape_for(&self, state: &State) -> Option<Shape> {
        let object = state.object_name();
        let mut latest = lock(&self.latest);
        let due = latest
            .asked
            .get(object.as_ref())
            .is_none_or(|t| t.elapsed().as_secs_f64() * self.rate_hz >= 1.0);
        if due {
            // Dropped when the decoder is still busy: the next state asks again.
            let request = Request {
                object: object.to_string(),
                z_e: state.filtered.z_e.clone(),
                z_i: state.shape.z_i.clone(),
            };
            if self.requests.try_send(request).is_ok() {
                latest.asked.insert(object.to_string(), Instant::now());
            }
        }
        latest.shapes.get(object.as_ref()).cloned()
    }
}

fn lock(latest: &Mutex<Latest>) -> std::sync::MutexGuard<'_, Latest> {
    latest.lock().unwrap_or_else(|e| e.into_inner())
}

impl Drop for ShapeWorker {
    fn drop(&mut self) {
        // Closing the channel ends the thread after the request it is on.
        let (closed, _) = crossbeam_channel::bounded(0);
        drop(std::mem::replace(&mut self.requests, closed));
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
