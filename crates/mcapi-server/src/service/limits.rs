//! Size limits of the server: every request beyond one is refused with a
//! clear error before any large allocation. Every count, length and index a
//! client sends is checked here, against a field of [`Limits`] that a flag
//! of `mcapi serve` can raise (docs/limits.md).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use mcapi_core::spec::ModelSpec;
use mcapi_core::{BasisSpec, EnvModel};

use super::agent_config::SessionConfig;
use super::error::ServiceError;
use super::wire::SessionCost;

/// Caps on what clients may ask of the server.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Limits {
    /// Sessions held at once.
    pub max_sessions: usize,
    /// States × actions of one model.
    pub max_pairs: usize,
    /// Stored transitions of one model.
    pub max_transitions: usize,
    /// Features of a basis (k·|A|).
    pub max_features: usize,
    /// States of a model using proto-value functions: a dense
    /// eigendecomposition (O(|S|³)) up to
    /// [`mcapi_core::basis::DENSE_PVF_MAX_STATES`] states, the sparse
    /// partial eigensolver above (docs/algorithm.md §5).
    pub max_pvf_states: usize,
    /// Stimulus dimensions.
    pub max_stimuli: usize,
    /// Request body size in bytes.
    pub max_body_bytes: usize,
    /// Observations in one batch.
    pub max_batch: usize,
    /// Members of one session group (docs/groups.md).
    pub max_group_members: usize,
    /// History entries per session.
    pub max_history: usize,
    /// Buffered messages per gRPC stream.
    pub stream_buffer: usize,
    /// Jobs waiting for the tick loop.
    pub queue: usize,
    /// Bytes of one name (action, stimulus, state, preset, grid mark).
    pub max_name_bytes: usize,
    /// Curiosity `tau` and `lag`: the error window and lag history of every
    /// module are this long.
    pub max_curiosity_window: usize,
    /// Curiosity `max_centres` (ROC centres per module and tracker).
    pub max_roc_centres: usize,
    /// Curiosity `max_sources` (each frozen module tracks every source).
    pub max_signal_sources: usize,
    /// Estimated memory of one session ([`SessionCost::bytes`]).
    pub max_session_bytes: u64,
    /// Estimated CPU time of one observation ([`SessionCost::tick_us`]).
    pub max_tick_us: u64,
    /// Estimated CPU time of one batch of observations, in milliseconds.
    pub max_batch_ms: u64,
    /// Time one basis build may take, in milliseconds: estimated before it
    /// starts ([`super::cost::basis_build_ms`]) and enforced while it runs.
    pub max_build_ms: u64,
    /// Sessions one API key (or, without keys, all clients) may hold.
    pub max_key_sessions: usize,
    /// Estimated memory of all sessions of one API key (or, without keys,
    /// of all sessions).
    pub max_key_bytes: u64,
    /// Bytes of one response of value tables (`/values`), estimated before
    /// the tables are built.
    pub max_response_bytes: usize,
    /// Bytes of all value and history responses in flight together, by
    /// the same estimate (`service::budget`); at least
    /// `max_response_bytes`.
    pub max_response_bytes_total: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_sessions: 1_000_000,
            max_pairs: 1_000_000,
            max_transitions: 2_000_000,
            max_features: 1024,
            max_pvf_states: 10_000,
            max_stimuli: 64,
            max_body_bytes: 16 << 20,
            max_batch: 10_000,
            max_group_members: 10_000,
            max_history: 100_000,
            stream_buffer: 64,
            queue: 1 << 20,
            max_name_bytes: 128,
            max_curiosity_window: 10_000,
            max_roc_centres: 64,
            max_signal_sources: 1024,
            max_session_bytes: 256 << 20,
            max_tick_us: 250_000,
            max_batch_ms: 30_000,
            max_build_ms: 30_000,
            max_key_sessions: 1_000_000,
            max_key_bytes: 8 << 30,
            max_response_bytes: 64 << 20,
            max_response_bytes_total: 256 << 20,
        }
    }
}

