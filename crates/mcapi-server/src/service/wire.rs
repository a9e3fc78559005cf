//! The service's wire types: what a session call takes and answers, the same
//! for REST (serde JSON, with the OpenAPI derives of the document) and gRPC
//! (converted in one place, `crate::api::grpc::convert`). Their shapes are
//! the API: a change here is a change of the wire format.

use serde::{Deserialize, Serialize};
use serde_json::Value;

use mcapi_core::continuous::ContinuousSpec;
use mcapi_core::model::GridMap;
use mcapi_core::spec::ActionRef;
use mcapi_core::{BasisSpec, CuriousAgent};

use super::agent_config::{EffectiveConfig, SessionConfig, UpdateMode};

/// A request to create a session.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateSession {
    /// An environment model, `{"preset": "hallway" | "three_room"}`, or
    /// `{"grid": [...], "sources": {"a": 0, ...}}`.
    #[schema(value_type = Object)]
    pub model: Value,
    /// Agent configuration.
    #[serde(default)]
    pub agent: SessionConfig,
}

/// The basis of a session: its kind and, for feature bases, k per action.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct BasisSummary {
    /// `indicator`, `proto_value` or `custom`.
    pub kind: String,
    /// State features per action block (0 for `indicator`).
    pub k: usize,
}

impl BasisSummary {
    /// Summarises a basis choice.
    pub fn of(spec: &BasisSpec) -> Self {
        let (kind, k) = match spec {
            BasisSpec::Indicator => ("indicator", 0),
            BasisSpec::ProtoValue { k } => ("proto_value", *k),
            BasisSpec::Custom { state_features } => {
                ("custom", state_features.first().map_or(0, Vec::len))
            }
        };
        Self {
            kind: kind.into(),
            k,
        }
    }
}

/// What a session's model looks like, returned at creation and by `get`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ModelSummary {
    /// Number of states.
    pub states: usize,
    /// Action names.
    pub actions: Vec<String>,
    /// Stimulus names.
    pub stimuli: Vec<String>,
    /// Valid state-action pairs.
    pub pairs: usize,
    /// Stored transitions.
    pub transitions: usize,
    /// Whether every pair has one successor.
    pub deterministic: bool,
    /// The basis in use.
    pub basis: BasisSummary,
    /// Number of features.
    pub features: usize,
    /// Where each state lies on the map, for grid models (grid form and the
    /// `three_room` preset); absent for other models.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<GridLayout>,
    /// For a model whose transitions the agent learns (`"transitions":
    /// "learn"` or a grid's `"learn": true`, docs/algorithm.md §8): m, the
    /// optimism rule and the cap on stored transitions; absent when the
    /// transitions were posted. `transitions` and `deterministic` then
    /// describe the structure only (each pair's placeholder successor),
    /// not what the agent learned.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learned: Option<LearnedSummary>,
    /// For a continuous model (docs/sessions.md, "Continuous worlds"): the
    /// model as built, its effective basis and sample store filled in;
    /// `states`, `pairs` and `transitions` are then 0 and `features` is
    /// k × |A|.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub continuous: Option<ContinuousSpec>,
}

/// How a session learns its transition model (docs/algorithm.md §8).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct LearnedSummary {
    /// m: a pair's row of P̂ is used once the pair was seen this many times;
    /// before that it is optimistic.
    pub known_after: u32,
    /// How unknown pairs are optimistic: `absorbing` (R-max: an extra state
    /// worth the largest reward forever) or `stimulus` (unknown pairs stay
    /// put; Ξ's optimistic start is the only optimism).
    #[schema(value_type = String)]
    pub optimism: mcapi_core::Optimism,
    /// The most (pair, successor) entries the session stores: |pairs| ×
    /// |states|, at most the server's `--max-transitions`, and at most what
    /// keeps the session's estimated cost (priced at this many, stochastic)
    /// within `--max-session-bytes` and `--max-tick-us`. An observation that
    /// would store one more is refused (`limit_exceeded`).
    pub max_transitions: usize,
}

/// The map of a grid model: its size, the cell of each state and the marked
/// cells (the stimulus sources), for drawing values over the map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GridLayout {
    /// Map height in cells.
    pub rows: usize,
    /// Map width in cells.
    pub cols: usize,
    /// `[row, col]` of each state, indexed by state.
    pub cells: Vec<[usize; 2]>,
    /// Marked cells in row-major order: the mark and its state.
    pub marks: Vec<GridMark>,
}

