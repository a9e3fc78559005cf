//! Every conversion between proto messages and service types, in one place
//! (docs/architecture.md). Inbound messages are destructured fully, so a field
//! added to the proto fails to compile here until it is handled; outbound
//! service types are destructured too, so a new service field is not
//! silently left off the wire. Failures are `ServiceError`s naming the field;
//! the caller maps them with `api::error::to_status`.

use std::time::Duration;

use crate::service::wire::{GridLayout, GridMark};
use crate::service::{
    BasisSummary, CreateSession, CuriosityConfig, CuriosityInfo, EffectiveConfig, FrozenModuleInfo,
    HistoryEntry, ModelSummary, ObservationIn, ServiceError, SessionConfig, SessionInfo,
    SessionPage, SessionStats, SessionSummary, StepOut, TickCuriosity, UpdateMode, ValueSelection,
    Values,
};
use std::collections::BTreeMap;

use crate::service::ModelInput;
use crate::service::spec::{LearnedSpec, learned_params};
use crate::service::wire::{ContinuousStatsOut, LearnedSummary};
use mcapi_core::continuous::{
    ContinuousBasisSpec, ContinuousSpec, ObservationSpace, OutOfBounds, SampleParams,
};
use mcapi_core::params::StimulusRateName;
use mcapi_core::spec::{ActionRef, ModelSpec, TransitionSpec};
use mcapi_core::{BasisSpec, LearnedParams, Optimism, StimulusRate};

use super::pb;
use crate::api::extract::create_part;
use crate::service::groups::{ADVISED, Columns, GroupInfo, MemberStep};

/// Interval of `Watch` when the request leaves it 0.
pub const DEFAULT_WATCH_INTERVAL: Duration = Duration::from_secs(1);
/// Shortest interval of `Watch`, in milliseconds.
pub const MIN_WATCH_INTERVAL_MS: u32 = 10;
/// Longest interval of `Watch`, in milliseconds (one hour).
pub const MAX_WATCH_INTERVAL_MS: u32 = 3_600_000;

// ------------------------------------------------------------------ inbound

fn to_usize(field: &str, n: u64) -> Result<usize, ServiceError> {
    usize::try_from(n).map_err(|_| ServiceError::field(field, format!("{n} is too large")))
}

/// What `CreateSession` asks for: the model as REST JSON (the deprecated
/// `model_json`) or typed (`model`), already parsed.
#[derive(Debug)]
pub enum CreateCall {
    /// `model_json`: parsed by the service exactly as REST's body.
    Json(CreateSession),
    /// `model`: converted here into the service's own model type.
    Typed {
        /// The model, in the form the REST JSON parses into.
        model: ModelInput,
        /// Agent configuration.
        agent: SessionConfig,
    },
}

/// `CreateSession`: exactly one of `model` (typed) and `model_json`
/// (deprecated, the JSON the REST API takes).
#[allow(deprecated)]
pub fn create_session(req: pb::CreateSessionRequest) -> Result<CreateCall, ServiceError> {
    let pb::CreateSessionRequest {
        model_json,
        agent,
        model,
    } = req;
    let agent = agent.map(session_config).transpose()?.unwrap_or_default();
    match (model, model_json.trim().is_empty()) {
        (Some(_), false) => Err(ServiceError::field(
            "model",
            "and `model_json` are both set; set only `model` (`model_json` is deprecated)",
        )),
        (None, true) => Err(ServiceError::field(
            "model",
            "is required: set `model` (or the deprecated `model_json`)",
        )),
        (Some(m), true) => Ok(CreateCall::Typed {
            model: model_input(m)?,
            agent,
        }),
        (None, false) => {
            let model = create_part("model_json", &model_json, "/model")?;
            Ok(CreateCall::Json(CreateSession { model, agent }))
        }
    }
}

/// The typed model as the service's [`ModelInput`], the type the REST JSON
/// parses into: from here on both transports share every check, limit and
/// error (`ModelInput::build`). Only what JSON cannot express wrongly is
/// checked here (an unset `oneof`, a negative successor); nothing is
/// allocated beyond the decoded message's own size.
pub fn model_input(m: pb::Model) -> Result<ModelInput, ServiceError> {
    use pb::model::Form;
    let pb::Model { form } = m;
    match form {
        None => Err(ServiceError::field(
            "model",
            "has no form: set one of `preset`, `grid`, `full` or `continuous`",
        )),
        Some(Form::Preset(pb::PresetModel { name, basis })) => Ok(ModelInput::Preset {
            name,
            basis: basis.map(basis_spec).transpose()?,
        }),
        Some(Form::Grid(pb::GridModel {
            rows,
            sources,
            stimuli,
            basis,
            learn,
            learning,
        })) => Ok(ModelInput::Grid {
            lines: rows,
            sources: sources
                .into_iter()
                .map(|(mark, dim)| Ok((mark, to_usize("model.sources", dim)?)))
                .collect::<Result<BTreeMap<_, _>, ServiceError>>()?,
            // proto3 cannot tell an empty list from an absent one: empty is
            // the default (the marks).
            stimuli: (!stimuli.is_empty()).then_some(stimuli),
            basis: basis.map(basis_spec).transpose()?,
            learn: match (learn, learning) {
                (false, Some(_)) => {
                    return Err(ServiceError::field(
                        "model.learning",
                        "is only taken with `learn` set",
                    ));
                }
                (false, None) => None,
                (true, l) => Some(learned_params(
                    "model.learning",
                    l.map(learned_transitions).transpose()?,
                )?),
            },
        }),
        Some(Form::Full(full)) => model_spec(full),
        Some(Form::Continuous(c)) => continuous_spec(c),
    }
}

