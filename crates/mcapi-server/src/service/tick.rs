//! The tick loop: a fixed pool of worker threads serving a bounded queue of
//! planning work, off the async runtime.
//!
//! Two kinds of job: `Plan` (an async-mode session whose reward changed; a
//! session is queued at most once, so its work coalesces) and `Observe` (a
//! lockstep observation whose reply waits for its one LSTDQ update). The
//! work itself is the synchronous [`Session`] methods, which tests call
//! directly; this file only moves jobs to threads.
//!
//! The queue is a mutex-guarded deque with a condition variable: an idle
//! worker sleeps in the kernel until a job arrives, instead of spinning and
//! yielding as lock-free channels do while they wait (that spinning cost
//! about a tenth of a core under light load on a 2-core machine).

use std::collections::VecDeque;
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::Instant;

use parking_lot::{Condvar, Mutex};
use tokio::sync::oneshot;

use super::error::ServiceError;
use super::session::{Observed, Session, SessionRef};
use super::wire::ObservationIn;

/// Work for the pool.
pub enum Job {
    /// Plan once if the session's reward changed.
    Plan(SessionRef),
    /// Observe in lockstep and reply.
    Observe {
        /// The session.
        session: SessionRef,
        /// Observations, in order.
        batch: Vec<ObservationIn>,
        /// Where the reply goes (the requester awaits its durability).
        reply: oneshot::Sender<Observed>,
    },
}

struct Queue {
    jobs: VecDeque<Job>,
    /// Jobs being run by a worker right now.
    running: usize,
    open: bool,
}

struct Shared {
    queue: Mutex<Queue>,
    ready: Condvar,
    capacity: usize,
}

/// The worker pool.
pub struct TickPool {
    shared: Arc<Shared>,
    workers: Mutex<Vec<JoinHandle<()>>>,
}

impl TickPool {
    /// Starts `workers` threads over a queue of `capacity` jobs.
    pub fn start(workers: usize, capacity: usize) -> std::io::Result<Self> {
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue {
                jobs: VecDeque::new(),
                running: 0,
                open: true,
            }),
            ready: Condvar::new(),
            capacity: capacity.max(1),
        });
        let mut handles = Vec::with_capacity(workers);
        for i in 0..workers.max(1) {
            let shared = Arc::clone(&shared);
            handles.push(
                std::thread::Builder::new()
                    .name(format!("mcapi-tick-{i}"))
                    .spawn(move || worker(&shared))?,
            );
        }
        Ok(Self {
            shared,
            workers: Mutex::new(handles),
        })
    }

    /// Queues a job without waiting; a full queue or a stopping pool is
    /// `Unavailable`.
    pub fn submit(&self, job: Job) -> Result<(), ServiceError> {
        let mut q = self.shared.queue.lock();
        if !q.open {
            return Err(ServiceError::Unavailable(
                "the server is shutting down".into(),
            ));
        }
        if q.jobs.len() >= self.shared.capacity {
            return Err(ServiceError::Unavailable(
                "the tick queue is full; retry shortly".into(),
            ));
        }
        q.jobs.push_back(job);
        let n = q.jobs.len() + q.running;
        drop(q);
        self.shared.ready.notify_one();
        meters().queue_length.set(n as f64);
        Ok(())
    }

    /// Jobs waiting or running.
    pub fn queue_len(&self) -> usize {
        let q = self.shared.queue.lock();
        q.jobs.len() + q.running
    }

    /// Stops accepting jobs, lets the workers drain the queue and joins them.
    pub fn shutdown(&self) {
        self.shared.queue.lock().open = false;
        self.shared.ready.notify_all();
        let handles = std::mem::take(&mut *self.workers.lock());
        for h in handles {
            if h.join().is_err() {
                tracing::error!("a tick worker panicked");
            }
        }
    }
}

fn worker(shared: &Shared) {
    loop {
        let job = {
            let mut q = shared.queue.lock();
            loop {
                if let Some(job) = q.jobs.pop_front() {
                    q.running += 1;
                    break job;
                }
                if !q.open {
                    return;
                }
                shared.ready.wait(&mut q);
            }
        };
        // A panic is caught where a session's state is updated (the session
        // is then quarantined); this catch keeps the worker alive whatever
        // else panics, so lockstep requests never wait for a dead pool.
        if std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(job))).is_err() {
            tracing::error!("a tick job panicked; the worker goes on");
            metrics::counter!("mcapi_tick_panics_total").increment(1);
        }
        let mut q = shared.queue.lock();
        q.running -= 1;
        let n = q.jobs.len() + q.running;
        drop(q);
        meters().queue_length.set(n as f64);
    }
}

/// The meters of the tick path, each resolved from the metrics recorder
/// once, at first use: recording then costs no registry lookup. The
/// recorder is installed first if nothing has installed it yet (a handle
/// resolved without one would record nothing for the rest of the process).
pub(super) struct Meters {
    /// `mcapi_tick_seconds`: one LSTDQ update or observation, as run.
    pub tick_seconds: metrics::Histogram,
    /// `mcapi_tick_queue_length`: jobs queued or running.
    pub queue_length: metrics::Gauge,
    /// `mcapi_observations_total`.
    pub observations: metrics::Counter,
}

pub(super) fn meters() -> &'static Meters {
    static METERS: OnceLock<Meters> = OnceLock::new();
    METERS.get_or_init(|| {
        crate::telemetry::prometheus();
        Meters {
            tick_seconds: metrics::histogram!("mcapi_tick_seconds"),
            queue_length: metrics::gauge!("mcapi_tick_queue_length"),
            observations: metrics::counter!("mcapi_observations_total"),
        }
    })
}

/// Runs one job on the calling thread.
fn run(job: Job) {
    let started = Instant::now();
    match job {
        Job::Plan(session) => {
            session.dequeued();
            if let Err(e) = session.plan_if_needed() {
                log_plan_error(&session, &e);
            }
        }
        Job::Observe {
            session,
            batch,
            reply,
        } => {
            let result = session.observe(&batch, true);
            if let Err(e @ ServiceError::Algo(mcapi_core::AlgoError::Numerical(_))) = &result.result
            {
                log_plan_error(&session, e);
            }
            // The requester may have gone away; nothing to do then.
            let _ = reply.send(result);
        }
    }
    meters()
        .tick_seconds
        .record(started.elapsed().as_secs_f64());
}

/// Logs a failed policy update.
pub fn log_plan_error(session: &Session, e: &ServiceError) {
    tracing::error!(session = %session.id, error = ?e, "policy update failed");
}