impl Limits {
    /// No limit at all (recovering sessions created under looser limits).
    pub fn unlimited() -> Self {
        Self {
            max_sessions: usize::MAX,
            max_pairs: usize::MAX,
            max_transitions: usize::MAX,
            max_features: usize::MAX,
            max_pvf_states: usize::MAX,
            max_stimuli: usize::MAX,
            max_body_bytes: usize::MAX,
            max_batch: usize::MAX,
            max_group_members: usize::MAX,
            max_history: usize::MAX,
            stream_buffer: usize::MAX,
            queue: usize::MAX,
            max_name_bytes: usize::MAX,
            max_curiosity_window: usize::MAX,
            max_roc_centres: usize::MAX,
            max_signal_sources: usize::MAX,
            max_session_bytes: u64::MAX,
            max_tick_us: u64::MAX,
            max_batch_ms: u64::MAX,
            max_build_ms: u64::MAX,
            max_key_sessions: usize::MAX,
            max_key_bytes: u64::MAX,
            max_response_bytes: usize::MAX,
            max_response_bytes_total: usize::MAX,
        }
    }
}

/// Bytes the PVF eigensolver allocates while it builds a basis of `k`
/// functions on `states` states: the dense Laplacian and its eigenvectors
/// up to [`mcapi_core::basis::DENSE_PVF_MAX_STATES`], else four blocks of
/// b × |S| (the sparse solver, docs/algorithm.md §5).
pub fn pvf_solver_bytes(states: usize, k: usize) -> u64 {
    let n = states as u64;
    if states <= mcapi_core::basis::DENSE_PVF_MAX_STATES {
        3u64.saturating_mul(n).saturating_mul(n).saturating_mul(8)
    } else {
        let b = mcapi_core::basis::sparse_pvf_block(k, states) as u64;
        4u64.saturating_mul(b).saturating_mul(n).saturating_mul(8)
    }
}

fn exceeded(
    what: &str,
    got: impl std::fmt::Display,
    limit: impl std::fmt::Display,
) -> ServiceError {
    ServiceError::LimitExceeded(format!("{what} is {got}; the limit is {limit}"))
}

/// What one API key (or, without keys, every client) holds now.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Usage {
    /// Sessions.
    pub sessions: usize,
    /// Bytes charged for those sessions: each resident one its estimated
    /// cost, each evicted one what its stub holds.
    pub bytes: u64,
}

