//! An MCA-PI agent with a curiosity drive: docs/algorithm.md §7 "Coupling to the
//! agent" (paper Sec. 4.3).
//!
//! [`CuriousAgent`] owns an [`Agent`] whose model has the curiosity
//! dimension as its **last** stimulus dimension, ξ = [extrinsic…, ξ_cur], and
//! a [`CuriosityChannel`] that turns raw signal samples into ξ_cur (Eq. 7).
//! One tick, in this order:
//!
//! 1. the signal sample of the tick, if any, goes to the channel, giving ξ_cur
//!    (0 on ticks without a sample);
//! 2. the agent observes ξ = [extrinsic, ξ_cur] (Algorithm 1 lines 5-7 and
//!    Eq. 3, the same MCA update for every dimension, Λ = diag(1/ρ));
//! 3. if a module froze on this sample, the curiosity column of Ξ is
//!    re-initialised optimistically, Ξ\[:, cur\] ~ N(0, σ²) with the agent's σ
//!    (0.3 by default) and its own visit counts n_cur restarted at 0 (the
//!    paper's "initialised with optimistic values"; the column's rate is
//!    1/n_cur from the start);
//! 4. **condition (3) (ours, from Sec. 3.1):** while every known signal
//!    source is explained, ξ_cur is identically zero and needs no planning:
//!    D\[cur\] = 0, renormalised. When a known source becomes unexplained
//!    again, D\[cur\] = 1/√n, renormalised. Without it MCA turns D towards the
//!    never-stimulated curiosity dimension once both signals are learned,
//!    and the agent starves;
//! 5. plan (line 8-9) and act, as [`Agent::step`].
//!
//! The channel's seed is derived from the agent's, so a curious agent is a
//! deterministic function of its parameters and observations.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::agent::{Agent, AgentSnapshot, Observation, ObserveOutcome, Step};
use super::curiosity::{CuriosityChannel, CuriosityStep, ValidCuriosityParams};
use super::error::{AlgoError, MAX_STIMULUS, Result};
use super::lstdq::{PlanOutcome, PlanningModel};
use super::params::ValidParams;
use super::stimulus::OwnColumn;

/// Mixed into the agent's seed to seed the curiosity channel.
const CHANNEL_SEED_MIX: u64 = 0xC0_1D_5E_ED_CA_FE_F0_0D;

/// What the caller reports at a tick of a [`CuriousAgent`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CuriousObservation<'a> {
    /// s_{t+1}.
    pub state: usize,
    /// The extrinsic part of ξ(t+1) (n − 1 components); absent on the first
    /// observation only.
    pub stimulus: Option<&'a [f64]>,
    /// The raw signal sample received on arrival, with its source index.
    pub signal: Option<(usize, &'a [f64])>,
    /// a_t if it differs from the advised action.
    pub action_taken: Option<usize>,
}

impl<'a> CuriousObservation<'a> {
    /// The first observation: a state only.
    pub fn first(state: usize) -> Self {
        Self {
            state,
            stimulus: None,
            signal: None,
            action_taken: None,
        }
    }

    /// A later observation: extrinsic stimulus and an optional signal sample.
    pub fn new(state: usize, stimulus: &'a [f64], signal: Option<(usize, &'a [f64])>) -> Self {
        Self {
            state,
            stimulus: Some(stimulus),
            signal,
            action_taken: None,
        }
    }
}

/// The reply to one observation of a [`CuriousAgent`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CuriousStep {
    /// The agent's step (tick, next action, |r|, plan).
    pub step: Step,
    /// ξ_cur of this tick (0 without a signal sample).
    pub xi_cur: f64,
    /// What the channel did with the tick's sample, if there was one.
    pub curiosity: Option<CuriosityStep>,
    /// The curiosity column of Ξ was re-initialised (a module froze).
    pub column_reset: bool,
    /// Condition (3) holds after this tick: D\[cur\] is held at 0.
    pub suppressed: bool,
}

