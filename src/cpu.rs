//! CPU time: this thread's and the whole process's, from the kernel's clocks. The replay benchmark
//! says where a frame's CPU goes (decode, each prepare step, track, publish, and ONNX Runtime),
//! which wall-clock latencies cannot: on two cores shared by a dozen threads a stage's latency
//! includes the time others held its core. Reading a clock costs about a microsecond (a system
//! call for the thread clock), so stages read it a few times per frame, not per point.

use std::thread::ThreadId;

/// CPU time this thread has used since it started, in nanoseconds (0 where unsupported).
pub fn thread_ns() -> u64 {
    clock(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// CPU time every thread of this process has used since it started, in nanoseconds.
pub fn process_ns() -> u64 {
    clock(libc::CLOCK_PROCESS_CPUTIME_ID)
}

fn clock(id: libc::clockid_t) -> u64 {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `t` is a valid, writable timespec; the clock ids are the kernel's own constants.
    if unsafe { libc::clock_gettime(id, &mut t) } != 0 {
        return 0;
    }
    t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
}

/// A stopwatch of this thread's CPU time: each `lap` is the CPU used since the previous one.
pub struct ThreadLap(u64);

impl ThreadLap {
    pub fn start() -> Self {
        Self(thread_ns())
    }

    pub fn lap(&mut self) -> u64 {
        let now = thread_ns();
        let spent = now.saturating_sub(self.0);
        self.0 = now;
        spent
    }
}

/// The CPU a thread spent between two calls, for work that is handed on from whichever thread
/// does it (a source's frames): a call on another thread than the previous one starts afresh and
/// counts nothing, since two threads' clocks cannot be subtracted.
#[derive(Debug, Default)]
pub struct BetweenCalls(Option<(ThreadId, u64)>);

impl BetweenCalls {
    /// The CPU this thread used since the previous call on it; the first call on a thread counts
    /// the thread's whole CPU time so far (a dedicated source thread's start-up is its work).
    pub fn lap(&mut self) -> u64 {
        let here = std::thread::current().id();
        let now = thread_ns();
        let spent = match self.0 {
            Some((thread, before)) if thread == here => now.saturating_sub(before),
            Some(_) => 0,
            None => now,
        };
        self.0 = Some((here, now));
        spent
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spin(ms: u64) {
        let until = std::time::Instant::now() + std::time::Duration::from_millis(ms);
        let mut x = 0u64;
        while std::time::Instant::now() < until {
            x = std::hint::black_box(x.wrapping_add(1));
        }
    }

    #[test]
    fn a_thread_that_works_uses_cpu_and_one_that_sleeps_does_not() {
        let mut lap = ThreadLap::start();
        spin(30);
        let working = lap.lap();
        std::thread::sleep(std::time::Duration::from_millis(30));
        let sleeping = lap.lap();
        assert!(working > 10_000_000, "30 ms of spinning counted {working} ns");
        assert!(sleeping < 5_000_000, "30 ms of sleep counted {sleeping} ns");
        assert!(process_ns() >= working);
    }

    #[test]
    fn laps_on_another_thread_count_nothing() {
        let mut between = BetweenCalls::default();
        spin(5);
        assert!(between.lap() > 0, "the first call counts the thread so far");
        let mut moved = std::thread::spawn(move || {
            spin(5);
            assert_eq!(between.lap(), 0, "another thread's clock");
            spin(20);
            assert!(between.lap() > 10_000_000);
            between
        })
        .join()
        .unwrap();
        assert_eq!(moved.lap(), 0);
    }
}
