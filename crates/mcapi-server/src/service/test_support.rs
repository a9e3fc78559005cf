//! What the service's unit tests share: an observation as a client sends
//! it, and a runtime to await the manager's async calls on.

use super::wire::ObservationIn;

/// One observation of `state`, with `stimulus` (none on the first).
pub(super) fn obs(state: usize, stimulus: Option<Vec<f64>>) -> ObservationIn {
    ObservationIn {
        state: Some(state),
        observation: None,
        stimulus,
        action_taken: None,
        signal: None,
        signal_source: None,
        seq: None,
    }
}

/// A current-thread runtime with timers and I/O.
pub(super) fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
}