/// What [`CuriousAgent::observe`] did: steps 1-4 of a tick, before
/// planning.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CuriousObserved {
    /// The agent's tick and |r| (Eq. 3) for ξ = [extrinsic, ξ_cur].
    pub observed: ObserveOutcome,
    /// ξ_cur of this tick (0 without a signal sample).
    pub xi_cur: f64,
    /// What the channel did with the tick's sample, if there was one.
    pub curiosity: Option<CuriosityStep>,
    /// The curiosity column of Ξ was re-initialised (a module froze).
    pub column_reset: bool,
    /// Condition (3) holds after this tick: D\[cur\] is held at 0.
    pub suppressed: bool,
}

/// An [`Agent`] with the intMCA curiosity channel as its last stimulus
/// dimension (§7).
#[derive(Debug, Clone)]
pub struct CuriousAgent {
    agent: Agent,
    channel: CuriosityChannel,
    /// The curiosity dimension: n − 1.
    cur: usize,
    /// Condition (3) in force: D\[cur\] held at 0.
    suppressed: bool,
    /// The agent's tick at each module freeze, in library order.
    frozen_ticks: Vec<u64>,
    /// Scratch: the full stimulus [extrinsic, ξ_cur].
    xi: Vec<f64>,
}

/// Everything of a [`CuriousAgent`] a durable store keeps to resume it: the
/// agent's snapshot, the curiosity column's own visit counts (which
/// [`AgentSnapshot`]'s encoding leaves out), the channel and condition (3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CuriousSnapshot {
    /// The MCA-PI agent.
    pub agent: AgentSnapshot,
    /// The curiosity column's own visit counts n_cur.
    pub own_column: Option<OwnColumn>,
    /// The curiosity channel (modules, library, known sources).
    pub channel: CuriosityChannel,
    /// Condition (3) in force.
    pub suppressed: bool,
    /// The agent's tick at each module freeze.
    pub frozen_ticks: Vec<u64>,
}

impl CuriousAgent {
    /// A fresh agent (as [`Agent::new`]; its model's last stimulus
    /// dimension is curiosity, so the model needs at least 2) and a fresh
    /// channel for m-dimensional signals, seeded from the agent's seed.
    pub fn new(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        curiosity: ValidCuriosityParams,
        signal_dim: usize,
    ) -> Result<Self> {
        let n = ctx.model().n_stimuli();
        if n < 2 {
            return Err(AlgoError::InvalidParameter {
                name: "stimuli",
                reason: format!(
                    "a curious agent needs an extrinsic and a curiosity dimension, got {n}"
                ),
            });
        }
        let seed = params.seed ^ CHANNEL_SEED_MIX;
        let channel = CuriosityChannel::new(signal_dim, curiosity, seed)?;
        let mut agent = Agent::new(ctx, params);
        let cur = n - 1;
        agent.count_stimulus_column_separately(cur)?;
        Ok(Self {
            agent,
            channel,
            cur,
            suppressed: false,
            frozen_ticks: Vec::new(),
            xi: vec![0.0; n],
        })
    }

    /// One tick (module docs, steps 1-5). Nothing changes on error.
    pub fn step(&mut self, obs: &CuriousObservation<'_>) -> Result<CuriousStep> {
        let o = self.observe(obs)?;
        let plan = self.agent.needs_plan().then(|| self.agent.plan());
        let action = self
            .agent
            .act()
            .ok_or_else(|| AlgoError::Numerical("no state after an observation".into()))?;
        let plan = plan.transpose()?;
        Ok(CuriousStep {
            step: Step {
                tick: o.observed.tick,
                action,
                reward: o.observed.reward,
                plan,
            },
            xi_cur: o.xi_cur,
            curiosity: o.curiosity,
            column_reset: o.column_reset,
            suppressed: o.suppressed,
        })
    }

