//! The learner of a session: the core's MCA-PI agent, the curious agent
//! with its curiosity channel, or the agent of a continuous world, behind
//! one interface.

use mcapi_core::continuous::{ContinuousAgent, ContinuousObservation};
use mcapi_core::drive::Drive;
use mcapi_core::{Agent, AlgoError, CuriousAgent, CuriousObservation, Observation};

use super::durable::{LearnedRecordRef, LearnerSnapshotRef};
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
    /// The agent of a continuous world (docs/algorithm.md §9).
    Continuous(Box<ContinuousAgent>),
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
    /// Hints the CPU to load the agent's tables
    /// ([`mcapi_core::prefetch`]); a continuous world's agent is left alone.
    pub fn prefetch(&self) {
        match self {
            Self::Plain(a) => a.prefetch(),
            Self::Curious(c) => c.agent().prefetch(),
            Self::Continuous(_) => {}
        }
    }

    /// The MCA-PI agent of a model with numbered states; `None` for a
    /// continuous world.
    pub fn agent(&self) -> Option<&Agent> {
        match self {
            Self::Plain(a) => Some(a),
            Self::Curious(c) => Some(c.agent()),
            Self::Continuous(_) => None,
        }
    }

    /// The curious agent, if this is one.
    pub fn curious(&self) -> Option<&CuriousAgent> {
        match self {
            Self::Curious(c) => Some(c),
            Self::Plain(_) | Self::Continuous(_) => None,
        }
    }

    /// The continuous agent, if this is one.
    pub fn continuous(&self) -> Option<&ContinuousAgent> {
        match self {
            Self::Continuous(c) => Some(c),
            Self::Plain(_) | Self::Curious(_) => None,
        }
    }

    /// Ticks so far.
    pub fn tick(&self) -> u64 {
        match self.agent() {
            Some(a) => a.tick(),
            None => self.continuous().map_or(0, ContinuousAgent::tick),
        }
    }

    /// The drive D.
    pub fn drive(&self) -> &Drive {
        match self {
            Self::Plain(a) => a.drive(),
            Self::Curious(c) => c.agent().drive(),
            Self::Continuous(c) => c.drive(),
        }
    }

    /// Policy updates applied.
    pub fn policy_version(&self) -> u64 {
        match self {
            Self::Plain(a) => a.policy_version(),
            Self::Curious(c) => c.agent().policy_version(),
            Self::Continuous(c) => c.policy_version(),
        }
    }

    /// The action advised at the current state or observation.
    pub fn advised_action(&self) -> Option<usize> {
        match self {
            Self::Plain(a) => a.advised_action(),
            Self::Curious(c) => c.agent().advised_action(),
            Self::Continuous(c) => c.advised_action(),
        }
    }

    /// ‖Q_t − Q_{t+1}‖ of the last policy update (0 for a continuous
    /// world, whose planner keeps no table to compare).
    pub fn lstdq_error(&self) -> f64 {
        self.agent().map_or(0.0, |a| a.last_plan().lstdq_error)
    }

    /// The action names.
    pub fn actions(&self) -> &[String] {
        match self {
            Self::Plain(a) => a.planning_model().model().actions(),
            Self::Curious(c) => c.agent().planning_model().model().actions(),
            Self::Continuous(c) => &c.model().spec.actions,
        }
    }

    /// The known fraction of a learned model (docs/algorithm.md §8).
    pub fn known_fraction(&self) -> Option<f64> {
        self.agent()?.learned().map(|l| l.known_fraction())
    }

    /// Lines 5-7 of a continuous world's tick (docs/algorithm.md §9); no
    /// plan, no action.
    pub fn observe_continuous(
        &mut self,
        obs: &ContinuousObservation<'_>,
    ) -> Result<LearnerObserved, ServiceError> {
        let Self::Continuous(agent) = self else {
            return Err(ServiceError::field(
                "observation",
                "this session's model has numbered states: send `state`",
            ));
        };
        let out = agent.observe(obs)?;
        Ok(LearnerObserved {
            tick: out.tick,
            reward: out.reward,
            xi_cur: None,
            curiosity: None,
        })
    }

    /// Algorithm 1 lines 5-7 (and §7 steps 1-4 with a channel); no plan.
    pub fn observe(
        &mut self,
        obs: &Observation<'_>,
        signal: Option<(usize, &[f64])>,
    ) -> Result<LearnerObserved, ServiceError> {
        match self {
            Self::Continuous(_) => Err(ServiceError::field(
                "state",
                "this session's model is continuous: send `observation`, a vector, instead of `state`",
            )),
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
        let Some(agent) = self.agent() else {
            return Ok(());
        };
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
    /// channel's snapshot holds all of its state; a continuous world's
    /// snapshot holds its whole agent, docs/algorithm.md §9.7).
    pub fn restores_exactly(&self) -> bool {
        match self {
            Self::Continuous(_) => true,
            Self::Plain(_) | Self::Curious(_) => self.agent().is_some_and(Agent::restores_exactly),
        }
    }

    /// True when R changed since the last policy update.
    pub fn needs_plan(&self) -> bool {
        match self {
            Self::Continuous(c) => c.needs_plan(),
            Self::Plain(a) => a.needs_plan(),
            Self::Curious(c) => c.agent().needs_plan(),
        }
    }

    /// Runs the first policy update on a copy, which is dropped: whether
    /// the planner can factorise its system for the initial policy (the
    /// copy's Ξ and D are the fresh agent's, so its factorisation is the
    /// one the session's first plan makes). A continuous world's planner
    /// regularises itself and has nothing to check.
    pub fn try_first_plan(&self) -> Result<(), AlgoError> {
        match self {
            Self::Plain(a) => a.clone().plan().map(drop),
            Self::Curious(c) => c.as_ref().clone().plan().map(drop),
            Self::Continuous(_) => Ok(()),
        }
    }

    /// One policy update (Algorithm 1, lines 8-9).
    pub fn plan(&mut self) -> Result<(), AlgoError> {
        match self {
            Self::Plain(a) => a.plan().map(drop),
            Self::Curious(c) => c.plan().map(drop),
            Self::Continuous(c) => {
                c.plan();
                Ok(())
            }
        }
    }

    /// The next action (line 10).
    pub fn act(&mut self) -> Option<usize> {
        match self {
            Self::Plain(a) => a.act(),
            Self::Curious(c) => c.act(),
            Self::Continuous(c) => c.act().map(|(a, _)| a),
        }
    }

    /// Records the action a logged reply advised (replay). A continuous
    /// world's agent chooses it again ([`Self::act`]): it must be the same.
    pub fn set_advised_action(&mut self, action: usize) -> Result<(), AlgoError> {
        match self {
            Self::Plain(a) => a.set_advised_action(action),
            Self::Curious(c) => c.set_advised_action(action),
            Self::Continuous(c) => match c.act() {
                Some((a, _)) if a == action => Ok(()),
                other => Err(AlgoError::InvalidSnapshot(format!(
                    "the replayed agent advises {:?}, the log says {action}",
                    other.map(|(a, _)| a)
                ))),
            },
        }
    }

    /// Resumes the policy version counter (replay).
    pub fn resume_policy_version(&mut self, version: u64) {
        match self {
            Self::Plain(a) => a.resume_policy_version(version),
            Self::Curious(c) => c.resume_policy_version(version),
            // Replayed plan by plan, its counter is the live one.
            Self::Continuous(_) => {}
        }
    }

    /// The resumable state, for encoding, borrowed rather than copied
    /// (with the learned counts for an agent that learns its transitions,
    /// docs/algorithm.md §8; a continuous world's agent whole,
    /// docs/algorithm.md §9.7; a curious agent's copied): it encodes to the bytes of the
    /// [`super::durable::LearnerSnapshot`] that recovery decodes.
    pub fn snapshot(&self) -> LearnerSnapshotRef<'_> {
        match self {
            Self::Plain(a) => match a.learned_snapshot_ref() {
                // The history's known fractions are the session's to add.
                Some(agent) => LearnerSnapshotRef::Learned(Box::new(LearnedRecordRef {
                    agent,
                    history_known: Vec::new(),
                })),
                None => LearnerSnapshotRef::Plain(a.snapshot_ref()),
            },
            Self::Curious(c) => LearnerSnapshotRef::Curious(Box::new(c.snapshot())),
            // The session adds its ring's observations.
            Self::Continuous(c) => LearnerSnapshotRef::continuous(c.snapshot_ref()),
        }
    }
}
