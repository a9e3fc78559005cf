//! Setting a session up: its model parsed and checked against the limits,
//! the planning model (shared by every session of the same model, built
//! once, a few at a time), its agent configuration checked, its learner
//! built. Creation and recovery both build here.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::{SystemTime, UNIX_EPOCH};

use parking_lot::Mutex;

use mcapi_core::continuous::{ContinuousAgent, ContinuousBasisSpec, ContinuousModel};
use mcapi_core::{Agent, AlgoError, Basis, CuriousAgent, PlanningModel};

use super::agent_config::{EffectiveConfig, SessionConfig};
use super::cost;
use super::error::ServiceError;
use super::learner::Learner;
use super::limits::Limits;
use super::spec::ModelInput;
use super::wire::{BasisSummary, GridLayout, LearnedSummary, ModelSummary};

/// A counting semaphore for model builds: at most `slots` at once, and at
/// most `queue` more waiting; beyond that a create is refused with 503
/// instead of piling up blocking threads.
struct BuildSlots {
    state: Mutex<(usize, usize)>,
    freed: parking_lot::Condvar,
    slots: usize,
    queue: usize,
}

struct BuildSlot<'a>(&'a BuildSlots);

impl BuildSlots {
    fn new(slots: usize) -> Self {
        Self {
            state: Mutex::new((0, 0)),
            freed: parking_lot::Condvar::new(),
            slots: slots.max(1),
            queue: 8 * slots.max(1),
        }
    }

    /// Waits for a slot (blocking: call off the async runtime).
    fn acquire(&self) -> Result<BuildSlot<'_>, ServiceError> {
        let mut st = self.state.lock();
        if st.0 >= self.slots {
            if st.1 >= self.queue {
                let building = match st.0 {
                    1 => "1 session is".to_owned(),
                    n => format!("{n} sessions are"),
                };
                return Err(ServiceError::Unavailable(format!(
                    "{building} being created and {} more wait; retry shortly",
                    st.1
                )));
            }
            st.1 += 1;
            while st.0 >= self.slots {
                self.freed.wait(&mut st);
            }
            st.1 -= 1;
        }
        st.0 += 1;
        Ok(BuildSlot(self))
    }
}

impl Drop for BuildSlot<'_> {
    fn drop(&mut self) {
        self.0.state.lock().0 -= 1;
        self.0.freed.notify_one();
    }
}

/// The model summary of every session sharing a planning model, built once
/// with it and shared (interned) by them: its names, basis and grid layout
/// are not copied into each session.
type Built = Arc<ModelSummary>;

/// The summary of a model as built: the basis chosen and the grid layout.
fn summary_of(
    ctx: &PlanningModel,
    basis: BasisSummary,
    layout: Option<GridLayout>,
    learned: Option<LearnedSummary>,
) -> ModelSummary {
    let model = ctx.model();
    ModelSummary {
        states: model.states(),
        actions: model.actions().to_vec(),
        stimuli: model.stimuli().to_vec(),
        pairs: model.n_pairs(),
        transitions: model.n_transitions(),
        deterministic: model.is_deterministic(),
        basis,
        features: ctx.n_features(),
        layout,
        learned,
        continuous: None,
    }
}

/// The summary of a continuous world as built (docs/algorithm.md §9).
fn continuous_summary(model: &ContinuousModel) -> ModelSummary {
    let (kind, k) = match model.spec.basis {
        Some(ContinuousBasisSpec::Fourier { .. }) => ("fourier", model.features.len()),
        Some(ContinuousBasisSpec::Rbf { .. }) => ("rbf", model.features.len()),
        Some(ContinuousBasisSpec::Tiles { .. }) => ("tiles", model.features.len()),
        Some(ContinuousBasisSpec::Pvf { .. }) => ("pvf", model.features.len()),
        // `build` fills the effective basis in.
        None => ("default", model.features.len()),
    };
    ModelSummary {
        states: 0,
        actions: model.spec.actions.clone(),
        stimuli: model.spec.stimuli.clone(),
        pairs: 0,
        transitions: 0,
        deterministic: false,
        basis: BasisSummary {
            kind: kind.into(),
            k,
        },
        features: k * model.n_actions(),
        layout: None,
        learned: None,
        continuous: Some(model.spec.clone()),
    }
}

/// SplitMix64, for seeds and shards.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// What every session build shares: the planning models by model, the
/// bound on concurrent builds and the seed source.
pub(super) struct Setup {
    models: Mutex<HashMap<String, (Weak<PlanningModel>, Built)>>,
    seed_counter: AtomicU64,
    builds: BuildSlots,
}

impl Setup {
    /// Builds at most `workers` planning models at once.
    pub(super) fn new(workers: usize) -> Self {
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        Self {
            models: Mutex::new(HashMap::new()),
            seed_counter: AtomicU64::new(splitmix(now ^ u64::from(std::process::id()))),
            builds: BuildSlots::new(workers),
        }
    }

