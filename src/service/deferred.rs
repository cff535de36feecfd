//! Deferred state estimates. A scheduled cycle of a surrogate field whose
//! window is all measured does not need its state estimate brought up to
//! the boundary: its setpoint comes from the measured window
//! ([`super::engine::Engine::control_cycle`]). It commits its setpoint
//! without one and queues the field here. These threads bring the queued
//! estimates up to date ([`Engine::update_estimate`]) at the lowest CPU
//! priority (nice 19 on Linux), so that a boundary's setpoints come
//! before its estimates: on a busy machine the estimator's ensemble
//! forecasts were about half of a boundary's work.
//!
//! The queue holds at most one entry per field (a newer boundary replaces
//! the older one's), so it never outgrows the fields. Nothing is lost when
//! an entry is dropped (at shutdown, or a lease that moved): the estimate
//! is a replay of the stored readings, and the next cycle, or the next
//! update, replays them all from the stored estimate. An update stores its
//! estimate only over the one it started from, so it never undoes a later
//! cycle's.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use chrono::{DateTime, Utc};
use prometheus::{IntCounterVec, IntGauge};

use super::engine::Engine;
use super::wire::Field;

/// The queue and its worker threads.
pub struct Deferred {
    shared: Arc<Shared>,
}

struct Shared {
    queue: Mutex<Queue>,
    ready: Condvar,
    stop: AtomicBool,
    outcomes: IntCounterVec,
    pending: IntGauge,
}

#[derive(Default)]
struct Queue {
    /// Field ids, oldest entry first; each once.
    order: VecDeque<i64>,
    /// Per queued field: the field and the boundary to bring it up to.
    entries: HashMap<i64, (Field, DateTime<Utc>)>,
}

impl Deferred {
    /// Starts `threads` workers that update estimates on `engine` as
    /// `replica`.
    pub fn start(
        engine: Arc<Engine>,
        replica: String,
        threads: usize,
        outcomes: IntCounterVec,
        pending: IntGauge,
    ) -> Deferred {
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue::default()),
            ready: Condvar::new(),
            stop: AtomicBool::new(false),
            outcomes,
            pending,
        });
        for k in 0..threads.max(1) {
            let (shared, engine, replica) = (shared.clone(), engine.clone(), replica.clone());
            let spawned = std::thread::Builder::new()
                .name(format!("estimates-{k}"))
                .spawn(move || work(&shared, &engine, &replica));
            if let Err(e) = spawned {
                // the cycles then bring their estimates up to date themselves
                // once the stored one falls a period behind
                tracing::error!(error = %e, "no thread for deferred estimates");
            }
        }
        Deferred { shared }
    }

    /// Queues `field`'s estimate to be brought up to `at` (replacing an
    /// older entry of the same field).
    pub fn push(&self, field: Field, at: DateTime<Utc>) {
        let mut q = self.shared.lock();
        let id = field.id;
        if q.entries.insert(id, (field, at)).is_none() {
            q.order.push_back(id);
        }
        self.shared.pending.set(q.order.len() as i64);
        drop(q);
        self.shared.ready.notify_one();
    }

    /// Fields queued.
    pub fn pending(&self) -> usize {
        self.shared.lock().order.len()
    }

    /// Stops the workers after the update each is running; the rest of the
    /// queue is dropped (the next cycles replay it).
    pub fn stop(&self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        let mut q = self.shared.lock();
        q.order.clear();
        q.entries.clear();
        self.shared.pending.set(0);
        drop(q);
        self.shared.ready.notify_all();
    }
}

impl Drop for Deferred {
    fn drop(&mut self) {
        self.stop();
    }
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The next entry, waiting for one; None once stopped.
    fn next(&self) -> Option<(Field, DateTime<Utc>)> {
        let mut q = self.lock();
        loop {
            if self.stop.load(Ordering::Relaxed) {
                return None;
            }
            if let Some(id) = q.order.pop_front() {
                self.pending.set(q.order.len() as i64);
                if let Some(entry) = q.entries.remove(&id) {
                    return Some(entry);
                }
                continue;
            }
            q = self
                .ready
                .wait_timeout(q, Duration::from_secs(1))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }
}

fn work(shared: &Shared, engine: &Engine, replica: &str) {
    use thread_priority::{ThreadPriority, set_current_thread_priority};
    if let Err(e) = set_current_thread_priority(ThreadPriority::Min) {
        tracing::warn!(error = ?e, "deferred estimates run at normal priority");
    }
    while let Some((field, at)) = shared.next() {
        // a panic in one field's estimate costs that update, not the thread
        let done = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            engine.update_estimate(&field, at, replica)
        }));
        let outcome = match done {
            Ok(Ok(true)) => "updated",
            Ok(Ok(false)) => "superseded",
            Ok(Err(e)) => {
                tracing::warn!(field = field.id, at = %at, error = %e,
                    "deferred state estimate failed; the next cycle replays it");
                "failed"
            }
            Err(_) => {
                tracing::error!(field = field.id, at = %at,
                    "deferred state estimate panicked; the next cycle replays it");
                "failed"
            }
        };
        shared.outcomes.with_label_values(&[outcome]).inc();
    }
}