/// The optional learned-model parameters (REST `learning`).
fn learned_transitions(l: pb::LearnedTransitions) -> Result<LearnedParams, ServiceError> {
    let pb::LearnedTransitions {
        known_after,
        optimism,
    } = l;
    let optimism = match pb::Optimism::try_from(optimism) {
        Ok(pb::Optimism::Unspecified) => None,
        Ok(pb::Optimism::Absorbing) => Some(Optimism::Absorbing),
        Ok(pb::Optimism::Stimulus) => Some(Optimism::Stimulus),
        Err(_) => {
            return Err(ServiceError::field(
                "model.learning.optimism",
                format!("unknown value {optimism} (1: absorbing, 2: stimulus)"),
            ));
        }
    };
    Ok(LearnedParams {
        known_after,
        optimism,
    })
}

fn optimism(o: Optimism) -> pb::Optimism {
    match o {
        Optimism::Absorbing => pb::Optimism::Absorbing,
        Optimism::Stimulus => pb::Optimism::Stimulus,
    }
}

fn model_spec(m: pb::FullModel) -> Result<ModelInput, ServiceError> {
    use pb::full_model::Transitions;
    let pb::FullModel {
        states,
        state_names,
        actions,
        stimuli,
        transitions,
        basis,
    } = m;
    let (next, transitions) = match transitions {
        None => (None, None),
        Some(Transitions::Learn(l)) => {
            return Ok(ModelInput::Learned(Box::new(LearnedSpec {
                states: to_usize("model.states", states)?,
                state_names: (!state_names.is_empty()).then_some(state_names),
                actions,
                stimuli,
                basis: basis.map(basis_spec).transpose()?,
                learning: learned_params("model.learning", Some(learned_transitions(l)?))?,
            })));
        }
        Some(Transitions::Next(pb::DeterministicTransitions { rows })) => {
            let next = rows
                .into_iter()
                .enumerate()
                .map(|(s, pb::NextRow { next })| {
                    next.into_iter()
                        .enumerate()
                        .map(|(a, s2)| match s2 {
                            -1 => Ok(None),
                            s2 => usize::try_from(s2).map(Some).map_err(|_| {
                                ServiceError::field(
                                    &format!("model.next[{s}][{a}]"),
                                    format!("is {s2}; a state is at least 0 (-1: unavailable)"),
                                )
                            }),
                        })
                        .collect::<Result<Vec<_>, _>>()
                })
                .collect::<Result<Vec<_>, _>>()?;
            (Some(next), None)
        }
        Some(Transitions::Stochastic(pb::StochasticTransitions { transitions })) => {
            let t = transitions
                .into_iter()
                .enumerate()
                .map(|(i, t)| transition_spec(i, t))
                .collect::<Result<Vec<_>, _>>()?;
            (None, Some(t))
        }
    };
    Ok(ModelInput::Spec(Box::new(ModelSpec {
        states: to_usize("model.states", states)?,
        // proto3 cannot tell an empty list from an absent one: empty is none.
        state_names: (!state_names.is_empty()).then_some(state_names),
        actions,
        next,
        transitions,
        stimuli,
        basis: basis.map(basis_spec).transpose()?,
    })))
}

fn transition_spec(i: usize, t: pb::Transition) -> Result<TransitionSpec, ServiceError> {
    use pb::transition::Action;
    let pb::Transition {
        state,
        action,
        next,
    } = t;
    let action = match action {
        None => {
            return Err(ServiceError::field(
                &format!("model.transitions[{i}].action"),
                "is required: set `action_index` or `action_name`",
            ));
        }
        Some(Action::ActionIndex(a)) => ActionRef::Index(to_usize(
            &format!("model.transitions[{i}].action_index"),
            a,
        )?),
        Some(Action::ActionName(name)) => ActionRef::Name(name),
    };
    let next = next
        .into_iter()
        .map(|pb::Successor { state, probability }| {
            Ok((
                to_usize(&format!("model.transitions[{i}].next.state"), state)?,
                probability,
            ))
        })
        .collect::<Result<Vec<_>, ServiceError>>()?;
    Ok(TransitionSpec {
        state: to_usize(&format!("model.transitions[{i}].state"), state)?,
        action,
        next,
    })
}

fn basis_spec(b: pb::Basis) -> Result<BasisSpec, ServiceError> {
    use pb::basis::Kind;
    let pb::Basis { kind } = b;
    match kind {
        None => Err(ServiceError::field(
            "model.basis",
            "has no kind: set one of `indicator`, `proto_value` or `custom`",
        )),
        Some(Kind::Indicator(pb::IndicatorBasis {})) => Ok(BasisSpec::Indicator),
        Some(Kind::ProtoValue(pb::ProtoValueBasis { k })) => Ok(BasisSpec::ProtoValue {
            k: to_usize("model.basis.k", k)?,
        }),
        Some(Kind::Custom(pb::CustomBasis { state_features })) => Ok(BasisSpec::Custom {
            state_features: state_features
                .into_iter()
                .map(|pb::FeatureRow { features }| features)
                .collect(),
        }),
    }
}

