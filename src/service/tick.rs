//! The tick loop: a fixed pool of worker threads serving a bounded queue of
//! planning work, off the async runtime.
//!
//! Two kinds of job: `Plan` (an async-mode session whose reward changed; a
//! session is queued at most once, so its work coalesces) and `Observe` (a
//! lockstep observation whose reply waits for its one LSTDQ update). The
//! work itself is the synchronous [`Session`] methods, which tests call
//! directly; this file only moves jobs to threads.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::thread::JoinHandle;
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender, TrySendError, bounded};
use parking_lot::Mutex;
use tokio::sync::oneshot;

use super::error::ServiceError;
use super::session::{ObservationIn, Session, SessionRef, StepOut};

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
        /// Where the reply goes.
        reply: oneshot::Sender<Result<Vec<StepOut>, ServiceError>>,
    },
}

/// The worker pool.
pub struct TickPool {
    tx: Mutex<Option<Sender<Job>>>,
    workers: Mutex<Vec<JoinHandle<()>>>,
    pending: Arc<AtomicUsize>,
}

impl TickPool {
    /// Starts `workers` threads over a queue of `capacity` jobs.
    pub fn start(workers: usize, capacity: usize) -> std::io::Result<Self> {
        let (tx, rx) = bounded::<Job>(capacity.max(1));
        let pending = Arc::new(AtomicUsize::new(0));
        let mut handles = Vec::with_capacity(workers);
        for i in 0..workers.max(1) {
            let rx = rx.clone();
            let pending = Arc::clone(&pending);
            handles.push(
                std::thread::Builder::new()
                    .name(format!("mcapi-tick-{i}"))
                    .spawn(move || worker(&rx, &pending))?,
            );
        }
        Ok(Self {
            tx: Mutex::new(Some(tx)),
            workers: Mutex::new(handles),
            pending,
        })
    }

    /// Queues a job without waiting; a full queue or a stopping pool is
    /// `Unavailable`.
    pub fn submit(&self, job: Job) -> Result<(), ServiceError> {
        let guard = self.tx.lock();
        let Some(tx) = guard.as_ref() else {
            return Err(ServiceError::Unavailable(
                "the server is shutting down".into(),
            ));
        };
        // Counted before sending: a worker may finish the job before
        // `try_send` returns.
        let n = self.pending.fetch_add(1, Ordering::Relaxed) + 1;
        match tx.try_send(job) {
            Ok(()) => {
                metrics::gauge!("mcapi_tick_queue_length").set(n as f64);
                Ok(())
            }
            Err(e) => {
                self.pending.fetch_sub(1, Ordering::Relaxed);
                Err(ServiceError::Unavailable(match e {
                    TrySendError::Full(_) => "the tick queue is full; retry shortly".into(),
                    TrySendError::Disconnected(_) => "the server is shutting down".into(),
                }))
            }
        }
    }

    /// Jobs waiting or running.
    pub fn queue_len(&self) -> usize {
        self.pending.load(Ordering::Relaxed)
    }

    /// Stops accepting jobs, lets the workers drain the queue and joins them.
    pub fn shutdown(&self) {
        self.tx.lock().take();
        let handles = std::mem::take(&mut *self.workers.lock());
        for h in handles {
            if h.join().is_err() {
                tracing::error!("a tick worker panicked");
            }
        }
    }
}

fn worker(rx: &Receiver<Job>, pending: &AtomicUsize) {
    while let Ok(job) = rx.recv() {
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
                if let Err(e @ ServiceError::Algo(crate::algo::AlgoError::Numerical(_))) = &result {
                    log_plan_error(&session, e);
                }
                // The requester may have gone away; nothing to do then.
                let _ = reply.send(result);
            }
        }
        metrics::histogram!("mcapi_tick_seconds").record(started.elapsed().as_secs_f64());
        let n = pending.fetch_sub(1, Ordering::Relaxed) - 1;
        metrics::gauge!("mcapi_tick_queue_length").set(n as f64);
    }
}

fn log_plan_error(session: &Session, e: &ServiceError) {
    tracing::error!(session = %session.id, error = ?e, "policy update failed");
}