    /// Steps 1-4 of a tick (module docs): the channel learns from the
    /// sample, the agent observes ξ = [extrinsic, ξ_cur], the column reset
    /// and condition (3). Planning and acting are left to the caller
    /// ([`Self::plan`], [`Self::act`]), as with [`Agent::observe`]. Nothing
    /// changes on error.
    pub fn observe(&mut self, obs: &CuriousObservation<'_>) -> Result<CuriousObserved> {
        let extrinsic = obs.stimulus;
        if let Some(x) = extrinsic
            && x.len() != self.cur
        {
            return Err(AlgoError::ExtrinsicStimulusLength {
                got: x.len(),
                expected: self.cur,
            });
        }
        if extrinsic.is_none() && obs.signal.is_some() {
            return Err(AlgoError::FirstObservation { field: "signal" });
        }
        // Validate the agent's part with a placeholder ξ_cur before the
        // channel learns anything.
        if let Some(x) = extrinsic {
            self.xi[..self.cur].copy_from_slice(x);
        }
        self.xi[self.cur] = 0.0;
        fn inner<'x>(obs: &CuriousObservation<'_>, xi: &'x [f64]) -> Observation<'x> {
            Observation {
                state: obs.state,
                stimulus: obs.stimulus.map(|_| xi),
                action_taken: obs.action_taken,
            }
        }
        self.agent.validate(&inner(obs, &self.xi))?;
        let curiosity = match obs.signal {
            Some((source, x)) => Some(self.channel.observe(source, x)?),
            None => None,
        };
        let xi_cur = curiosity.map_or(0.0, |c| c.xi_cur);
        // ξ_cur is the server's own number, not the client's: Eq. 7 keeps
        // it in [0, clip], and the table bounds the clip far inside the
        // stimulus limit, so the agent never refuses it as if the client
        // had sent it.
        debug_assert!((0.0..=MAX_STIMULUS).contains(&xi_cur), "ξ_cur = {xi_cur:e}");
        self.xi[self.cur] = xi_cur;
        let xi = std::mem::take(&mut self.xi);
        let observed = self.agent.observe(&inner(obs, &xi));
        self.xi = xi;
        let observed = observed?;
        let column_reset = curiosity.is_some_and(|c| c.frozen.is_some());
        if column_reset {
            let sd = self.agent.params().optimistic_sd;
            self.agent.reset_stimulus_column(self.cur, sd)?;
            self.frozen_ticks.push(observed.tick);
        }
        self.apply_condition_3()?;
        Ok(CuriousObserved {
            observed,
            xi_cur,
            curiosity,
            column_reset,
            suppressed: self.suppressed,
        })
    }

    /// One LSTDQ policy update (Algorithm 1, lines 8-9), as [`Agent::plan`].
    pub fn plan(&mut self) -> Result<PlanOutcome> {
        self.agent.plan()
    }

    /// The next action, as [`Agent::act`].
    pub fn act(&mut self) -> Option<usize> {
        self.agent.act()
    }

    /// Records the action a reply advised, as [`Agent::set_advised_action`]
    /// (replaying a log).
    pub fn set_advised_action(&mut self, action: usize) -> Result<()> {
        self.agent.set_advised_action(action)
    }

    /// Resumes the policy version counter, as [`Agent::resume_policy_version`].
    pub fn resume_policy_version(&mut self, version: u64) {
        self.agent.resume_policy_version(version);
    }

    /// The agent's tick at each module freeze, in library order.
    pub fn frozen_ticks(&self) -> &[u64] {
        &self.frozen_ticks
    }

    /// The resumable state.
    pub fn snapshot(&self) -> CuriousSnapshot {
        CuriousSnapshot {
            agent: self.agent.snapshot(),
            own_column: self.agent.stimulus().own_column().cloned(),
            channel: self.channel.clone(),
            suppressed: self.suppressed,
            frozen_ticks: self.frozen_ticks.clone(),
        }
    }

