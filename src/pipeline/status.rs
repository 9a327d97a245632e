//! The node's status: the zenoh queryable (`<prefix>/<node>/status`: config, bundle, counters,
//! queue depths) and the periodic summary line in the log.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::{Session, Wait};

use super::faults::Queues;
use crate::bundle::Bundle;
use crate::config::Config;
use crate::stats::Stats;

pub(super) fn status_queryable(
    session: &Session,
    config: &Config,
    bundle: &Bundle,
    stats: Arc<Stats>,
    queues: Arc<Queues>,
    started: Instant,
) -> Result<zenoh::query::Queryable<()>, zenoh::Error> {
    let m = &bundle.manifest;
    let fixed = serde_json::json!({
        "schema": "gdvae.status/1",
        "node": config.node.name,
        "version": env!("CARGO_PKG_VERSION"),
        "config": config,
        "bundle": {
            "folder": bundle.folder.display().to_string(),
            "regime": m.model.regime,
            "sizes": m.sizes,
            "model_units_per_metre": m.units.model_units_per_metre,
        },
    });
    session
        .declare_queryable(config.status_key())
        .callback(move |query| {
            let mut reply = fixed.clone();
            reply["uptime_s"] = serde_json::json!(started.elapsed().as_secs_f64());
            reply["counters"] = serde_json::to_value(stats.snapshot()).unwrap_or_default();
            reply["queues"] = serde_json::to_value(queues.depths()).unwrap_or_default();
            let payload = serde_json::to_vec(&reply).unwrap_or_default();
            if let Err(e) = query
                .reply(query.key_expr().clone(), payload)
                .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
                .wait()
            {
                log::warn!("status reply failed: {e}");
            }
        })
        .wait()
}

pub(super) fn summary_logger(finished: &AtomicBool, stats: &Stats, seconds: f64) {
    if seconds <= 0.0 {
        return;
    }
    let mut last = Instant::now();
    while !finished.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(100));
        if last.elapsed().as_secs_f64() < seconds {
            continue;
        }
        last = Instant::now();
        let s = stats.snapshot();
        let e2e = s.stages.get("end_to_end");
        let streams: Vec<String> = s
            .streams
            .iter()
            .map(|(name, c)| {
                let rejected: u64 = c.rejected.values().sum();
                format!(
                    "{name}: {} in, {} out, {} dropped, {rejected} rejected",
                    c.received, c.published, c.dropped
                )
            })
            .collect();
        log::info!(
            "{} | latency p50 {:.1} ms, p99 {:.1} ms | mean batch {:.1}",
            streams.join("; "),
            e2e.map(|l| l.p50_ms).unwrap_or(0.0),
            e2e.map(|l| l.p99_ms).unwrap_or(0.0),
            s.mean_batch
        );
    }
}