impl Limits {
    /// Checks names against [`Limits::max_name_bytes`] before they are used.
    pub fn check_names<'a>(
        &self,
        field: &str,
        names: impl IntoIterator<Item = &'a String>,
    ) -> Result<(), ServiceError> {
        for (i, name) in names.into_iter().enumerate() {
            if name.len() > self.max_name_bytes {
                return Err(exceeded(
                    &format!("`{field}[{i}]` length in bytes"),
                    name.len(),
                    self.max_name_bytes,
                ));
            }
        }
        Ok(())
    }

    /// Checks one name (a preset, an unknown action's name).
    pub fn check_name(&self, field: &str, name: &str) -> Result<(), ServiceError> {
        if name.len() > self.max_name_bytes {
            return Err(exceeded(
                &format!("`{field}` length in bytes"),
                name.len(),
                self.max_name_bytes,
            ));
        }
        Ok(())
    }

    /// Checks a grid map and its sources before the map is parsed: the
    /// bounding box (rows × widest row) and every source's dimension index.
    pub fn check_grid(
        &self,
        lines: &[String],
        sources: &BTreeMap<String, usize>,
        stimuli: Option<&[String]>,
    ) -> Result<(), ServiceError> {
        let widest = lines.iter().map(String::len).max().unwrap_or(0);
        let cells = lines.len().saturating_mul(widest);
        if cells > self.max_pairs {
            return Err(exceeded(
                "`model.grid` rows x widest row (cells)",
                cells,
                self.max_pairs,
            ));
        }
        if sources.len() > self.max_stimuli {
            return Err(exceeded(
                "`model.sources` entries",
                sources.len(),
                self.max_stimuli,
            ));
        }
        for (mark, &dim) in sources {
            self.check_name("model.sources key", mark)?;
            if dim >= self.max_stimuli {
                return Err(ServiceError::LimitExceeded(format!(
                    "`model.sources.{mark}` is dimension {dim}; dimensions are 0..{} (the limit on stimulus dimensions is {})",
                    self.max_stimuli, self.max_stimuli
                )));
            }
        }
        if let Some(names) = stimuli {
            if names.len() > self.max_stimuli {
                return Err(exceeded(
                    "`model.stimuli` length",
                    names.len(),
                    self.max_stimuli,
                ));
            }
            self.check_names("model.stimuli", names)?;
        }
        Ok(())
    }

    /// Checks a grid map's free cells (its states: every cell but `#`)
    /// against [`Limits::max_pvf_states`] when it asks for proto-value
    /// functions, before the map is parsed or its model built.
    pub fn check_grid_basis(
        &self,
        lines: &[String],
        basis: Option<&BasisSpec>,
    ) -> Result<(), ServiceError> {
        if !matches!(basis, Some(BasisSpec::ProtoValue { .. })) {
            return Ok(());
        }
        let free: usize = lines
            .iter()
            .map(|l| l.chars().filter(|&c| c != '#').count())
            .sum();
        if free > self.max_pvf_states {
            return Err(exceeded(
                "`model.grid` free cells (states) for a proto_value basis",
                free,
                self.max_pvf_states,
            ));
        }
        Ok(())
    }

    /// Checks the agent configuration's sizes: the history ring and the
    /// curiosity channel's windows, centres and sources.
    pub fn check_config(&self, agent: &SessionConfig) -> Result<(), ServiceError> {
        if let Some(history) = agent.history
            && history > self.max_history
        {
            return Err(exceeded("`agent.history`", history, self.max_history));
        }
        if let Some(p) = &agent.priorities
            && p.len() > self.max_stimuli
        {
            return Err(exceeded(
                "`agent.priorities` length",
                p.len(),
                self.max_stimuli,
            ));
        }
        let Some(c) = &agent.curiosity else {
            return Ok(());
        };
        let p = &c.params;
        for (field, value) in [
            ("agent.curiosity.params.tau", p.tau),
            ("agent.curiosity.params.lag", p.lag),
        ] {
            if value > self.max_curiosity_window {
                return Err(exceeded(
                    &format!("`{field}`"),
                    value,
                    self.max_curiosity_window,
                ));
            }
        }
        if p.max_centres > self.max_roc_centres {
            return Err(exceeded(
                "`agent.curiosity.params.max_centres`",
                p.max_centres,
                self.max_roc_centres,
            ));
        }
        if p.max_sources > self.max_signal_sources {
            return Err(exceeded(
                "`agent.curiosity.params.max_sources`",
                p.max_sources,
                self.max_signal_sources,
            ));
        }
        Ok(())
    }

    /// Checks a session's estimated cost against the per-session budget and
    /// what its key already holds against the key's quota.
    pub fn check_cost(&self, cost: &SessionCost, held: Usage) -> Result<(), ServiceError> {
        if cost.bytes > self.max_session_bytes {
            return Err(ServiceError::LimitExceeded(format!(
                "the session's estimated memory is {} bytes; the limit per session is {} (--max-session-bytes); use a smaller model, basis, history or curiosity channel",
                cost.bytes, self.max_session_bytes
            )));
        }
        if cost.tick_us > self.max_tick_us {
            return Err(ServiceError::LimitExceeded(format!(
                "one observation's estimated CPU time is {} µs; the limit is {} µs (--max-tick-us); use a smaller model, basis, `gamma` or `agent.curiosity.signal_dim`",
                cost.tick_us, self.max_tick_us
            )));
        }
        if held.sessions >= self.max_key_sessions {
            return Err(ServiceError::QuotaExceeded(format!(
                "this API key already holds {} sessions; its quota is {} (--max-key-sessions)",
                held.sessions, self.max_key_sessions
            )));
        }
        let total = held.bytes.saturating_add(cost.bytes);
        if total > self.max_key_bytes {
            return Err(ServiceError::QuotaExceeded(format!(
                "this API key's sessions would hold an estimated {total} bytes ({} now, {} for the new one); its quota is {} (--max-key-bytes)",
                held.bytes, cost.bytes, self.max_key_bytes
            )));
        }
        Ok(())
    }

    /// Checks a batch's estimated CPU time (its length times one
    /// observation's) against [`Limits::max_batch_ms`].
    pub fn check_batch_cost(&self, len: usize, cost: &SessionCost) -> Result<(), ServiceError> {
        let us = (len as u64).saturating_mul(cost.tick_us);
        if us / 1000 > self.max_batch_ms {
            let fits = (self.max_batch_ms.saturating_mul(1000) / cost.tick_us.max(1)).max(1);
            return Err(ServiceError::LimitExceeded(format!(
                "`observations` has {len} entries at an estimated {} µs each ({} ms in all); the limit per batch is {} ms (--max-batch-ms): send at most {fits} per batch",
                cost.tick_us,
                us / 1000,
                self.max_batch_ms
            )));
        }
        Ok(())
    }
}