fn session_config(c: pb::SessionConfig) -> Result<SessionConfig, ServiceError> {
    let pb::SessionConfig {
        eta,
        gamma,
        priorities,
        stimulus_rate,
        optimistic_sd,
        ridge,
        epsilon,
        seed,
        update_mode,
        history,
        curiosity,
    } = c;
    let stimulus_rate = match stimulus_rate {
        None => None,
        Some(pb::session_config::StimulusRate::StimulusRateConstant(c)) => {
            Some(StimulusRate::Constant(c))
        }
        Some(pb::session_config::StimulusRate::StimulusRateRule(rule)) => {
            Some(stimulus_rate_rule("agent.stimulus_rate_rule", rule)?)
        }
    };
    let update_mode = match pb::UpdateMode::try_from(update_mode) {
        Ok(pb::UpdateMode::Unspecified) => None,
        Ok(pb::UpdateMode::Lockstep) => Some(UpdateMode::Lockstep),
        Ok(pb::UpdateMode::Async) => Some(UpdateMode::Async),
        Err(_) => {
            return Err(ServiceError::field(
                "agent.update_mode",
                format!("unknown value {update_mode}"),
            ));
        }
    };
    Ok(SessionConfig {
        eta,
        gamma,
        // proto3 cannot tell an empty list from an absent one: empty is the
        // default (an empty list is never valid, every model has stimuli).
        priorities: (!priorities.is_empty()).then_some(priorities),
        stimulus_rate,
        optimistic_sd,
        ridge,
        epsilon,
        seed,
        update_mode,
        history: history.map(|h| to_usize("agent.history", h)).transpose()?,
        curiosity: curiosity.map(curiosity_config).transpose()?,
    })
}

fn curiosity_config(c: pb::CuriosityConfig) -> Result<CuriosityConfig, ServiceError> {
    let pb::CuriosityConfig {
        signal_dim,
        params_json,
    } = c;
    let params = if params_json.trim().is_empty() {
        Default::default()
    } else {
        create_part(
            "agent.curiosity.params_json",
            &params_json,
            "/agent/curiosity/params",
        )?
    };
    Ok(CuriosityConfig {
        signal_dim: to_usize("agent.curiosity.signal_dim", signal_dim)?,
        params,
    })
}

fn stimulus_rate_rule(field: &str, rule: i32) -> Result<StimulusRate, ServiceError> {
    match pb::StimulusRateRule::try_from(rule) {
        Ok(pb::StimulusRateRule::SampleMean) => {
            Ok(StimulusRate::Named(StimulusRateName::SampleMean))
        }
        Ok(pb::StimulusRateRule::Unspecified) => Err(ServiceError::field(
            field,
            "is unspecified; leave `stimulus_rate` unset for the default",
        )),
        Err(_) => Err(ServiceError::field(field, format!("unknown value {rule}"))),
    }
}

/// The session id a call concerns: the message's, or when that is empty the
/// `x-mcapi-session` metadata's; when both are given they must agree
/// (docs/sessions.md, "Session ids and ownership").
pub fn session_id(message_id: String, metadata_id: Option<&str>) -> Result<String, ServiceError> {
    match (message_id.is_empty(), metadata_id) {
        (false, Some(meta)) if meta != message_id => Err(ServiceError::field(
            "session_id",
            format!("`{message_id}` does not match the `x-mcapi-session` metadata `{meta}`"),
        )),
        (false, _) => Ok(message_id),
        (true, Some(meta)) if !meta.is_empty() => Ok(meta.to_string()),
        (true, _) => Err(ServiceError::field(
            "session_id",
            "is required (in the message or as `x-mcapi-session` metadata)",
        )),
    }
}

/// One observation and the session it is for (its own `session_id`, or
/// `default_id` when empty; both must agree when both are given).
pub fn observation(
    obs: pb::Observation,
    default_id: Option<&str>,
) -> Result<(String, ObservationIn), ServiceError> {
    let pb::Observation {
        session_id: id,
        state,
        stimulus,
        action_taken,
        signal,
        signal_source,
        observation,
        seq,
    } = obs;
    let id = session_id(id, default_id)?;
    let action_taken = match action_taken {
        None => None,
        Some(pb::observation::ActionTaken::ActionName(name)) => Some(ActionRef::Name(name)),
        Some(pb::observation::ActionTaken::ActionIndex(a)) => {
            Some(ActionRef::Index(to_usize("action_index", u64::from(a))?))
        }
    };
    let stimulus = stimulus.map(|pb::Stimulus { values }| values);
    Ok((
        id,
        ObservationIn {
            // proto3 cannot tell state 0 from none: with an observation
            // vector, 0 is none, and any other state is refused with both.
            state: match (state, observation.is_empty()) {
                (0, false) => None,
                (s, _) => Some(to_usize("state", s)?),
            },
            observation: (!observation.is_empty()).then_some(observation),
            stimulus,
            action_taken,
            // proto3 cannot tell an empty list from an absent one; a signal
            // has at least one component.
            signal: (!signal.is_empty()).then_some(signal),
            signal_source: signal_source.map(|s| s as usize),
            seq,
        },
    ))
}

