//! Faults inside the node: a panic while one frame is processed becomes that frame's counted
//! rejection (`crate::contain`); a stage thread that dies anyway stops the run (`StageGuard`), and the
//! status reply's queue observers (`Queues`) let go of their channels so nothing waits for ever.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crossbeam_channel::Receiver;

pub(super) type Depth = Box<dyn Fn() -> usize + Send + Sync>;

/// How many items wait in a channel, read by the status queryable.
pub(super) fn depth_of<T: Send + 'static>(receiver: &Receiver<T>) -> Depth {
    let receiver = receiver.clone();
    Box::new(move || receiver.len())
}

/// The queue-depth observers of the status reply. Each holds a receiver of its channel, which
/// would keep the channel open after its stage died: `release` drops them all.
pub(super) struct Queues {
    pub(super) channels: std::sync::Mutex<Vec<(&'static str, Depth)>>,
}

impl Queues {
    pub(super) fn depths(&self) -> BTreeMap<&'static str, usize> {
        let channels = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        channels.iter().map(|(name, len)| (*name, len())).collect()
    }

    pub(super) fn release(&self) {
        self.channels.lock().unwrap_or_else(|e| e.into_inner()).clear();
    }
}

/// Held by every stage thread: if the thread dies by a panic that per-frame containment did not
/// catch, the run is stopped (sources end, every stage drains) and the queue observers let go of
/// their channels, so no stage waits for ever on a channel only they kept open.
pub(super) struct StageGuard {
    pub(super) name: String,
    pub(super) stop: Arc<AtomicBool>,
    pub(super) queues: Arc<Queues>,
    pub(super) failed: Arc<std::sync::Mutex<Vec<String>>>,
}

impl Drop for StageGuard {
    fn drop(&mut self) {
        if std::thread::panicking() {
            log::error!("stage thread {} died; stopping the node", self.name);
            self.failed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(self.name.clone());
            self.stop.store(true, Ordering::SeqCst);
            self.queues.release();
        }
    }
}

#[cfg(test)]
mod tests {
    //! The panic containment on its own: a frame's panic is an error, a dying stage thread stops the
    //! run and lets go of the channels the status observers held.

    use super::*;
    use crossbeam_channel::bounded;
    use std::time::Duration;

    #[test]
    fn a_dying_stage_stops_the_run_and_releases_the_observed_channels() {
        let (tx, rx) = bounded::<u32>(1);
        let queues = Arc::new(Queues {
            channels: std::sync::Mutex::new(vec![("work", depth_of(&rx))]),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let failed: Arc<std::sync::Mutex<Vec<String>>> = Arc::default();
        tx.send(1).unwrap();
        assert_eq!(queues.depths()["work"], 1);
        // The stage that reads the channel dies outside any frame's containment.
        let guard = StageGuard {
            name: "prepare:0".into(),
            stop: stop.clone(),
            queues: queues.clone(),
            failed: failed.clone(),
        };
        let handle = std::thread::spawn(move || {
            let _guard = guard;
            let _rx = rx;
            panic!("a bug outside the per-frame work");
        });
        assert!(handle.join().is_err());
        assert!(stop.load(Ordering::SeqCst), "the run is told to stop");
        assert_eq!(*failed.lock().unwrap(), vec!["prepare:0".to_string()]);
        assert!(queues.depths().is_empty(), "the observers let go");
        // Nobody holds a receiver any more: the upstream stage sees the channel closed instead of
        // blocking for ever on a full queue.
        assert!(tx
            .send_timeout(2, Duration::from_secs(1))
            .unwrap_err()
            .is_disconnected());
    }

    #[test]
    fn a_stage_that_ends_normally_leaves_everything_as_it_was() {
        let (_tx, rx) = bounded::<u32>(1);
        let queues = Arc::new(Queues {
            channels: std::sync::Mutex::new(vec![("work", depth_of(&rx))]),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let failed: Arc<std::sync::Mutex<Vec<String>>> = Arc::default();
        let guard = StageGuard {
            name: "batcher".into(),
            stop: stop.clone(),
            queues: queues.clone(),
            failed: failed.clone(),
        };
        std::thread::spawn(move || drop(guard)).join().unwrap();
        assert!(!stop.load(Ordering::SeqCst));
        assert!(failed.lock().unwrap().is_empty());
        assert_eq!(queues.depths().len(), 1);
    }
}