impl Limits {
    /// Checks a posted model before it is built.
    pub fn check_model_spec(&self, spec: &ModelSpec) -> Result<(), ServiceError> {
        if spec.actions.len() > self.max_pairs {
            return Err(exceeded(
                "`model.actions` length",
                spec.actions.len(),
                self.max_pairs,
            ));
        }
        self.check_structure(
            spec.states,
            &spec.actions,
            &spec.stimuli,
            spec.state_names.as_deref(),
        )?;
        if let Some(t) = &spec.transitions {
            let n: usize = t.iter().map(|t| t.next.len()).sum();
            if n > self.max_transitions {
                return Err(exceeded(
                    "`model.transitions` count",
                    n,
                    self.max_transitions,
                ));
            }
        }
        if spec.stimuli.len() > self.max_stimuli {
            return Err(exceeded(
                "`model.stimuli` length",
                spec.stimuli.len(),
                self.max_stimuli,
            ));
        }
        Ok(())
    }

    /// The names of a posted model's actions, stimuli and states, and its
    /// states × actions: what a full model and a learned one share.
    fn check_structure(
        &self,
        states: usize,
        actions: &[String],
        stimuli: &[String],
        state_names: Option<&[String]>,
    ) -> Result<(), ServiceError> {
        self.check_names("model.actions", actions)?;
        self.check_names("model.stimuli", stimuli)?;
        if let Some(names) = state_names {
            self.check_names("model.state_names", names)?;
        }
        let pairs = states.saturating_mul(actions.len());
        if pairs > self.max_pairs {
            return Err(exceeded("`model` states x actions", pairs, self.max_pairs));
        }
        Ok(())
    }

    /// Checks a full model whose transitions the agent learns before its
    /// structure is built: names, states × actions (and states alone, so
    /// that no action list makes the state count free), stimuli.
    pub fn check_learned_spec(
        &self,
        states: usize,
        actions: &[String],
        stimuli: &[String],
        state_names: Option<&[String]>,
    ) -> Result<(), ServiceError> {
        if actions.is_empty() {
            return Err(ServiceError::field(
                "model.actions",
                "must name at least one action",
            ));
        }
        if actions.len() > self.max_pairs {
            return Err(exceeded(
                "`model.actions` length",
                actions.len(),
                self.max_pairs,
            ));
        }
        if states > self.max_pairs {
            return Err(exceeded("`model.states`", states, self.max_pairs));
        }
        self.check_structure(states, actions, stimuli, state_names)?;
        if stimuli.len() > self.max_stimuli {
            return Err(exceeded(
                "`model.stimuli` length",
                stimuli.len(),
                self.max_stimuli,
            ));
        }
        Ok(())
    }

    /// The most (pair, successor) entries a learned model of `model` may
    /// store (docs/algorithm.md §8): every successor of every pair, at most
    /// [`Limits::max_transitions`], the cap a posted model's table has too.
    /// The session's cost is estimated at this many entries, and an
    /// observation that would store one more is refused
    /// (`SessionState::apply`).
    pub fn learned_transitions(&self, model: &EnvModel) -> usize {
        model
            .n_pairs()
            .saturating_mul(model.states())
            .min(self.max_transitions)
    }