/// `Observe`: the session and its batch; every observation's own id must
/// be empty or the request's.
pub fn observe_request(
    req: pb::ObserveRequest,
    metadata_id: Option<&str>,
) -> Result<(String, Vec<ObservationIn>), ServiceError> {
    let pb::ObserveRequest {
        session_id: id,
        observations,
    } = req;
    let id = session_id(id, metadata_id)?;
    let batch = observations
        .into_iter()
        .enumerate()
        .map(|(i, obs)| {
            if !obs.session_id.is_empty() && obs.session_id != id {
                return Err(ServiceError::field(
                    &format!("observations[{i}].session_id"),
                    format!("`{}` differs from the request's `{id}`", obs.session_id),
                ));
            }
            observation(obs, Some(&id)).map(|(_, obs)| obs)
        })
        .collect::<Result<_, _>>()?;
    Ok((id, batch))
}

/// `ListSessions`: `after` and `limit`.
pub fn list_request(req: pb::ListSessionsRequest) -> (Option<String>, Option<usize>) {
    let pb::ListSessionsRequest { after, limit } = req;
    // u32 always fits usize on the platforms tonic supports.
    (after, limit.map(|l| l as usize))
}

/// `Watch`: the session and the interval between snapshots.
pub fn watch_request(
    req: pb::WatchRequest,
    metadata_id: Option<&str>,
) -> Result<(String, Duration), ServiceError> {
    let pb::WatchRequest {
        session_id: id,
        interval_ms,
    } = req;
    let id = session_id(id, metadata_id)?;
    let interval = match interval_ms {
        0 => DEFAULT_WATCH_INTERVAL,
        ms if (MIN_WATCH_INTERVAL_MS..=MAX_WATCH_INTERVAL_MS).contains(&ms) => {
            Duration::from_millis(u64::from(ms))
        }
        ms => {
            return Err(ServiceError::field(
                "interval_ms",
                format!(
                    "{ms} is not between {MIN_WATCH_INTERVAL_MS} and {MAX_WATCH_INTERVAL_MS} (or 0 for the default of {} ms)",
                    DEFAULT_WATCH_INTERVAL.as_millis()
                ),
            ));
        }
    };
    Ok((id, interval))
}

/// `GetHistory`: the session and the number of ticks.
pub fn history_request(
    req: pb::GetHistoryRequest,
    metadata_id: Option<&str>,
) -> Result<(String, Option<usize>), ServiceError> {
    let pb::GetHistoryRequest {
        session_id: id,
        limit,
    } = req;
    let id = session_id(id, metadata_id)?;
    match limit {
        // As REST refuses `?limit=0`.
        Some(0) => Err(ServiceError::field(
            "limit",
            "must be at least 1 (leave it unset for every tick kept)",
        )),
        limit => Ok((id, limit.map(|l| l as usize))),
    }
}

/// `GetValues`: the session and the tables, parsed as REST's `?include=`.
pub fn values_request(
    req: pb::GetValuesRequest,
    metadata_id: Option<&str>,
) -> Result<(String, ValueSelection), ServiceError> {
    let pb::GetValuesRequest {
        session_id: id,
        include,
    } = req;
    let id = session_id(id, metadata_id)?;
    Ok((id, ValueSelection::parse(Some(&include.join(",")))?))
}

// ----------------------------------------------------------------- outbound

