//! Setting a session up: its model parsed and checked against the limits,
//! the planning model (shared by every session of the same model, built
//! once, a few at a time), its agent configuration checked, its learner
//! built. Creation and recovery both build here.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};
use std::time::{SystemTime, UNIX_EPOCH};

use parking_lot::Mutex;

use mcapi_core::continuous::{ContinuousAgent, ContinuousBasisSpec, ContinuousModel};
use mcapi_core::{Agent, AlgoError, Basis, BasisSpec, BuildBudget, CuriousAgent, PlanningModel};

use super::agent_config::{EffectiveConfig, SessionConfig};
use super::cost;
use super::error::ServiceError;
use super::learner::Learner;
use super::limits::Limits;
use super::spec::ModelInput;
use super::wire::{BasisSummary, GridLayout, LearnedSummary, ModelSummary, SessionCost};

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

/// What the build of a new session checks before it spends anything, and
/// when it gives up. Creation builds with one; recovery without (a session
/// accepted once is rebuilt whatever it costs).
pub(super) struct NewBuild<'a> {
    /// The session's estimated cost against the caller's quota, checked
    /// before the basis is built.
    pub admit: &'a dyn Fn(&SessionCost) -> Result<(), ServiceError>,
    /// Set when the request that asked for the session is abandoned (its
    /// client went away, or its time ran out): the build stops.
    pub abandoned: Option<&'a AtomicBool>,
}

/// The summary of a model as built: the basis chosen and the grid layout.
fn summary_of(
    ctx: &PlanningModel,
    basis: BasisSummary,
    layout: Option<GridLayout>,
    learned: Option<LearnedSummary>,
) -> ModelSummary {
    summary_with(ctx.model(), ctx.n_features(), basis, layout, learned)
}