/// A marked cell of a grid map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GridMark {
    /// The mark character.
    pub mark: String,
    /// The state of the marked cell.
    pub state: usize,
}

impl GridLayout {
    /// The layout of a parsed map.
    pub fn of(grid: &GridMap) -> Self {
        Self {
            rows: grid.rows(),
            cols: grid.cols(),
            cells: (0..grid.states())
                .map(|s| {
                    let (r, c) = grid.cell_of(s);
                    [r, c]
                })
                .collect(),
            marks: grid
                .marks()
                .iter()
                .map(|&(mark, state)| GridMark {
                    mark: mark.to_string(),
                    state,
                })
                .collect(),
        }
    }
}

/// One observation as a client sends it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ObservationIn {
    /// The state the agent is in now (a model with numbered states).
    #[serde(default)]
    pub state: Option<usize>,
    /// The observation vector (a continuous model): one finite number per
    /// dimension of its space.
    #[serde(default)]
    pub observation: Option<Vec<f64>>,
    /// The stimulus received on arrival; omitted on the first observation.
    #[serde(default)]
    pub stimulus: Option<Vec<f64>>,
    /// The action actually taken, by name or index, if not the advised one.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    pub action_taken: Option<ActionRef>,
    /// A raw signal sample x(t) received on arrival, for a session with a
    /// curiosity channel (docs/algorithm.md §7); `stimulus` is then the
    /// extrinsic part and the server appends ξ_cur.
    #[serde(default)]
    pub signal: Option<Vec<f64>>,
    /// The signal's source (e.g. 0 = book, 1 = music); default 0.
    #[serde(default)]
    pub signal_source: Option<usize>,
    /// The observation's 0-based index in the session's stream of applied
    /// observations (the first has seq 0), for exactly-once delivery
    /// (docs/sessions.md, "Delivery guarantees"): an observation resent
    /// with a seq already applied is answered with its recorded reply and
    /// not applied again. Absent: applied as it comes (at least once).
    #[serde(default, deserialize_with = "seq_field::deserialize")]
    pub seq: Option<u64>,
}

/// Reads `seq` with a message that says what it must be: serde's own
/// ("invalid value: integer `-1`, expected u64") names neither the field
/// nor the range.
mod seq_field {
    use std::fmt;

    use serde::Deserializer;
    use serde::de::{self, Visitor};

    pub(super) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
        d.deserialize_option(Seq)
    }

    struct Seq;

    fn refused<E: de::Error>(what: impl fmt::Display) -> E {
        E::custom(format_args!(
            "`seq` must be an integer from 0 to {} (the observation's index in the \
             session's stream), not {what}",
            u64::MAX
        ))
    }

    impl<'de> Visitor<'de> for Seq {
        type Value = Option<u64>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("`seq`, an integer from 0 to 2^64 - 1")
        }

        fn visit_none<E: de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }

        fn visit_unit<E: de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }

        fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
            d.deserialize_any(self)
        }

        fn visit_u64<E: de::Error>(self, v: u64) -> Result<Self::Value, E> {
            Ok(Some(v))
        }

        fn visit_i64<E: de::Error>(self, v: i64) -> Result<Self::Value, E> {
            u64::try_from(v)
                .map(Some)
                .map_err(|_| refused(format_args!("the negative number {v}")))
        }

        fn visit_f64<E: de::Error>(self, v: f64) -> Result<Self::Value, E> {
            // 2^64, exact in f64. An integral float below it (`3.0`) is the
            // integer, as JSON Schema reads numbers everywhere in the API.
            const TWO_64: f64 = 18_446_744_073_709_551_616.0;
            if v < 0.0 {
                Err(refused(format_args!("the negative number {v}")))
            } else if v.fract() != 0.0 || !v.is_finite() {
                Err(refused(format_args!("the fractional number {v}")))
            } else if v >= TWO_64 {
                Err(refused(format_args!("{v}, beyond 2^64 - 1")))
            } else {
                Ok(Some(v as u64))
            }
        }

        fn visit_str<E: de::Error>(self, v: &str) -> Result<Self::Value, E> {
            let mut shown: String = v.chars().take(32).collect();
            if shown.len() < v.len() {
                shown.push_str("...");
            }
            Err(refused(format_args!("the string {shown:?}")))
        }

        fn visit_bool<E: de::Error>(self, v: bool) -> Result<Self::Value, E> {
            Err(refused(format_args!("the boolean {v}")))
        }

        fn visit_seq<A: de::SeqAccess<'de>>(self, _: A) -> Result<Self::Value, A::Error> {
            Err(refused("an array"))
        }

        fn visit_map<A: de::MapAccess<'de>>(self, _: A) -> Result<Self::Value, A::Error> {
            Err(refused("an object"))
        }
    }
}