    pub(super) fn fresh_u64(&self) -> u64 {
        splitmix(
            self.seed_counter
                .fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed),
        )
    }

    /// The shared planning model for `input`, built once per distinct model,
    /// with what a session's model summary takes from its build.
    fn planning_model(
        &self,
        input: &ModelInput,
        curious: bool,
        limits: &Limits,
    ) -> Result<(Arc<PlanningModel>, Built), ServiceError> {
        let key = format!("{}:curious={curious}", input.cache_key());
        if let Some((weak, built)) = self.models.lock().get(&key)
            && let Some(ctx) = weak.upgrade()
        {
            return Ok((ctx, Arc::clone(built)));
        }
        // Built outside the lock (PVFs cost an eigendecomposition), a few at
        // a time.
        let _slot = self.builds.acquire()?;
        let (model, basis_spec) = input.build(limits, curious)?;
        let basis = Basis::build_checked(&basis_spec, &model).map_err(|e| match e {
            // A basis the solver could not compute (the sparse PVF solver
            // gives up on some graphs) is no fault of the server's: say
            // which basis, and what to ask for instead.
            AlgoError::Numerical(detail) => ServiceError::field(
                "model.basis",
                format!(
                    "the {} basis of this model could not be computed ({detail}); ask for                      `{{\"kind\": \"indicator\"}}` or fewer proto-value functions (`k`)",
                    BasisSummary::of(&basis_spec).kind
                ),
            ),
            other => other.into(),
        })?;
        let ctx = Arc::new(PlanningModel::new(model, basis));
        let learned = input.learning().map(|l| LearnedSummary {
            known_after: l.known_after,
            optimism: l.optimism,
            max_transitions: limits.learned_transitions(ctx.model()),
        });
        let built = Arc::new(summary_of(
            &ctx,
            BasisSummary::of(&basis_spec),
            input.layout(),
            learned,
        ));
        let mut models = self.models.lock();
        models.retain(|_, (w, _)| w.strong_count() > 0);
        if let Some((weak, existing_built)) = models.get(&key)
            && let Some(existing) = weak.upgrade()
        {
            return Ok((existing, Arc::clone(existing_built)));
        }
        models.insert(key, (Arc::downgrade(&ctx), Arc::clone(&built)));
        Ok((ctx, built))
    }

    /// Builds the agent of a session (fresh, or the base of a recovery).
    pub(super) fn build(
        &self,
        input: &ModelInput,
        agent: &SessionConfig,
        limits: &Limits,
    ) -> Result<(Learner, Arc<ModelSummary>, EffectiveConfig), ServiceError> {
        limits.check_config(agent)?;
        if let Some(spec) = input.continuous() {
            if agent.curiosity.is_some() {
                return Err(ServiceError::field(
                    "agent.curiosity",
                    "a curiosity channel needs a model with numbered states; this model is continuous",
                ));
            }
            // Sizes and names before anything is built.
            if spec.stimuli.len() > limits.max_stimuli {
                return Err(ServiceError::LimitExceeded(format!(
                    "`model.stimuli` has {} names; the limit is {} (--max-stimuli)",
                    spec.stimuli.len(),
                    limits.max_stimuli
                )));
            }
            limits.check_names("model.actions", &spec.actions)?;
            limits.check_names("model.stimuli", &spec.stimuli)?;
            let model = ModelInput::build_continuous(spec)?;
            let params = agent.params().check(model.n_stimuli(), self.fresh_u64())?;
            let config = agent.effective(&params);
            let summary = Arc::new(continuous_summary(&model));
            let learner = Learner::Continuous(Box::new(ContinuousAgent::new(model, params)));
            return Ok((learner, summary, config));
        }
        if agent.curiosity.is_some() && input.learning().is_some() {
            return Err(ServiceError::field(
                "agent.curiosity",
                "a curiosity channel needs a model with posted transitions; this model learns them (`learn`)",
            ));
        }
        let (ctx, summary) = self.planning_model(input, agent.curiosity.is_some(), limits)?;
        let params = agent
            .params()
            .check(ctx.model().n_stimuli(), self.fresh_u64())?;
        let config = agent.effective(&params);
        let summary = within_budget(summary, &config, limits);
        let learner = match (&agent.curiosity, input.learning()) {
            (None, None) => Learner::Plain(Agent::new(ctx, params)),
            // docs/algorithm.md §8: the same agent, planning on P̂.
            (None, Some(learned)) => Learner::Plain(
                Agent::new_learned(ctx, params, learned)
                    .map_err(|e| ServiceError::algo_at("model.learning", e))?,
            ),
            // A learned model with a channel was refused above.
            (Some(c), _) => {
                let checked = c
                    .params
                    .check()
                    .map_err(|e| ServiceError::algo_at("agent.curiosity.params", e))?;
                Learner::Curious(Box::new(
                    CuriousAgent::new(ctx, params, checked, c.signal_dim)
                        .map_err(|e| ServiceError::algo_at("agent.curiosity", e))?,
                ))
            }
        };
        if summary.basis.kind == "custom" {
            // A client's features can be well conditioned and still leave
            // the planner a system it cannot solve at this discount: refuse
            // the session now rather than answer every observation 500.
            learner.try_first_plan().map_err(|e| match e {
                AlgoError::Numerical(detail) => ServiceError::Algo(AlgoError::InvalidBasis(format!(
                    "`state_features`: the planner cannot solve its first policy update with these features at `gamma` = {} and `ridge` = {} ({detail}); scale the features alike, or lower `gamma` or raise `ridge`",
                    config.gamma, config.ridge
                ))),
                other => other.into(),
            })?;
        }
        Ok((learner, summary, config))
    }
}

/// A learned session's summary with its cap on stored transitions lowered
/// to what the per-session budgets allow for its configuration
/// ([`cost::learned_cap_within`]); other summaries as they are (shared).
fn within_budget(
    summary: Arc<ModelSummary>,
    config: &EffectiveConfig,
    limits: &Limits,
) -> Arc<ModelSummary> {
    let Some(learned) = &summary.learned else {
        return summary;
    };
    let cap = cost::learned_cap_within(
        &summary,
        config,
        learned.max_transitions,
        limits.max_session_bytes,
        limits.max_tick_us,
    );
    if cap == learned.max_transitions {
        return summary;
    }
    let mut own = (*summary).clone();
    if let Some(l) = &mut own.learned {
        l.max_transitions = cap;
    }
    Arc::new(own)
}
