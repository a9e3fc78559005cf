//! The simulated hallway client: the world's states, actions and stimuli,
//! its next observation drawn from a seeded generator, and that
//! observation as REST JSON and as a gRPC message.

use mcapi_server::api::grpc::pb;
use rand::RngExt as _;
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

/// Hallway actions, in the preset's order.
pub const ACTIONS: [&str; 3] = ["left", "right", "stay"];
/// States of the hallway.
pub const STATES: usize = 50;

/// ξ on arrival in `s`: food at 10, rest at 40.
pub fn stimulus(s: usize) -> [f64; 2] {
    match s {
        10 => [6.0, 0.0],
        40 => [0.0, 6.0],
        _ => [0.0, 0.0],
    }
}

/// Whether action `a` is available in `s` (no left at 0, no right at 49).
pub fn available(s: usize, a: usize) -> bool {
    match a {
        0 => s > 0,
        1 => s + 1 < STATES,
        2 => true,
        _ => false,
    }
}

/// The state after taking `a` in `s`.
pub fn step_state(s: usize, a: usize) -> usize {
    assert!(available(s, a), "action {a} is not available in {s}");
    match a {
        0 => s - 1,
        1 => s + 1,
        _ => s,
    }
}

/// A simulated hallway client's next observation from `state` when the
/// server advised `advised`: usually takes the advice, sometimes (and
/// always when the advice is unknown) reports another available action.
/// The first observation (no state yet) lands in a random state. With
/// `names`, the action is reported by name half the time (one more draw).
pub fn next_hallway_obs(
    rng: &mut ChaCha8Rng,
    state: Option<usize>,
    advised: Option<usize>,
    names: bool,
) -> Obs {
    let Some(s) = state else {
        return Obs {
            state: rng.random_range(0..STATES),
            stimulus: None,
            taken: None,
            report: None,
            by_name: false,
        };
    };
    let report = advised.is_none() || rng.random_bool(0.1);
    let a = match advised {
        Some(a) if !report => a,
        _ => loop {
            let a = rng.random_range(0..ACTIONS.len());
            if available(s, a) {
                break a;
            }
        },
    };
    let next = step_state(s, a);
    Obs {
        state: next,
        stimulus: Some(stimulus(next)),
        taken: Some(a),
        report: report.then_some(a),
        by_name: names && rng.random_bool(0.5),
    }
}

/// One observation as the client sent it, resolved: `taken` is the action
/// whose pair its stimulus updates (the advised one unless `report`ed).
#[derive(Debug, Clone, PartialEq)]
pub struct Obs {
    /// The state arrived in.
    pub state: usize,
    /// Its stimulus (None on a session's first observation).
    pub stimulus: Option<[f64; 2]>,
    /// The action taken (None on the first observation).
    pub taken: Option<usize>,
    /// Reported as `action_taken` (by index or, if `by_name`, by name).
    pub report: Option<usize>,
    /// Report by name rather than index.
    pub by_name: bool,
}

impl Obs {
    /// The REST JSON of this observation.
    pub fn json(&self) -> Value {
        let mut v = json!({"state": self.state});
        if let Some(x) = self.stimulus {
            v["stimulus"] = json!(x);
        }
        if let Some(a) = self.report {
            v["action_taken"] = if self.by_name {
                json!(ACTIONS[a])
            } else {
                json!(a)
            };
        }
        v
    }

    /// The gRPC message of this observation.
    pub fn pb(&self, id: &str) -> pb::Observation {
        use pb::observation::ActionTaken;
        pb::Observation {
            session_id: id.into(),
            state: self.state as u64,
            stimulus: self.stimulus.map(|x| pb::Stimulus { values: x.to_vec() }),
            action_taken: self.report.map(|a| {
                if self.by_name {
                    ActionTaken::ActionName(ACTIONS[a].into())
                } else {
                    ActionTaken::ActionIndex(a as u32)
                }
            }),
            ..Default::default()
        }
    }
}