    /// Checks a built model.
    pub fn check_model(&self, model: &EnvModel) -> Result<(), ServiceError> {
        self.check_names("model.actions", model.actions())?;
        self.check_names("model.stimuli", model.stimuli())?;
        let pairs = model.states() * model.n_actions();
        if pairs > self.max_pairs {
            return Err(exceeded("`model` states x actions", pairs, self.max_pairs));
        }
        if model.n_transitions() > self.max_transitions {
            return Err(exceeded(
                "`model` transitions",
                model.n_transitions(),
                self.max_transitions,
            ));
        }
        if model.n_stimuli() > self.max_stimuli {
            return Err(exceeded(
                "`model.stimuli` length",
                model.n_stimuli(),
                self.max_stimuli,
            ));
        }
        Ok(())
    }

    /// Checks a basis choice for a model before it is built.
    pub fn check_basis(&self, model: &EnvModel, basis: &BasisSpec) -> Result<(), ServiceError> {
        let k = match basis {
            BasisSpec::Indicator => return Ok(()),
            BasisSpec::ProtoValue { k } => {
                if model.states() > self.max_pvf_states {
                    return Err(exceeded(
                        "`model` states for a proto_value basis",
                        model.states(),
                        self.max_pvf_states,
                    ));
                }
                *k
            }
            BasisSpec::Custom { state_features } => state_features.first().map_or(0, Vec::len),
        };
        let features = k.saturating_mul(model.n_actions());
        if features > self.max_features {
            return Err(exceeded(
                "`model.basis` features (k x actions)",
                features,
                self.max_features,
            ));
        }
        if let BasisSpec::ProtoValue { k } = basis {
            // Before the eigensolver allocates: its working memory counts
            // against the per-session budget.
            let bytes = pvf_solver_bytes(model.states(), *k);
            if bytes > self.max_session_bytes {
                return Err(ServiceError::LimitExceeded(format!(
                    "the proto_value basis's eigensolver needs an estimated {bytes} bytes for {} states and k = {k}; the limit per session is {} (--max-session-bytes); use a smaller `k` or model",
                    model.states(),
                    self.max_session_bytes
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pvf_basis_is_refused_when_its_eigensolver_would_not_fit_the_session_budget() {
        let chain = EnvModel::chain(5000, vec!["x".into()]).expect("chain");
        let basis = BasisSpec::ProtoValue { k: 1000 };
        // Four blocks of 1,500 × 5,000 numbers: 240 MB.
        assert_eq!(pvf_solver_bytes(5000, 1000), 4 * 1500 * 5000 * 8);
        let limits = Limits {
            max_session_bytes: 64 << 20,
            max_features: usize::MAX,
            ..Limits::default()
        };
        let e = limits.check_basis(&chain, &basis).expect_err("too big");
        assert!(
            e.to_string().contains(
                "eigensolver needs an estimated 240000000 bytes for 5000 states and k = 1000"
            ),
            "{e}"
        );
        limits
            .check_basis(&chain, &BasisSpec::ProtoValue { k: 30 })
            .expect("30 PVFs fit");
        // Up to the dense threshold the dense solver's n × n matrices count.
        assert_eq!(pvf_solver_bytes(800, 30), 3 * 800 * 800 * 8);
    }

    #[test]
    fn a_pvf_grid_is_refused_by_its_free_cells_before_it_is_parsed() {
        let limits = Limits {
            max_pvf_states: 5,
            ..Limits::default()
        };
        let pvf = BasisSpec::ProtoValue { k: 2 };
        let lines = vec!["#..#".to_string(), "#..#".to_string()];
        limits
            .check_grid_basis(&lines, Some(&pvf))
            .expect("4 cells");
        let lines = vec!["a..#".to_string(), "#..b".to_string()];
        let e = limits
            .check_grid_basis(&lines, Some(&pvf))
            .expect_err("6 cells");
        assert!(e.to_string().contains("is 6; the limit is 5"), "{e}");
        limits
            .check_grid_basis(&lines, Some(&BasisSpec::Indicator))
            .expect("only proto_value is checked");
    }
}