    /// A curious agent resumed from a snapshot of one with the same model,
    /// parameters and signal dimension; refuses a snapshot that does not fit.
    pub fn restore(
        ctx: Arc<PlanningModel>,
        params: ValidParams,
        curiosity: &ValidCuriosityParams,
        signal_dim: usize,
        snap: CuriousSnapshot,
    ) -> Result<Self> {
        let n = ctx.model().n_stimuli();
        let bad = |what: String| Err(AlgoError::InvalidSnapshot(what));
        if n < 2 {
            return bad(format!(
                "a curious agent needs 2 stimuli, the model has {n}"
            ));
        }
        let cur = n - 1;
        if snap.own_column.as_ref().is_none_or(|c| c.dim != cur) {
            return bad(format!(
                "Ξ's own column is not the curiosity dimension {cur}"
            ));
        }
        if snap.channel.signal_dim() != signal_dim {
            return bad(format!(
                "the channel takes {}-dimensional signals, the session {signal_dim}",
                snap.channel.signal_dim()
            ));
        }
        if snap.channel.params() != curiosity {
            return bad("the channel's parameters differ from the session's".into());
        }
        if snap.frozen_ticks.len() != snap.channel.module_count() {
            return bad(format!(
                "{} freeze ticks for {} frozen modules",
                snap.frozen_ticks.len(),
                snap.channel.module_count()
            ));
        }
        let mut agent_snap = snap.agent;
        agent_snap.stimulus.restore_own_column(snap.own_column);
        let agent = Agent::restore(ctx, params, agent_snap)?;
        Ok(Self {
            agent,
            channel: snap.channel,
            cur,
            suppressed: snap.suppressed,
            frozen_ticks: snap.frozen_ticks,
            xi: vec![0.0; n],
        })
    }

    /// Condition (3) (§7, ours): D\[cur\] = 0 while every known source is
    /// explained; 1/√n, renormalised, when one becomes unexplained again.
    fn apply_condition_3(&mut self) -> Result<()> {
        let all = self.channel.all_explained();
        if all {
            self.agent.set_drive_component(self.cur, 0.0)?;
        } else if self.suppressed {
            let n = (self.cur + 1) as f64;
            self.agent.set_drive_component(self.cur, 1.0 / n.sqrt())?;
        }
        self.suppressed = all;
        Ok(())
    }

    /// The MCA-PI agent.
    pub fn agent(&self) -> &Agent {
        &self.agent
    }

    /// The curiosity channel.
    pub fn channel(&self) -> &CuriosityChannel {
        &self.channel
    }

    /// The curiosity dimension (the last).
    pub fn curiosity_dim(&self) -> usize {
        self.cur
    }

    /// Condition (3) in force: D\[cur\] is held at 0.
    pub fn suppressed(&self) -> bool {
        self.suppressed
    }