/// The curiosity channel at one tick (docs/algorithm.md §7).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TickCuriosity {
    /// ξ_cur of the tick (Eq. 7; 0 without a signal sample).
    pub xi_cur: f64,
    /// The active module's estimation error ε after the tick.
    pub epsilon: f64,
    /// Frozen modules in the library after the tick.
    pub modules: usize,
    /// The source of the tick's signal sample, if there was one.
    pub source: Option<usize>,
}

/// The reply to one observation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StepOut {
    /// Ticks so far.
    pub tick: u64,
    /// Name of the next action.
    pub action: String,
    /// Index of the next action.
    pub action_index: usize,
    /// The drive D after this tick.
    pub drive: Vec<f64>,
    /// |r| of this tick (Eq. 3).
    pub reward: f64,
    /// Number of policy updates applied.
    pub policy_version: u64,
    /// The curiosity channel at this tick, for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<TickCuriosity>,
    /// `true` when the observation carried a `seq` already applied: this
    /// is the reply it got then, bit for bit, and nothing was applied now
    /// (docs/sessions.md, "Delivery guarantees"). Absent otherwise, so a
    /// replayed body differs from the first one by this field alone.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub replayed: bool,
}

/// One tick of the history ring.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct HistoryEntry {
    /// Tick.
    pub tick: u64,
    /// State after the tick.
    pub state: usize,
    /// Action advised for that state.
    pub action: usize,
    /// Drive after the tick.
    pub drive: Vec<f64>,
    /// |r|.
    pub reward: f64,
    /// LSTDQ error of the newest policy update.
    pub lstdq_error: f64,
    /// The full stimulus received at this tick (ξ_cur last for a curious
    /// session); absent only for ticks restored from a snapshot written
    /// before store format 3.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stimulus: Option<Vec<f64>>,
    /// The curiosity channel at this tick, for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<TickCuriosity>,
    /// For a session that learns its transitions (docs/algorithm.md §8):
    /// the fraction of valid pairs seen at least m times after this tick;
    /// absent for a session with posted transitions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub known_fraction: Option<f64>,
    /// For a continuous session: the observation of this tick (`state` is
    /// then 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation: Option<Vec<f64>>,
}

/// A session as `get` returns it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionInfo {
    /// `s<shard>.<ULID>`.
    pub id: String,
    /// Ticks so far.
    pub tick: u64,
    /// The drive D.
    pub drive: Vec<f64>,
    /// Policy updates applied.
    pub policy_version: u64,
    /// The `seq` the session's next observation takes: how many it has
    /// applied (`tick + 1` once it has observed). A client resuming
    /// exactly-once delivery after a crash sends from here
    /// (docs/sessions.md, "Delivery guarantees").
    pub next_seq: u64,
    /// The agent's current state, once it has observed one.
    pub state: Option<usize>,
    /// The model.
    pub model: ModelSummary,
    /// Effective configuration.
    pub agent: EffectiveConfig,
    /// Statistics of the learner.
    pub stats: SessionStats,
    /// The session's estimated memory and per-observation CPU time, as
    /// checked against the server's budgets when it was created.
    pub cost: SessionCost,
    /// The curiosity channel, for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<CuriosityInfo>,
}

/// The state of a session's curiosity channel (docs/algorithm.md §7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CuriosityInfo {
    /// Signal samples received.
    pub samples: u64,
    /// The active module's estimation error ε.
    pub epsilon: f64,
    /// The source the active module learns, once bound.
    pub active_source: Option<usize>,
    /// Samples the active module learned from.
    pub active_samples: u64,
    /// Every known source is explained by a frozen module: condition (3)
    /// holds and D\[curiosity\] is held at 0.
    pub all_explained: bool,
    /// The module library, in freezing order.
    pub modules: Vec<FrozenModuleInfo>,
}

/// One frozen module of the library.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct FrozenModuleInfo {
    /// The source it learned.
    pub source: usize,
    /// The session's tick when it froze.
    pub frozen_tick: u64,
    /// Samples it learned from before freezing.
    pub learned_samples: u64,
}