// Counts and indices fit u32/u64: the model stores pair indices as u32.
fn u32_of(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

fn update_mode(mode: UpdateMode) -> pb::UpdateMode {
    match mode {
        UpdateMode::Lockstep => pb::UpdateMode::Lockstep,
        UpdateMode::Async => pb::UpdateMode::Async,
    }
}

fn basis(summary: BasisSummary) -> pb::BasisSummary {
    let BasisSummary { kind, k } = summary;
    pb::BasisSummary { kind, k: k as u64 }
}

fn model_summary(m: ModelSummary) -> pb::ModelSummary {
    let ModelSummary {
        states,
        actions,
        stimuli,
        pairs,
        transitions,
        deterministic,
        basis: spec,
        features,
        layout,
        learned,
        continuous,
    } = m;
    pb::ModelSummary {
        states: states as u64,
        actions,
        stimuli,
        pairs: pairs as u64,
        transitions: transitions as u64,
        deterministic,
        basis: Some(basis(spec)),
        features: features as u64,
        layout: layout.map(grid_layout),
        learned: learned.map(
            |LearnedSummary {
                 known_after,
                 optimism: o,
                 max_transitions,
             }| pb::LearnedSummary {
                known_after,
                optimism: optimism(o).into(),
                max_transitions: max_transitions as u64,
            },
        ),
        continuous: continuous.map(continuous_model_pb),
    }
}

/// A continuous model as the typed API shows it.
fn continuous_model_pb(spec: ContinuousSpec) -> pb::ContinuousModel {
    let ContinuousSpec {
        observation_space: ObservationSpace { low, high },
        actions,
        stimuli,
        basis,
        out_of_bounds,
        samples,
    } = spec;
    use pb::continuous_basis::Kind;
    pb::ContinuousModel {
        low,
        high,
        actions,
        stimuli,
        basis: basis.map(|b| pb::ContinuousBasis {
            kind: Some(match b {
                ContinuousBasisSpec::Fourier {
                    order,
                    max_coupling,
                } => Kind::Fourier(pb::FourierBasis {
                    order,
                    max_coupling,
                }),
                ContinuousBasisSpec::Rbf {
                    centres_per_dim,
                    width,
                } => Kind::Rbf(pb::RbfBasis {
                    centres_per_dim,
                    width,
                }),
                ContinuousBasisSpec::Tiles {
                    tilings,
                    tiles_per_dim,
                    table,
                } => Kind::Tiles(pb::TileBasis {
                    tilings,
                    tiles_per_dim,
                    table,
                }),
                ContinuousBasisSpec::Pvf {
                    k,
                    nodes,
                    neighbours,
                } => Kind::Pvf(pb::NystromPvfBasis {
                    k,
                    nodes,
                    neighbours,
                }),
                ContinuousBasisSpec::Grid {
                    cells_per_dim,
                    neighbours,
                    reach,
                } => Kind::Grid(pb::GridBasis {
                    cells_per_dim,
                    neighbours,
                    reach,
                }),
            }),
        }),
        out_of_bounds: match out_of_bounds {
            OutOfBounds::Clip => pb::OutOfBounds::Clip,
            OutOfBounds::Refuse => pb::OutOfBounds::Refuse,
        }
        .into(),
        samples: Some(pb::SampleParams {
            cells_per_dim: samples.cells_per_dim,
            per_cell: samples.per_cell,
            max: samples.max,
            known_after: samples.known_after,
        }),
    }
}

/// The typed continuous model as the service's [`ContinuousSpec`]; its
/// sizes are checked by [`ContinuousSpec::build`], as the REST JSON's.
fn continuous_spec(m: pb::ContinuousModel) -> Result<ModelInput, ServiceError> {
    use pb::continuous_basis::Kind;
    let pb::ContinuousModel {
        low,
        high,
        actions,
        stimuli,
        basis,
        out_of_bounds,
        samples,
    } = m;
    let basis = match basis {
        None => None,
        Some(pb::ContinuousBasis { kind: None }) => {
            return Err(ServiceError::field(
                "model.basis",
                "has no kind: set one of `fourier`, `rbf`, `tiles`, `pvf` or `grid`",
            ));
        }
        Some(pb::ContinuousBasis { kind: Some(k) }) => Some(match k {
            Kind::Fourier(pb::FourierBasis {
                order,
                max_coupling,
            }) => ContinuousBasisSpec::Fourier {
                order,
                max_coupling,
            },
            Kind::Rbf(pb::RbfBasis {
                centres_per_dim,
                width,
            }) => ContinuousBasisSpec::Rbf {
                centres_per_dim,
                width,
            },
            Kind::Tiles(pb::TileBasis {
                tilings,
                tiles_per_dim,
                table,
            }) => ContinuousBasisSpec::Tiles {
                tilings,
                tiles_per_dim,
                table,
            },
            Kind::Pvf(pb::NystromPvfBasis {
                k,
                nodes,
                neighbours,
            }) => ContinuousBasisSpec::Pvf {
                k,
                nodes,
                neighbours,
            },
            Kind::Grid(pb::GridBasis {
                cells_per_dim,
                neighbours,
                reach,
            }) => ContinuousBasisSpec::Grid {
                cells_per_dim,
                neighbours,
                reach,
            },
        }),
    };
    let out_of_bounds = match pb::OutOfBounds::try_from(out_of_bounds) {
        Ok(pb::OutOfBounds::Unspecified | pb::OutOfBounds::Clip) => OutOfBounds::Clip,
        Ok(pb::OutOfBounds::Refuse) => OutOfBounds::Refuse,
        Err(_) => {
            return Err(ServiceError::field(
                "model.out_of_bounds",
                format!("unknown value {out_of_bounds} (1: clip, 2: refuse)"),
            ));
        }
    };
    let samples = samples.map_or_else(SampleParams::default, |s| SampleParams {
        cells_per_dim: s.cells_per_dim,
        per_cell: s.per_cell,
        max: s.max,
        known_after: s.known_after,
    });
    Ok(ModelInput::Continuous(Box::new(ContinuousSpec {
        observation_space: ObservationSpace { low, high },
        actions,
        stimuli,
        basis,
        out_of_bounds,
        samples,
    })))
}

fn grid_layout(l: GridLayout) -> pb::GridLayout {
    let GridLayout {
        rows,
        cols,
        cells,
        marks,
    } = l;
    pb::GridLayout {
        rows: rows as u64,
        cols: cols as u64,
        cells: cells
            .into_iter()
            .map(|[row, col]| pb::GridCell {
                row: row as u64,
                col: col as u64,
            })
            .collect(),
        marks: marks
            .into_iter()
            .map(|GridMark { mark, state }| pb::GridMark {
                mark,
                state: state as u64,
            })
            .collect(),
    }
}

fn effective_config(c: EffectiveConfig) -> pb::EffectiveConfig {
    let EffectiveConfig {
        eta,
        gamma,
        priorities,
        stimulus_rate,
        optimistic_sd,
        ridge,
        epsilon,
        seed,
        update_mode: mode,
        history,
        curiosity,
    } = c;
    use pb::effective_config::StimulusRate as Rate;
    let stimulus_rate = match stimulus_rate {
        StimulusRate::Constant(c) => Rate::StimulusRateConstant(c),
        StimulusRate::Named(StimulusRateName::SampleMean) => {
            Rate::StimulusRateRule(pb::StimulusRateRule::SampleMean.into())
        }
    };
    pb::EffectiveConfig {
        eta,
        gamma,
        priorities,
        stimulus_rate: Some(stimulus_rate),
        optimistic_sd,
        ridge,
        epsilon,
        seed,
        update_mode: update_mode(mode).into(),
        history: history as u64,
        curiosity: curiosity.map(
            |CuriosityConfig { signal_dim, params }| pb::CuriosityConfig {
                signal_dim: signal_dim as u64,
                params_json: serde_json::to_string(&params).unwrap_or_default(),
            },
        ),
    }
}

fn curiosity_info(c: CuriosityInfo) -> pb::CuriosityInfo {
    let CuriosityInfo {
        samples,
        epsilon,
        active_source,
        active_samples,
        all_explained,
        modules,
    } = c;
    pb::CuriosityInfo {
        samples,
        epsilon,
        active_source: active_source.map(|s| s as u64),
        active_samples,
        all_explained,
        modules: modules
            .into_iter()
            .map(
                |FrozenModuleInfo {
                     source,
                     frozen_tick,
                     learned_samples,
                 }| pb::FrozenModule {
                    source: source as u64,
                    frozen_tick,
                    learned_samples,
                },
            )
            .collect(),
    }
}

fn tick_curiosity(c: TickCuriosity) -> pb::TickCuriosity {
    let TickCuriosity {
        xi_cur,
        epsilon,
        modules,
        source,
    } = c;
    pb::TickCuriosity {
        xi_cur,
        epsilon,
        modules: modules as u64,
        source: source.map(|s| s as u64),
    }
}

fn stats(s: SessionStats) -> pb::SessionStats {
    let SessionStats {
        lstdq_error,
        lambda1_estimate,
        condition_1_holds,
        constant_stimuli,
        factorisation_reuses,
        factorisations,
        continuous,
    } = s;
    pb::SessionStats {
        lstdq_error,
        lambda1_estimate,
        condition_1_holds,
        constant_stimuli: constant_stimuli.into_iter().map(|d| d as u64).collect(),
        factorisation_reuses,
        factorisations,
        continuous: continuous.map(
            |ContinuousStatsOut {
                 clipped,
                 samples,
                 slots,
                 updates,
                 rebuilds,
                 basis_builds,
             }| pb::ContinuousStats {
                clipped,
                samples: samples as u64,
                slots: slots as u64,
                updates,
                rebuilds,
                basis_builds,
            },
        ),
    }
}

/// A session's details.
pub fn session_info(info: SessionInfo) -> pb::SessionInfo {
    let SessionInfo {
        id,
        tick,
        drive,
        policy_version,
        next_seq,
        state,
        model,
        agent,
        stats: s,
        cost,
        curiosity,
    } = info;
    pb::SessionInfo {
        id,
        tick,
        drive,
        policy_version,
        next_seq,
        state: state.map(|s| s as u64),
        model: Some(model_summary(model)),
        agent: Some(effective_config(agent)),
        stats: Some(stats(s)),
        curiosity: curiosity.map(curiosity_info),
        cost: Some(pb::SessionCost {
            bytes: cost.bytes,
            tick_us: cost.tick_us,
        }),
    }
}

/// A page of sessions.
pub fn session_page(page: SessionPage) -> pb::ListSessionsResponse {
    let SessionPage { sessions, next } = page;
    pb::ListSessionsResponse {
        sessions: sessions
            .into_iter()
            .map(
                |SessionSummary {
                     id,
                     tick,
                     states,
                     update_mode: mode,
                     idle_ms,
                 }| pb::SessionSummary {
                    id,
                    tick,
                    states: states as u64,
                    update_mode: update_mode(mode).into(),
                    idle_ms,
                },
            )
            .collect(),
        next,
    }
}

/// The reply to one observation.
pub fn step(s: StepOut) -> pb::Step {
    let StepOut {
        tick,
        action,
        action_index,
        drive,
        reward,
        policy_version,
        curiosity,
        replayed,
    } = s;
    pb::Step {
        tick,
        action,
        action_index: u32_of(action_index),
        drive,
        reward,
        policy_version,
        curiosity: curiosity.map(tick_curiosity),
        replayed,
    }
}

/// A session's recent ticks.
pub fn history(entries: Vec<HistoryEntry>) -> pb::History {
    pb::History {
        entries: entries
            .into_iter()
            .map(
                |HistoryEntry {
                     tick,
                     state,
                     action,
                     drive,
                     reward,
                     lstdq_error,
                     stimulus,
                     curiosity,
                     known_fraction,
                     observation,
                 }| pb::HistoryEntry {
                    tick,
                    state: state as u64,
                    action_index: u32_of(action),
                    drive,
                    reward,
                    lstdq_error,
                    stimulus: stimulus.map(|values| pb::Stimulus { values }),
                    curiosity: curiosity.map(tick_curiosity),
                    known_fraction,
                    observation: observation.unwrap_or_default(),
                },
            )
            .collect(),
    }
}

/// The available pairs of a `[state][action]` table, row by row.
fn pairs<T>(table: Vec<Vec<Option<T>>>) -> impl Iterator<Item = (u64, u32, T)> {
    table.into_iter().enumerate().flat_map(|(s, row)| {
        row.into_iter()
            .enumerate()
            .filter_map(move |(a, x)| x.map(|x| (s as u64, u32_of(a), x)))
    })
}

fn pair_values(table: Vec<Vec<Option<f64>>>) -> pb::PairValues {
    pb::PairValues {
        pairs: pairs(table)
            .map(|(state, action, value)| pb::PairValue {
                state,
                action,
                value,
            })
            .collect(),
    }
}

/// Value tables; per-pair tables list the available pairs only.
pub fn values(v: Values) -> pb::Values {
    let Values {
        tick,
        policy_version,
        v,
        q,
        policy,
        r,
        xi,
        curiosity,
        known_fraction,
        points,
    } = v;
    pb::Values {
        tick,
        policy_version,
        v: v.map(|values| pb::StateValues { values }),
        q: q.map(pair_values),
        policy: policy.map(|actions| pb::Policy { actions }),
        r: r.map(pair_values),
        xi: xi.map(|table| pb::PairVectors {
            pairs: pairs(table)
                .map(|(state, action, values)| pb::PairVector {
                    state,
                    action,
                    values,
                })
                .collect(),
        }),
        curiosity: curiosity.map(curiosity_info),
        known_fraction,
        points: points
            .unwrap_or_default()
            .into_iter()
            .map(|x| pb::Point { x })
            .collect(),
    }
}

// ------------------------------------------------------------------ groups

/// `CreateGroup`: the typed model, the members' configuration, `n` and the
/// group's seed.
pub fn create_group(
    req: pb::CreateGroupRequest,
) -> Result<(ModelInput, SessionConfig, u64, Option<u64>), ServiceError> {
    let pb::CreateGroupRequest {
        model,
        agent,
        n,
        seed,
    } = req;
    let agent = agent.map(session_config).transpose()?.unwrap_or_default();
    let model = model.ok_or_else(|| ServiceError::field("model", "is required"))?;
    Ok((model_input(model)?, agent, u64::from(n), seed))
}

/// A group's id: the message's, or the `x-mcapi-session` metadata's; both
/// must agree when both are given.
pub fn group_id(message_id: String, metadata_id: Option<&str>) -> Result<String, ServiceError> {
    match (message_id.is_empty(), metadata_id) {
        (false, Some(meta)) if meta != message_id => Err(ServiceError::field(
            "group_id",
            format!("`{message_id}` does not match the `x-mcapi-session` metadata `{meta}`"),
        )),
        (false, _) => Ok(message_id),
        (true, Some(meta)) if !meta.is_empty() => Ok(meta.to_string()),
        (true, _) => Err(ServiceError::field(
            "group_id",
            "is required (in the message or as `x-mcapi-session` metadata)",
        )),
    }
}

/// A group as the proto says it.
pub fn group_info(g: GroupInfo) -> pb::GroupInfo {
    let GroupInfo {
        id,
        size,
        seed,
        update_mode: mode,
        stimuli,
        observation_dim,
        members,
    } = g;
    pb::GroupInfo {
        group_id: id,
        size: u32_of(size),
        seed,
        update_mode: update_mode(mode).into(),
        stimuli: u32_of(stimuli),
        observation_dim: u32_of(observation_dim.unwrap_or(0)),
        member_ids: members.into_iter().map(Option::unwrap_or_default).collect(),
    }
}

/// Little-endian binary64 numbers of a `bytes` column; its length must be
/// a whole number of them.
fn le_f64s(field: &str, bytes: &[u8]) -> Result<Vec<f64>, ServiceError> {
    if bytes.len() % 8 != 0 {
        return Err(ServiceError::ColumnLength(format!(
            "`{field}` has {} bytes, not a whole number of 8-byte little-endian numbers",
            bytes.len()
        )));
    }
    Ok(bytes
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
        .collect())
}

/// Numbers as a little-endian binary64 `bytes` column.
fn le_bytes(xs: impl IntoIterator<Item = f64>) -> Vec<u8> {
    xs.into_iter().flat_map(f64::to_le_bytes).collect()
}

/// One `StepGroup` message: its group id (possibly empty), its seq and its
/// columns.
pub fn group_step(req: pb::GroupStepRequest) -> Result<(String, u64, Columns), ServiceError> {
    let pb::GroupStepRequest {
        group_id,
        seq,
        states,
        observations,
        stimuli,
        action_taken,
        mask,
        seqs,
    } = req;
    let columns = Columns {
        mask,
        states,
        observations: le_f64s("observations", &observations)?,
        stimuli: le_f64s("stimuli", &stimuli)?,
        action_taken,
        seqs,
    };
    Ok((group_id, seq, columns))
}

/// The reply to one `StepGroup` message: the columns of its members' steps,
/// `n` numbers of drive each; a refused member's entries are
/// placeholders (action `u32::MAX`, drive and reward 0, version and tick 0,
/// not replayed) and a status: no NaN leaves the server, not even as a
/// marker. `numbered`: the message carried `seqs`, and the reply's
/// `replayed` has one entry per member.
pub fn group_step_reply(
    seq: u64,
    n: usize,
    steps: Vec<MemberStep>,
    numbered: bool,
) -> pb::GroupStepReply {
    let m = steps.len();
    let mut reply = pb::GroupStepReply {
        seq,
        actions: Vec::with_capacity(m),
        drives: Vec::with_capacity(m * n * 8),
        rewards: Vec::with_capacity(m * 8),
        policy_versions: Vec::with_capacity(m),
        statuses: Vec::new(),
        ticks: Vec::with_capacity(m),
        replayed: Vec::with_capacity(if numbered { m } else { 0 }),
    };
    for MemberStep { index, result } in steps {
        match result {
            Ok(step) => {
                let StepOut {
                    tick,
                    action: _,
                    action_index,
                    drive,
                    reward,
                    policy_version,
                    curiosity: _,
                    replayed,
                } = step;
                reply.actions.push(u32_of(action_index));
                reply.drives.extend(le_bytes(drive));
                reply.rewards.extend(reward.to_le_bytes());
                reply.policy_versions.push(policy_version);
                reply.ticks.push(tick);
                if numbered {
                    reply.replayed.push(replayed);
                }
            }
            Err(e) => {
                reply.actions.push(ADVISED);
                reply.drives.extend(le_bytes(std::iter::repeat_n(0.0, n)));
                reply.rewards.extend(0.0f64.to_le_bytes());
                reply.policy_versions.push(0);
                reply.ticks.push(0);
                if numbered {
                    reply.replayed.push(false);
                }
                let (expected_seq, oldest_seq) = crate::api::error::seq_details(&e);
                let pb::StepError {
                    status,
                    code,
                    message,
                    owner: _,
                } = crate::api::error::step_error(e);
                reply.statuses.push(pb::MemberStatus {
                    index: u32_of(index),
                    status,
                    code,
                    message,
                    expected_seq,
                    oldest_seq,
                });
            }
        }
    }
    reply
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadata_fills_an_empty_id_and_must_agree_with_a_given_one() {
        assert_eq!(session_id("a".into(), None).expect("id"), "a");
        assert_eq!(session_id(String::new(), Some("b")).expect("id"), "b");
        assert_eq!(session_id("a".into(), Some("a")).expect("id"), "a");
        let e = session_id("a".into(), Some("b")).expect_err("mismatch");
        assert!(e.to_string().contains("x-mcapi-session"), "{e}");
        assert!(session_id(String::new(), None).is_err());
    }

    #[test]
    fn an_observation_without_stimulus_is_a_first_observation() {
        let (id, obs) = observation(
            pb::Observation {
                session_id: "s".into(),
                state: 3,
                stimulus: None,
                action_taken: None,
                signal: vec![],
                signal_source: None,
                observation: vec![],
                seq: None,
            },
            None,
        )
        .expect("valid");
        assert_eq!(id, "s");
        assert_eq!(obs.stimulus, None);
        let (_, obs) = observation(
            pb::Observation {
                session_id: "s".into(),
                state: 3,
                stimulus: Some(pb::Stimulus { values: vec![] }),
                action_taken: Some(pb::observation::ActionTaken::ActionName("left".into())),
                signal: vec![0.5, 1.0],
                signal_source: Some(1),
                observation: vec![],
                seq: None,
            },
            None,
        )
        .expect("valid");
        assert_eq!(obs.stimulus, Some(vec![]));
        assert_eq!(obs.action_taken, Some(ActionRef::Name("left".into())));
        assert_eq!(obs.signal, Some(vec![0.5, 1.0]));
        assert_eq!(obs.signal_source, Some(1));
    }

    #[test]
    fn watch_interval_is_bounded() {
        let req = |ms| pb::WatchRequest {
            session_id: "s".into(),
            interval_ms: ms,
        };
        assert_eq!(
            watch_request(req(0), None).expect("default").1,
            DEFAULT_WATCH_INTERVAL
        );
        assert_eq!(
            watch_request(req(10), None).expect("min").1,
            Duration::from_millis(10)
        );
        assert!(watch_request(req(9), None).is_err());
        assert!(watch_request(req(MAX_WATCH_INTERVAL_MS + 1), None).is_err());
    }

    #[test]
    fn per_pair_tables_skip_unavailable_pairs() {
        let t = pair_values(vec![vec![None, Some(1.0)], vec![Some(2.0), None]]);
        let got: Vec<_> = t
            .pairs
            .iter()
            .map(|p| (p.state, p.action, p.value))
            .collect();
        assert_eq!(got, vec![(0, 1, 1.0), (1, 0, 2.0)]);
    }
}