    /// The action advised by the last step.
    pub fn advised_action(&self) -> Option<usize> {
        self.agent.advised_action()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::basis::Basis;
    use crate::curiosity::{CuriosityParams, Eq6Source, Signals};
    use crate::model::EnvModel;
    use crate::params::AgentParams;

    /// A 3-state chain: food at 0, book signal at 2; stimuli food, curiosity.
    fn agent(seed: u64) -> CuriousAgent {
        let model =
            EnvModel::chain(3, vec!["food".into(), "curiosity".into()]).expect("chain model");
        let params = AgentParams {
            seed: Some(seed),
            ..Default::default()
        }
        .check(2, 0)
        .expect("params");
        let curiosity = CuriosityParams::default().check().expect("defaults");
        CuriousAgent::new(
            Arc::new(PlanningModel::new(model, Basis::Indicator)),
            params,
            curiosity,
            2,
        )
        .expect("curious agent")
    }

    /// Walks the chain; the book signal is delivered at state 2.
    fn walk(a: &mut CuriousAgent, ticks: usize) -> Vec<CuriousStep> {
        let mut signals = Signals::new(0.08);
        let mut state = a.agent().state().unwrap_or(1);
        let mut out = Vec::new();
        for _ in 0..ticks {
            state = match a.advised_action().unwrap_or(2) {
                0 => state.saturating_sub(1),
                1 => (state + 1).min(2),
                _ => state,
            };
            let food = [if state == 0 { 6.0 } else { 0.0 }];
            // The source's clock advances only when it delivers a sample.
            let x = (state == 2).then(|| signals.next(Eq6Source::Book));
            let signal = x.as_ref().map(|x| (0, &x[..]));
            out.push(
                a.step(&CuriousObservation::new(state, &food, signal))
                    .expect("step"),
            );
        }
        out
    }

    #[test]
    fn a_frozen_module_resets_the_column_and_suppresses_curiosity() {
        let mut a = agent(3);
        a.step(&CuriousObservation::first(1)).expect("first");
        let steps = walk(&mut a, 3000);
        let reset = steps
            .iter()
            .position(|s| s.column_reset)
            .expect("the book signal is learned and frozen within 3000 ticks");
        assert!(steps[..reset].iter().any(|s| s.xi_cur > 0.0));
        assert!(
            steps[reset].suppressed,
            "the only known source is explained"
        );
        assert_eq!(a.channel().module_count(), 1);
        // The freezing sample itself was learned (ξ_cur ≥ 0); from then on
        // D[cur] is held at exactly 0 and the explained samples give 0.
        for s in &steps[reset + 1..] {
            assert!(s.suppressed);
            assert_eq!(s.xi_cur, 0.0);
        }
        assert_eq!(a.agent().drive().vector()[1], 0.0);
        let d = a.agent().drive().vector();
        assert!((crate::drive::norm(d) - 1.0).abs() < 1e-12);
        let own = a.agent().stimulus().own_column().expect("own column");
        assert_eq!(own.dim, 1);
        // A new source (music) is known and unexplained: D[cur] = 1/√2,
        // renormalised from D = (±1, 0), i.e. 1/√3.
        let x = Signals::eq6(Eq6Source::Music, 0.0);
        let state = a.agent().state().expect("state");
        let s = a
            .step(&CuriousObservation::new(state, &[0.0], Some((1, &x))))
            .expect("music sample");
        assert!(!s.suppressed);
        let d = a.agent().drive().vector();
        assert!((d[1] - 1.0 / 3f64.sqrt()).abs() < 1e-12, "{d:?}");
    }

    #[test]
    fn same_seed_same_trajectory_and_bad_input_changes_nothing() {
        let run = |seed| {
            let mut a = agent(seed);
            a.step(&CuriousObservation::first(1)).expect("first");
            walk(&mut a, 400)
                .iter()
                .map(|s| (s.step.action, s.xi_cur.to_bits()))
                .collect::<Vec<_>>()
        };
        assert_eq!(run(7), run(7));
        let mut a = agent(1);
        let x = [0.0, 0.0];
        let err = a
            .step(&CuriousObservation::new(1, &[0.0], Some((0, &x))))
            .expect_err("signal on the first observation");
        assert_eq!(err, AlgoError::FirstObservation { field: "stimulus" });
        a.step(&CuriousObservation::first(1)).expect("first");
        let err = a
            .step(&CuriousObservation::new(1, &[0.0, 0.0], None))
            .expect_err("extrinsic part only");
        assert!(matches!(
            err,
            AlgoError::ExtrinsicStimulusLength { expected: 1, .. }
        ));
        let nan = [f64::NAN, 0.0];
        a.step(&CuriousObservation::new(1, &[0.0], Some((0, &nan))))
            .expect_err("non-finite signal");
        assert_eq!(a.channel().samples(), 0, "the channel learned nothing");
        assert_eq!(a.agent().tick(), 0);
    }

    #[test]
    fn a_replayed_log_rebuilds_the_reset_column_exactly() {
        // Live: step (observe, plan, act) with exploration, so act() draws
        // from the agent's RNG. Replay, as a store does: observe and the
        // advised action only, no act() and so none of those draws.
        let mut params = AgentParams {
            seed: Some(11),
            epsilon: Some(0.5),
            ..Default::default()
        };
        let make = |params: &AgentParams| {
            let model =
                EnvModel::chain(3, vec!["food".into(), "curiosity".into()]).expect("chain model");
            CuriousAgent::new(
                Arc::new(PlanningModel::new(model, Basis::Indicator)),
                params.clone().check(2, 0).expect("params"),
                CuriosityParams::default().check().expect("defaults"),
                2,
            )
            .expect("curious agent")
        };
        let mut live = make(&params);
        let mut replayed = make(&params);
        let first = live.step(&CuriousObservation::first(1)).expect("first");
        replayed
            .observe(&CuriousObservation::first(1))
            .expect("first");
        replayed
            .set_advised_action(first.step.action)
            .expect("advised action");
        let mut signals = Signals::new(0.08);
        let mut state: usize = 1;
        let mut froze = false;
        for _ in 0..3000 {
            state = match live.advised_action().unwrap_or(2) {
                0 => state.saturating_sub(1),
                1 => (state + 1).min(2),
                _ => state,
            };
            let food = [if state == 0 { 6.0 } else { 0.0 }];
            let x = (state == 2).then(|| signals.next(Eq6Source::Book));
            let obs = CuriousObservation::new(state, &food, x.as_ref().map(|x| (0, &x[..])));
            let step = live.step(&obs).expect("live step");
            replayed.observe(&obs).expect("replayed observation");
            replayed
                .set_advised_action(step.step.action)
                .expect("advised action");
            if step.column_reset {
                // Compared at once: with the sample-mean rate, a pair's first
                // visit after the reset overwrites its optimistic value.
                froze = true;
                break;
            }
        }
        assert!(froze, "a module froze, so the column was re-drawn");
        let column = |a: &CuriousAgent| {
            let xi = a.agent().stimulus().table();
            xi.iter()
                .skip(1)
                .step_by(2)
                .map(|x| x.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(column(&live), column(&replayed));
        assert_eq!(
            live.agent().stimulus().table(),
            replayed.agent().stimulus().table()
        );
        // The draws do depend on the seed.
        params.seed = Some(12);
        let mut other = make(&params);
        other.observe(&CuriousObservation::first(1)).expect("first");
        other.agent.reset_stimulus_column(1, 0.3).expect("reset");
        replayed.agent.reset_stimulus_column(1, 0.3).expect("reset");
        assert_ne!(column(&other), column(&replayed));
    }

    #[test]
    fn a_restored_snapshot_continues_bit_for_bit() {
        let mut a = agent(5);
        a.step(&CuriousObservation::first(1)).expect("first");
        let before = walk(&mut a, 2500);
        assert!(
            before.iter().any(|s| s.column_reset),
            "a module froze, so the snapshot holds a library and own counts"
        );
        assert_eq!(a.frozen_ticks().len(), a.channel().module_count());
        // Through the store's encoding, which drops the own column from Ξ.
        let bytes = postcard::to_stdvec(&a.snapshot()).expect("encode");
        let snap: CuriousSnapshot = postcard::from_bytes(&bytes).expect("decode");
        let ctx = Arc::clone(a.agent().planning_model());
        let curiosity = a.channel().params().clone();
        let mut b = CuriousAgent::restore(ctx, a.agent().params().clone(), &curiosity, 2, snap)
            .expect("restore");
        assert_eq!(b.snapshot(), a.snapshot());
        let key = |s: &CuriousStep| (s.step.action, s.xi_cur.to_bits(), s.step.reward.to_bits());
        let ka: Vec<_> = walk(&mut a, 800).iter().map(key).collect();
        let kb: Vec<_> = walk(&mut b, 800).iter().map(key).collect();
        assert_eq!(ka, kb);
        // A snapshot for another signal dimension is refused.
        let ctx = Arc::clone(a.agent().planning_model());
        let err =
            CuriousAgent::restore(ctx, a.agent().params().clone(), &curiosity, 3, a.snapshot())
                .expect_err("wrong signal dimension");
        assert!(matches!(err, AlgoError::InvalidSnapshot(_)), "{err}");
    }
}
