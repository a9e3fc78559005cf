//! The learner of a session: the core's MCA-PI agent, or the curious agent
//! with its curiosity channel, behind one interface.

use mcapi_core::{Agent, AlgoError, CuriousAgent, CuriousObservation, Observation, PlanOutcome};

use super::durable::{LearnedRecord, LearnerSnapshot};
use super::error::ServiceError;
use super::wire::TickCuriosity;

/// A session's learner: an MCA-PI agent, or one with a curiosity channel.
#[derive(Debug)]
#[expect(
    clippy::large_enum_variant,
    reason = "one per session, never moved after creation; the common plain agent stays unboxed"
)]
pub enum Learner {
    /// An MCA-PI agent.
    Plain(Agent),
    /// An agent with a curiosity channel (docs/algorithm.md §7).
    Curious(Box<CuriousAgent>),
}

/// What [`Learner::observe`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnerObserved {
    /// Ticks so far.
    pub tick: u64,
    /// |r| (Eq. 3).
    pub reward: f64,
    /// ξ_cur appended to the client's stimulus (curious sessions only).
    pub xi_cur: Option<f64>,
    /// The curiosity channel after the tick.
    pub curiosity: Option<TickCuriosity>,
}

impl Learner {
    /// The MCA-PI agent.
    pub fn agent(&self) -> &Agent {
        match self {
            Self::Plain(a) => a,
            Self::Curious(c) => c.agent(),
        }
    }

    /// The curious agent, if this is one.
    pub fn curious(&self) -> Option<&CuriousAgent> {
        match self {
            Self::Plain(_) => None,
            Self::Curious(c) => Some(c),
        }
    }

    /// Algorithm 1 lines 5-7 (and §7 steps 1-4 with a channel); no plan.
    pub fn observe(
        &mut self,
        obs: &Observation<'_>,
        signal: Option<(usize, &[f64])>,
    ) -> Result<LearnerObserved, ServiceError> {
        match self {
            Self::Plain(agent) => {
                if signal.is_some() {
                    return Err(ServiceError::field(
                        "signal",
                        "this session has no curiosity channel (declare `agent.curiosity` when creating it)",
                    ));
                }
                let out = agent.observe(obs)?;
                Ok(LearnerObserved {
                    tick: out.tick,
                    reward: out.reward,
                    xi_cur: None,
                    curiosity: None,
                })
            }
            Self::Curious(agent) => {
                let out = agent.observe(&CuriousObservation {
                    state: obs.state,
                    stimulus: obs.stimulus,
                    signal,
                    action_taken: obs.action_taken,
                })?;
                Ok(LearnerObserved {
                    tick: out.observed.tick,
                    reward: out.observed.reward,
                    xi_cur: Some(out.xi_cur),
                    curiosity: Some(TickCuriosity {
                        xi_cur: out.xi_cur,
                        epsilon: agent.channel().epsilon(),
                        modules: agent.channel().module_count(),
                        source: signal.map(|(s, _)| s),
                    }),
                })
            }
        }
    }

    /// Refuses an observation that would make a learned model store more
    /// than `cap` (pair, successor) entries (docs/algorithm.md §8): only a
    /// successor never seen before from its pair adds one. Nothing
    /// changes; sessions with posted transitions always pass.
    pub fn check_learned_room(
        &self,
        obs: &Observation<'_>,
        cap: usize,
    ) -> Result<(), ServiceError> {
        let agent = self.agent();
        let Some(learned) = agent.learned() else {
            return Ok(());
        };
        let Some(p) = agent.validate(obs)? else {
            return Ok(());
        };
        let counts = learned.counts();
        let seen = counts
            .successors(p)
            .iter()
            .any(|&(t, _)| t as usize == obs.state);
        if !seen && counts.entries() >= cap {
            return Err(ServiceError::LimitExceeded(format!(
                "the learned model already stores {} transitions, its limit (`model.learned.max_transitions`: |pairs| x |states|, at most --max-transitions and what the session's budgets allow); `state` {} was never reached from this state and action before, so it would be one more",
                counts.entries(),
                obs.state
            )));
        }
        Ok(())
    }

    /// True when a snapshot of this learner restores to one that continues
    /// bit for bit as it would ([`Agent::restores_exactly`]; a curiosity
    /// channel's snapshot holds all of its state).
    pub fn restores_exactly(&self) -> bool {
        self.agent().restores_exactly()
    }

    /// True when R changed since the last policy update.
    pub fn needs_plan(&self) -> bool {
        self.agent().needs_plan()
    }

    /// One LSTDQ policy update (Algorithm 1, lines 8-9).
    pub fn plan(&mut self) -> Result<PlanOutcome, AlgoError> {
        match self {
            Self::Plain(a) => a.plan(),
            Self::Curious(c) => c.plan(),
        }
    }

    /// The next action (line 10).
    pub fn act(&mut self) -> Option<usize> {
        match self {
            Self::Plain(a) => a.act(),
            Self::Curious(c) => c.act(),
        }
    }

    /// Records the action a logged reply advised (replay).
    pub fn set_advised_action(&mut self, action: usize) -> Result<(), AlgoError> {
        match self {
            Self::Plain(a) => a.set_advised_action(action),
            Self::Curious(c) => c.set_advised_action(action),
        }
    }

    /// Resumes the policy version counter (replay).
    pub fn resume_policy_version(&mut self, version: u64) {
        match self {
            Self::Plain(a) => a.resume_policy_version(version),
            Self::Curious(c) => c.resume_policy_version(version),
        }
    }

    /// The resumable state (with the learned counts for an agent that
    /// learns its transitions, docs/algorithm.md §8).
    pub fn snapshot(&self) -> LearnerSnapshot {
        match self {
            Self::Plain(a) => match a.learned_snapshot() {
                // The history's known fractions are the session's to add.
                Some(agent) => LearnerSnapshot::Learned(Box::new(LearnedRecord {
                    agent,
                    history_known: Vec::new(),
                })),
                None => LearnerSnapshot::Plain(a.snapshot()),
            },
            Self::Curious(c) => LearnerSnapshot::Curious(Box::new(c.snapshot())),
        }
    }
}
