//! The replay benchmark's yardstick: ONNX Runtime alone on the same bundle, batch size, workers
//! and threads as the pipeline, with nothing else running. The pipeline is not the bottleneck
//! when its throughput comes close to this.

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::bundle::Bundle;
use crate::config::ModelSettings;
use crate::runtime::{Encoder, RuntimeError};

#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct EncoderAlone {
    pub frames: usize,
    pub seconds: f64,
    pub frames_per_second: f64,
    /// The process's CPU time over the run (ONNX Runtime's threads; nothing else runs then).
    pub cpu_seconds: f64,
}

/// Encodes `frames` clouds (N_p random points in a unit ball: a dense network's cost does not
/// depend on the values) in batches of `max_batch`, split over `workers` sessions in parallel.
pub fn encoder_alone(bundle: &Bundle, model: &ModelSettings, frames: usize) -> Result<EncoderAlone, RuntimeError> {
    let points = bundle.manifest.sizes.points;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let batch: Vec<Vec<[f32; 3]>> = (0..model.max_batch)
        .map(|_| {
            (0..points)
                .map(|_| [0; 3].map(|_| rng.random_range(-0.5f32..0.5)))
                .collect()
        })
        .collect();
    let mut encoders = Vec::new();
    for _ in 0..model.workers {
        encoders.push(
            Encoder::load(bundle, model.onnxruntime.as_deref(), model.threads, model.spin)?
                .with_yaw_copies(model.yaw_copies),
        );
    }
    // Warm up each session once, as the pipeline's first batches do.
    let clouds: Vec<&[[f32; 3]]> = batch.iter().map(Vec::as_slice).collect();
    for encoder in &mut encoders {
        encoder.encode(&clouds)?;
    }
    let batches = frames.div_ceil(model.max_batch).max(1);
    let start = Instant::now();
    let cpu_start = crate::cpu::process_ns();
    let results: Vec<Result<usize, RuntimeError>> = std::thread::scope(|scope| {
        let handles: Vec<_> = encoders
            .iter_mut()
            .enumerate()
            .map(|(worker, encoder)| {
                let clouds = &clouds;
                scope.spawn(move || {
                    let mut done = 0;
                    for _ in (worker..batches).step_by(model.workers) {
                        done += encoder.encode(clouds)?.len();
                    }
                    Ok(done)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("encoder thread")).collect()
    });
    let mut encoded = 0;
    for result in results {
        encoded += result?;
    }
    let seconds = start.elapsed().as_secs_f64();
    let cpu_seconds = crate::cpu::process_ns().saturating_sub(cpu_start) as f64 * 1e-9;
    Ok(EncoderAlone {
        frames: encoded,
        seconds,
        frames_per_second: encoded as f64 / seconds,
        cpu_seconds,
    })
}