impl CuriosityInfo {
    pub fn of(agent: &CuriousAgent) -> Self {
        let channel = agent.channel();
        let active = channel.active();
        Self {
            samples: channel.samples(),
            epsilon: channel.epsilon(),
            active_source: active.source(),
            active_samples: active.learned_samples(),
            all_explained: channel.all_explained(),
            modules: channel
                .library()
                .iter()
                .zip(agent.frozen_ticks())
                .map(|(m, &tick)| FrozenModuleInfo {
                    source: m.source(),
                    frozen_tick: tick,
                    learned_samples: m.learned_samples(),
                })
                .collect(),
        }
    }
}

/// Learner statistics of a session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionStats {
    /// ‖Q_t − Q_{t+1}‖ of the last policy update.
    pub lstdq_error: f64,
    /// Running estimate of λ₁ of E[Λξ ξᵀΛ] (condition (1)).
    pub lambda1_estimate: f64,
    /// Whether η λ₁ < 0.5 holds for the estimate.
    pub condition_1_holds: bool,
    /// Stimulus dimensions whose column of Ξ is constant (condition (3)).
    pub constant_stimuli: Vec<usize>,
    /// Policy updates that reused the factorisation.
    pub factorisation_reuses: u64,
    /// Full factorisations of A.
    pub factorisations: u64,
    /// For a continuous session: its sample store and clipping.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub continuous: Option<ContinuousStatsOut>,
}

/// The counters of a continuous session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ContinuousStatsOut {
    /// Observations outside the box, clipped into it.
    pub clipped: u64,
    /// Transitions in the sample store now (on a grid: the moves kept, each
    /// counted once for every (cell, action) it teaches).
    pub samples: usize,
    /// (cell, action) slots visited (on a grid: the pairs whose successor
    /// is known).
    pub slots: usize,
    /// Rank-one updates of the planner's inverse.
    pub updates: u64,
    /// Rebuilds of the planner's inverse.
    pub rebuilds: u64,
    /// Builds of a `pvf` basis (0 for the other bases).
    pub basis_builds: u64,
}

impl From<mcapi_core::continuous::ContinuousStats> for ContinuousStatsOut {
    fn from(s: mcapi_core::continuous::ContinuousStats) -> Self {
        Self {
            clipped: s.clipped,
            samples: s.samples,
            slots: s.slots,
            updates: s.updates,
            rebuilds: s.rebuilds,
            basis_builds: s.basis_builds,
        }
    }
}

/// One line of `list`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionSummary {
    /// Session id.
    pub id: String,
    /// Ticks so far.
    pub tick: u64,
    /// Number of states of its model.
    pub states: usize,
    /// Update mode.
    pub update_mode: UpdateMode,
    /// Milliseconds since its last applied observation; absent if it had
    /// none since the server started.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub idle_ms: Option<u64>,
}

/// A page of sessions, ordered by id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionPage {
    /// The sessions.
    pub sessions: Vec<SessionSummary>,
    /// Pass as `after` for the next page; absent on the last page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next: Option<String>,
}

/// Value tables of a session; per-pair tables are `[state][action]`, null
/// where the action is unavailable.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Values {
    /// Ticks so far.
    pub tick: u64,
    /// Policy updates applied.
    pub policy_version: u64,
    /// V(s) = Q(s, π(s)).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub v: Option<Vec<f64>>,
    /// Q(s, a).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub q: Option<Vec<Vec<Option<f64>>>>,
    /// Greedy action name per state.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub policy: Option<Vec<String>>,
    /// R(s, a) = |Ξ Λ D| as of the last update.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub r: Option<Vec<Vec<Option<f64>>>>,
    /// Ξ(s, a), one vector per pair.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub xi: Option<Vec<Vec<Option<Vec<f64>>>>>,
    /// The curiosity channel (ε, module library), for a session with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curiosity: Option<CuriosityInfo>,
    /// For a session that learns its transitions (docs/algorithm.md §8):
    /// the fraction of valid pairs seen at least m times, in [0, 1];
    /// absent for a session with posted transitions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub known_fraction: Option<f64>,
    /// For a continuous session: the observations the tables are indexed
    /// by (a grid over the box for d ≤ 2, else the observations of the
    /// history ring), `v[i]` and `q[i]` being at `points[i]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points: Option<Vec<Vec<f64>>>,
}

/// The estimated cost of one session.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionCost {
    /// Memory the session may hold at most: its learner, planner, history
    /// ring, curiosity channel and (counted in full, although sessions on one
    /// model share it) its planning model.
    pub bytes: u64,
    /// Worst-case CPU time of one observation in lockstep mode (observe
    /// plus one policy update), in microseconds.
    pub tick_us: u64,
}