/// [`summary_of`] from the model and its feature count: what a session
/// will be, before its basis is built.
fn summary_with(
    model: &mcapi_core::EnvModel,
    features: usize,
    basis: BasisSummary,
    layout: Option<GridLayout>,
    learned: Option<LearnedSummary>,
) -> ModelSummary {
    ModelSummary {
        states: model.states(),
        actions: model.actions().to_vec(),
        stimuli: model.stimuli().to_vec(),
        pairs: model.n_pairs(),
        transitions: model.n_transitions(),
        deterministic: model.is_deterministic(),
        basis,
        features,
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
        // The indicator basis of the cells, which the grid plans on exactly.
        Some(ContinuousBasisSpec::Grid { .. }) => (
            "grid",
            match &model.features {
                mcapi_core::continuous::FeatureMap::Grid(shape) => shape.cells(),
                _ => 0,
            },
        ),
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
    /// Basis builds stopped before they finished (their request abandoned,
    /// or past `--max-build-ms`).
    stopped: AtomicU64,
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
            stopped: AtomicU64::new(0),
        }
    }

    /// Basis builds stopped before they finished, since the start.
    pub(super) fn builds_stopped(&self) -> u64 {
        self.stopped.load(Ordering::Relaxed)
    }

    pub(super) fn fresh_u64(&self) -> u64 {
        splitmix(
            self.seed_counter
                .fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed),
        )
    }

    /// The shared planning model for `input`, built once per distinct model,
    /// with what a session's model summary takes from its build. Before a
    /// basis is built, `before` sees what the session will be (so that every
    /// check that costs nothing runs first); with `new`, a build estimated
    /// over `--max-build-ms` is refused, and one that runs past it or whose
    /// request is abandoned is stopped.
    fn planning_model(
        &self,
        input: &ModelInput,
        curious: bool,
        limits: &Limits,
        before: &dyn Fn(&ModelSummary) -> Result<(), ServiceError>,
        new: Option<&NewBuild<'_>>,
    ) -> Result<(Arc<PlanningModel>, Built), ServiceError> {
        let key = format!("{}:curious={curious}", input.cache_key());
        // Not held while `before` runs: it may make room for the session
        // by evicting others, which waits for the store.
        let cached = self
            .models
            .lock()
            .get(&key)
            .and_then(|(weak, built)| Some((weak.upgrade()?, Arc::clone(built))));
        if let Some((ctx, built)) = cached {
            before(&built)?;
            return Ok((ctx, built));
        }
        let (model, basis_spec) = input.build(limits, curious)?;
        // A client's features are checked entry by entry before anything
        // waits for a build's place (their conditioning, an SVD, is
        // checked with the build).
        if let BasisSpec::Custom { state_features } = &basis_spec {
            mcapi_core::basis::check_custom_rows(&model, state_features)?;
        }
        let learned = |model: &mcapi_core::EnvModel| {
            input.learning().map(|l| LearnedSummary {
                known_after: l.known_after,
                optimism: l.optimism,
                max_transitions: limits.learned_transitions(model),
            })
        };
        let features = match &basis_spec {
            BasisSpec::Indicator => model.n_pairs(),
            BasisSpec::ProtoValue { k } => k.saturating_mul(model.n_actions()),
            BasisSpec::Custom { state_features } => state_features
                .first()
                .map_or(0, Vec::len)
                .saturating_mul(model.n_actions()),
        };
        before(&summary_with(
            &model,
            features,
            BasisSummary::of(&basis_spec),
            input.layout(),
            learned(&model),
        ))?;
        let kind = BasisSummary::of(&basis_spec).kind;
        let way_out = "ask for fewer proto-value functions (`k`) or `{\"kind\": \"indicator\"}`";
        let budget_ms = limits.max_build_ms;
        if new.is_some() {
            let estimate = cost::basis_build_ms(&basis_spec, &model);
            if estimate > budget_ms {
                return Err(ServiceError::LimitExceeded(format!(
                    "the {kind} basis of this model ({} states) would take at least {estimate} ms to build; the limit is {budget_ms} ms (--max-build-ms); {way_out}",
                    model.states()
                )));
            }
        }
        // Built outside the lock (PVFs cost an eigendecomposition), a few at
        // a time; a new session's build within its time budget, counted
        // from when it gets its slot.
        let _slot = self.builds.acquire()?;
        let budget = match new {
            Some(new) => BuildBudget {
                deadline: Instant::now().checked_add(Duration::from_millis(budget_ms)),
                cancelled: new.abandoned,
            },
            None => BuildBudget::UNLIMITED,
        };
        let basis = Basis::build_checked_within(&basis_spec, &model, budget).map_err(|e| match e {
            // A basis the solver could not compute (the sparse PVF solver
            // gives up on some graphs) is no fault of the server's: say
            // which basis, and what to ask for instead.
            AlgoError::Numerical(detail) => ServiceError::field(
                "model.basis",
                format!(
                    "the {kind} basis of this model could not be computed ({detail}); ask for                      `{{\"kind\": \"indicator\"}}` or fewer proto-value functions (`k`)"
                ),
            ),
            AlgoError::BuildStopped(why) => {
                self.stopped.fetch_add(1, Ordering::Relaxed);
                let abandoned = budget.cancelled.is_some_and(|c| c.load(Ordering::Relaxed));
                let reason = if abandoned { "abandoned" } else { "deadline" };
                metrics::counter!("mcapi_builds_stopped_total", "reason" => reason).increment(1);
                ServiceError::LimitExceeded(format!(
                    "the {kind} basis of this model was not built: {why} (--max-build-ms is {budget_ms} ms); {way_out}"
                ))
            }
            other => other.into(),
        })?;
        let ctx = Arc::new(PlanningModel::new(model, basis));
        let learned = learned(ctx.model());
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

    /// Builds the agent of a session: the base of a recovery, or a group's
    /// later members (their model is built by then).
    pub(super) fn build(
        &self,
        input: &ModelInput,
        agent: &SessionConfig,
        limits: &Limits,
    ) -> Result<(Learner, Arc<ModelSummary>, EffectiveConfig), ServiceError> {
        self.build_as(input, agent, limits, None)
    }

    /// Builds the agent of a new session: as [`Self::build`], with the
    /// session's cost admitted before its basis is built, and that build
    /// priced, timed and stopped as `new` and `--max-build-ms` say.
    pub(super) fn build_new(
        &self,
        input: &ModelInput,
        agent: &SessionConfig,
        limits: &Limits,
        new: &NewBuild<'_>,
    ) -> Result<(Learner, Arc<ModelSummary>, EffectiveConfig), ServiceError> {
        self.build_as(input, agent, limits, Some(new))
    }

    fn build_as(
        &self,
        input: &ModelInput,
        agent: &SessionConfig,
        limits: &Limits,
        new: Option<&NewBuild<'_>>,
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
        if let Some(c) = &agent.curiosity {
            // Checked before the channel is priced (its cost grows with
            // the signal's dimension to the fourth power).
            c.params
                .check()
                .map_err(|e| ServiceError::algo_at("agent.curiosity.params", e))?;
            mcapi_core::curiosity::CuriosityChannel::check_signal_dim(c.signal_dim)
                .map_err(|e| ServiceError::algo_at("agent.curiosity", e))?;
        }
        let seed = self.fresh_u64();
        // The agent's parameters and the session's cost, checked against
        // what the session will be before anything is built.
        let before = |summary: &ModelSummary| -> Result<(), ServiceError> {
            let params = agent.params().check(summary.stimuli.len(), seed)?;
            if let Some(new) = new {
                let config = agent.effective(&params);
                let summary = within_budget(Arc::new(summary.clone()), &config, limits);
                (new.admit)(&cost::estimate(&summary, &config))?;
            }
            Ok(())
        };
        let curious = agent.curiosity.is_some();
        let (ctx, summary) = self.planning_model(input, curious, limits, &before, new)?;
        let params = agent.params().check(ctx.model().n_stimuli(), seed)?;
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
