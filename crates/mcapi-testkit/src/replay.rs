//! The exact in-memory replay a served session is compared with: a core
//! agent built as the server builds it, fed the observations the server
//! applied, checked against every reply that was seen.

use std::sync::Arc;

use mcapi_core::model::hallway;
use mcapi_core::{Agent, AgentParams, Basis, Observation, PlanningModel};

use crate::floats::assert_bits_eq;
use crate::hallway::Obs;
use crate::reply::Reply;

/// The agent parameters a session with this seed and ε has.
pub fn params(seed: u64, epsilon: Option<f64>) -> AgentParams {
    AgentParams {
        seed: Some(seed),
        epsilon,
        ..AgentParams::default()
    }
}

/// A fresh core agent on the hallway, as the server builds it.
pub fn core_agent(params: &AgentParams) -> Agent {
    let preset = hallway();
    let ctx = Arc::new(PlanningModel::new(preset.model, Basis::Indicator));
    Agent::new(ctx, params.check(2, 0).expect("parameters"))
}

/// One tick of the expected history.
#[derive(Debug, Clone, PartialEq)]
pub struct Expected {
    /// Tick.
    pub tick: u64,
    /// State arrived in.
    pub state: usize,
    /// D after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
    /// The advised action, if the reply was seen.
    pub action: Option<usize>,
    /// The known fraction after the tick, for an agent that learns its
    /// transitions.
    pub known_fraction: Option<f64>,
}

/// Replays `applied` observations through a core agent (observe only: Ξ,
/// visits, D and the tick are pure functions of them), checking every
/// reply that was seen against it; returns the agent and the history.
pub fn replay(
    params: &AgentParams,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) -> (Agent, Vec<Expected>) {
    replay_on(core_agent(params), applied, ctx)
}

/// [`replay`] through a given fresh agent (one that learns its
/// transitions, say): the counts N(s, a, s′) are pure functions of the
/// observations too.
pub fn replay_on(
    mut agent: Agent,
    applied: &[(Obs, Option<Reply>)],
    ctx: &str,
) -> (Agent, Vec<Expected>) {
    let mut history = Vec::new();
    for (i, (obs, reply)) in applied.iter().enumerate() {
        let out = agent
            .observe(&Observation {
                state: obs.state,
                stimulus: obs.stimulus.as_ref().map(|x| &x[..]),
                action_taken: obs.taken,
            })
            .unwrap_or_else(|e| panic!("{ctx}: replay of observation {i} {obs:?}: {e}"));
        if let Some(r) = reply {
            assert_eq!(r.tick, out.tick, "{ctx}: tick of reply {i}");
            assert_bits_eq(
                &r.drive,
                agent.drive().vector(),
                &format!("{ctx}: drive of reply {i}"),
            );
            assert_eq!(
                r.reward.to_bits(),
                out.reward.to_bits(),
                "{ctx}: reward of reply {i}"
            );
        }
        if obs.stimulus.is_some() {
            history.push(Expected {
                tick: out.tick,
                state: obs.state,
                drive: agent.drive().vector().to_vec(),
                reward: out.reward,
                action: reply.as_ref().map(|r| r.action),
                known_fraction: agent.learned().map(|l| l.known_fraction()),
            });
        }
    }
    (agent, history)
}
