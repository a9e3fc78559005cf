from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class OutOfBounds(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    OUT_OF_BOUNDS_UNSPECIFIED: _ClassVar[OutOfBounds]
    OUT_OF_BOUNDS_CLIP: _ClassVar[OutOfBounds]
    OUT_OF_BOUNDS_REFUSE: _ClassVar[OutOfBounds]

class Optimism(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    OPTIMISM_UNSPECIFIED: _ClassVar[Optimism]
    OPTIMISM_ABSORBING: _ClassVar[Optimism]
    OPTIMISM_STIMULUS: _ClassVar[Optimism]

class UpdateMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    UPDATE_MODE_UNSPECIFIED: _ClassVar[UpdateMode]
    UPDATE_MODE_LOCKSTEP: _ClassVar[UpdateMode]
    UPDATE_MODE_ASYNC: _ClassVar[UpdateMode]

class StimulusRateRule(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STIMULUS_RATE_RULE_UNSPECIFIED: _ClassVar[StimulusRateRule]
    STIMULUS_RATE_RULE_SAMPLE_MEAN: _ClassVar[StimulusRateRule]
OUT_OF_BOUNDS_UNSPECIFIED: OutOfBounds
OUT_OF_BOUNDS_CLIP: OutOfBounds
OUT_OF_BOUNDS_REFUSE: OutOfBounds
OPTIMISM_UNSPECIFIED: Optimism
OPTIMISM_ABSORBING: Optimism
OPTIMISM_STIMULUS: Optimism
UPDATE_MODE_UNSPECIFIED: UpdateMode
UPDATE_MODE_LOCKSTEP: UpdateMode
UPDATE_MODE_ASYNC: UpdateMode
STIMULUS_RATE_RULE_UNSPECIFIED: StimulusRateRule
STIMULUS_RATE_RULE_SAMPLE_MEAN: StimulusRateRule

class CreateSessionRequest(_message.Message):
    __slots__ = ("model_json", "agent", "model")
    MODEL_JSON_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    model_json: str
    agent: SessionConfig
    model: Model
    def __init__(self, model_json: _Optional[str] = ..., agent: _Optional[_Union[SessionConfig, _Mapping]] = ..., model: _Optional[_Union[Model, _Mapping]] = ...) -> None: ...

class Model(_message.Message):
    __slots__ = ("preset", "grid", "full", "continuous")
    PRESET_FIELD_NUMBER: _ClassVar[int]
    GRID_FIELD_NUMBER: _ClassVar[int]
    FULL_FIELD_NUMBER: _ClassVar[int]
    CONTINUOUS_FIELD_NUMBER: _ClassVar[int]
    preset: PresetModel
    grid: GridModel
    full: FullModel
    continuous: ContinuousModel
    def __init__(self, preset: _Optional[_Union[PresetModel, _Mapping]] = ..., grid: _Optional[_Union[GridModel, _Mapping]] = ..., full: _Optional[_Union[FullModel, _Mapping]] = ..., continuous: _Optional[_Union[ContinuousModel, _Mapping]] = ...) -> None: ...

class ContinuousModel(_message.Message):
    __slots__ = ("low", "high", "actions", "stimuli", "basis", "out_of_bounds", "samples")
    LOW_FIELD_NUMBER: _ClassVar[int]
    HIGH_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    BASIS_FIELD_NUMBER: _ClassVar[int]
    OUT_OF_BOUNDS_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    low: _containers.RepeatedScalarFieldContainer[float]
    high: _containers.RepeatedScalarFieldContainer[float]
    actions: _containers.RepeatedScalarFieldContainer[str]
    stimuli: _containers.RepeatedScalarFieldContainer[str]
    basis: ContinuousBasis
    out_of_bounds: OutOfBounds
    samples: SampleParams
    def __init__(self, low: _Optional[_Iterable[float]] = ..., high: _Optional[_Iterable[float]] = ..., actions: _Optional[_Iterable[str]] = ..., stimuli: _Optional[_Iterable[str]] = ..., basis: _Optional[_Union[ContinuousBasis, _Mapping]] = ..., out_of_bounds: _Optional[_Union[OutOfBounds, str]] = ..., samples: _Optional[_Union[SampleParams, _Mapping]] = ...) -> None: ...

class ContinuousBasis(_message.Message):
    __slots__ = ("fourier", "rbf", "tiles", "pvf", "grid")
    FOURIER_FIELD_NUMBER: _ClassVar[int]
    RBF_FIELD_NUMBER: _ClassVar[int]
    TILES_FIELD_NUMBER: _ClassVar[int]
    PVF_FIELD_NUMBER: _ClassVar[int]
    GRID_FIELD_NUMBER: _ClassVar[int]
    fourier: FourierBasis
    rbf: RbfBasis
    tiles: TileBasis
    pvf: NystromPvfBasis
    grid: GridBasis
    def __init__(self, fourier: _Optional[_Union[FourierBasis, _Mapping]] = ..., rbf: _Optional[_Union[RbfBasis, _Mapping]] = ..., tiles: _Optional[_Union[TileBasis, _Mapping]] = ..., pvf: _Optional[_Union[NystromPvfBasis, _Mapping]] = ..., grid: _Optional[_Union[GridBasis, _Mapping]] = ...) -> None: ...

class GridBasis(_message.Message):
    __slots__ = ("cells_per_dim", "neighbours", "reach")
    CELLS_PER_DIM_FIELD_NUMBER: _ClassVar[int]
    NEIGHBOURS_FIELD_NUMBER: _ClassVar[int]
    REACH_FIELD_NUMBER: _ClassVar[int]
    cells_per_dim: int
    neighbours: int
    reach: float
    def __init__(self, cells_per_dim: _Optional[int] = ..., neighbours: _Optional[int] = ..., reach: _Optional[float] = ...) -> None: ...

class NystromPvfBasis(_message.Message):
    __slots__ = ("k", "nodes", "neighbours")
    K_FIELD_NUMBER: _ClassVar[int]
    NODES_FIELD_NUMBER: _ClassVar[int]
    NEIGHBOURS_FIELD_NUMBER: _ClassVar[int]
    k: int
    nodes: int
    neighbours: int
    def __init__(self, k: _Optional[int] = ..., nodes: _Optional[int] = ..., neighbours: _Optional[int] = ...) -> None: ...

class FourierBasis(_message.Message):
    __slots__ = ("order", "max_coupling")
    ORDER_FIELD_NUMBER: _ClassVar[int]
    MAX_COUPLING_FIELD_NUMBER: _ClassVar[int]
    order: int
    max_coupling: int
    def __init__(self, order: _Optional[int] = ..., max_coupling: _Optional[int] = ...) -> None: ...

class RbfBasis(_message.Message):
    __slots__ = ("centres_per_dim", "width")
    CENTRES_PER_DIM_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    centres_per_dim: int
    width: float
    def __init__(self, centres_per_dim: _Optional[int] = ..., width: _Optional[float] = ...) -> None: ...

class TileBasis(_message.Message):
    __slots__ = ("tilings", "tiles_per_dim", "table")
    TILINGS_FIELD_NUMBER: _ClassVar[int]
    TILES_PER_DIM_FIELD_NUMBER: _ClassVar[int]
    TABLE_FIELD_NUMBER: _ClassVar[int]
    tilings: int
    tiles_per_dim: int
    table: int
    def __init__(self, tilings: _Optional[int] = ..., tiles_per_dim: _Optional[int] = ..., table: _Optional[int] = ...) -> None: ...

class SampleParams(_message.Message):
    __slots__ = ("cells_per_dim", "per_cell", "max", "known_after")
    CELLS_PER_DIM_FIELD_NUMBER: _ClassVar[int]
    PER_CELL_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    KNOWN_AFTER_FIELD_NUMBER: _ClassVar[int]
    cells_per_dim: int
    per_cell: int
    max: int
    known_after: int
    def __init__(self, cells_per_dim: _Optional[int] = ..., per_cell: _Optional[int] = ..., max: _Optional[int] = ..., known_after: _Optional[int] = ...) -> None: ...

class PresetModel(_message.Message):
    __slots__ = ("name", "basis")
    NAME_FIELD_NUMBER: _ClassVar[int]
    BASIS_FIELD_NUMBER: _ClassVar[int]
    name: str
    basis: Basis
    def __init__(self, name: _Optional[str] = ..., basis: _Optional[_Union[Basis, _Mapping]] = ...) -> None: ...

class GridModel(_message.Message):
    __slots__ = ("rows", "sources", "stimuli", "basis", "learn", "learning")
    class SourcesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    ROWS_FIELD_NUMBER: _ClassVar[int]
    SOURCES_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    BASIS_FIELD_NUMBER: _ClassVar[int]
    LEARN_FIELD_NUMBER: _ClassVar[int]
    LEARNING_FIELD_NUMBER: _ClassVar[int]
    rows: _containers.RepeatedScalarFieldContainer[str]
    sources: _containers.ScalarMap[str, int]
    stimuli: _containers.RepeatedScalarFieldContainer[str]
    basis: Basis
    learn: bool
    learning: LearnedTransitions
    def __init__(self, rows: _Optional[_Iterable[str]] = ..., sources: _Optional[_Mapping[str, int]] = ..., stimuli: _Optional[_Iterable[str]] = ..., basis: _Optional[_Union[Basis, _Mapping]] = ..., learn: _Optional[bool] = ..., learning: _Optional[_Union[LearnedTransitions, _Mapping]] = ...) -> None: ...

class FullModel(_message.Message):
    __slots__ = ("states", "state_names", "actions", "stimuli", "next", "stochastic", "learn", "basis")
    STATES_FIELD_NUMBER: _ClassVar[int]
    STATE_NAMES_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    NEXT_FIELD_NUMBER: _ClassVar[int]
    STOCHASTIC_FIELD_NUMBER: _ClassVar[int]
    LEARN_FIELD_NUMBER: _ClassVar[int]
    BASIS_FIELD_NUMBER: _ClassVar[int]
    states: int
    state_names: _containers.RepeatedScalarFieldContainer[str]
    actions: _containers.RepeatedScalarFieldContainer[str]
    stimuli: _containers.RepeatedScalarFieldContainer[str]
    next: DeterministicTransitions
    stochastic: StochasticTransitions
    learn: LearnedTransitions
    basis: Basis
    def __init__(self, states: _Optional[int] = ..., state_names: _Optional[_Iterable[str]] = ..., actions: _Optional[_Iterable[str]] = ..., stimuli: _Optional[_Iterable[str]] = ..., next: _Optional[_Union[DeterministicTransitions, _Mapping]] = ..., stochastic: _Optional[_Union[StochasticTransitions, _Mapping]] = ..., learn: _Optional[_Union[LearnedTransitions, _Mapping]] = ..., basis: _Optional[_Union[Basis, _Mapping]] = ...) -> None: ...

class LearnedTransitions(_message.Message):
    __slots__ = ("known_after", "optimism")
    KNOWN_AFTER_FIELD_NUMBER: _ClassVar[int]
    OPTIMISM_FIELD_NUMBER: _ClassVar[int]
    known_after: int
    optimism: Optimism
    def __init__(self, known_after: _Optional[int] = ..., optimism: _Optional[_Union[Optimism, str]] = ...) -> None: ...

class DeterministicTransitions(_message.Message):
    __slots__ = ("rows",)
    ROWS_FIELD_NUMBER: _ClassVar[int]
    rows: _containers.RepeatedCompositeFieldContainer[NextRow]
    def __init__(self, rows: _Optional[_Iterable[_Union[NextRow, _Mapping]]] = ...) -> None: ...

class NextRow(_message.Message):
    __slots__ = ("next",)
    NEXT_FIELD_NUMBER: _ClassVar[int]
    next: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, next: _Optional[_Iterable[int]] = ...) -> None: ...

class StochasticTransitions(_message.Message):
    __slots__ = ("transitions",)
    TRANSITIONS_FIELD_NUMBER: _ClassVar[int]
    transitions: _containers.RepeatedCompositeFieldContainer[Transition]
    def __init__(self, transitions: _Optional[_Iterable[_Union[Transition, _Mapping]]] = ...) -> None: ...

class Transition(_message.Message):
    __slots__ = ("state", "action_index", "action_name", "next")
    STATE_FIELD_NUMBER: _ClassVar[int]
    ACTION_INDEX_FIELD_NUMBER: _ClassVar[int]
    ACTION_NAME_FIELD_NUMBER: _ClassVar[int]
    NEXT_FIELD_NUMBER: _ClassVar[int]
    state: int
    action_index: int
    action_name: str
    next: _containers.RepeatedCompositeFieldContainer[Successor]
    def __init__(self, state: _Optional[int] = ..., action_index: _Optional[int] = ..., action_name: _Optional[str] = ..., next: _Optional[_Iterable[_Union[Successor, _Mapping]]] = ...) -> None: ...

class Successor(_message.Message):
    __slots__ = ("state", "probability")
    STATE_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    state: int
    probability: float
    def __init__(self, state: _Optional[int] = ..., probability: _Optional[float] = ...) -> None: ...

class Basis(_message.Message):
    __slots__ = ("indicator", "proto_value", "custom")
    INDICATOR_FIELD_NUMBER: _ClassVar[int]
    PROTO_VALUE_FIELD_NUMBER: _ClassVar[int]
    CUSTOM_FIELD_NUMBER: _ClassVar[int]
    indicator: IndicatorBasis
    proto_value: ProtoValueBasis
    custom: CustomBasis
    def __init__(self, indicator: _Optional[_Union[IndicatorBasis, _Mapping]] = ..., proto_value: _Optional[_Union[ProtoValueBasis, _Mapping]] = ..., custom: _Optional[_Union[CustomBasis, _Mapping]] = ...) -> None: ...

class IndicatorBasis(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ProtoValueBasis(_message.Message):
    __slots__ = ("k",)
    K_FIELD_NUMBER: _ClassVar[int]
    k: int
    def __init__(self, k: _Optional[int] = ...) -> None: ...

class CustomBasis(_message.Message):
    __slots__ = ("state_features",)
    STATE_FEATURES_FIELD_NUMBER: _ClassVar[int]
    state_features: _containers.RepeatedCompositeFieldContainer[FeatureRow]
    def __init__(self, state_features: _Optional[_Iterable[_Union[FeatureRow, _Mapping]]] = ...) -> None: ...

class FeatureRow(_message.Message):
    __slots__ = ("features",)
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    features: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, features: _Optional[_Iterable[float]] = ...) -> None: ...

class SessionConfig(_message.Message):
    __slots__ = ("eta", "gamma", "priorities", "stimulus_rate_rule", "stimulus_rate_constant", "optimistic_sd", "ridge", "epsilon", "seed", "update_mode", "history", "curiosity")
    ETA_FIELD_NUMBER: _ClassVar[int]
    GAMMA_FIELD_NUMBER: _ClassVar[int]
    PRIORITIES_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_RATE_RULE_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_RATE_CONSTANT_FIELD_NUMBER: _ClassVar[int]
    OPTIMISTIC_SD_FIELD_NUMBER: _ClassVar[int]
    RIDGE_FIELD_NUMBER: _ClassVar[int]
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    UPDATE_MODE_FIELD_NUMBER: _ClassVar[int]
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    eta: float
    gamma: float
    priorities: _containers.RepeatedScalarFieldContainer[float]
    stimulus_rate_rule: StimulusRateRule
    stimulus_rate_constant: float
    optimistic_sd: float
    ridge: float
    epsilon: float
    seed: int
    update_mode: UpdateMode
    history: int
    curiosity: CuriosityConfig
    def __init__(self, eta: _Optional[float] = ..., gamma: _Optional[float] = ..., priorities: _Optional[_Iterable[float]] = ..., stimulus_rate_rule: _Optional[_Union[StimulusRateRule, str]] = ..., stimulus_rate_constant: _Optional[float] = ..., optimistic_sd: _Optional[float] = ..., ridge: _Optional[float] = ..., epsilon: _Optional[float] = ..., seed: _Optional[int] = ..., update_mode: _Optional[_Union[UpdateMode, str]] = ..., history: _Optional[int] = ..., curiosity: _Optional[_Union[CuriosityConfig, _Mapping]] = ...) -> None: ...

class CuriosityConfig(_message.Message):
    __slots__ = ("signal_dim", "params_json")
    SIGNAL_DIM_FIELD_NUMBER: _ClassVar[int]
    PARAMS_JSON_FIELD_NUMBER: _ClassVar[int]
    signal_dim: int
    params_json: str
    def __init__(self, signal_dim: _Optional[int] = ..., params_json: _Optional[str] = ...) -> None: ...

class EffectiveConfig(_message.Message):
    __slots__ = ("eta", "gamma", "priorities", "stimulus_rate_rule", "stimulus_rate_constant", "optimistic_sd", "ridge", "epsilon", "seed", "update_mode", "history", "curiosity")
    ETA_FIELD_NUMBER: _ClassVar[int]
    GAMMA_FIELD_NUMBER: _ClassVar[int]
    PRIORITIES_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_RATE_RULE_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_RATE_CONSTANT_FIELD_NUMBER: _ClassVar[int]
    OPTIMISTIC_SD_FIELD_NUMBER: _ClassVar[int]
    RIDGE_FIELD_NUMBER: _ClassVar[int]
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    UPDATE_MODE_FIELD_NUMBER: _ClassVar[int]
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    eta: float
    gamma: float
    priorities: _containers.RepeatedScalarFieldContainer[float]
    stimulus_rate_rule: StimulusRateRule
    stimulus_rate_constant: float
    optimistic_sd: float
    ridge: float
    epsilon: float
    seed: int
    update_mode: UpdateMode
    history: int
    curiosity: CuriosityConfig
    def __init__(self, eta: _Optional[float] = ..., gamma: _Optional[float] = ..., priorities: _Optional[_Iterable[float]] = ..., stimulus_rate_rule: _Optional[_Union[StimulusRateRule, str]] = ..., stimulus_rate_constant: _Optional[float] = ..., optimistic_sd: _Optional[float] = ..., ridge: _Optional[float] = ..., epsilon: _Optional[float] = ..., seed: _Optional[int] = ..., update_mode: _Optional[_Union[UpdateMode, str]] = ..., history: _Optional[int] = ..., curiosity: _Optional[_Union[CuriosityConfig, _Mapping]] = ...) -> None: ...

class BasisSummary(_message.Message):
    __slots__ = ("kind", "k")
    KIND_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    kind: str
    k: int
    def __init__(self, kind: _Optional[str] = ..., k: _Optional[int] = ...) -> None: ...

class ModelSummary(_message.Message):
    __slots__ = ("states", "actions", "stimuli", "pairs", "transitions", "deterministic", "basis", "features", "layout", "learned", "continuous")
    STATES_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    PAIRS_FIELD_NUMBER: _ClassVar[int]
    TRANSITIONS_FIELD_NUMBER: _ClassVar[int]
    DETERMINISTIC_FIELD_NUMBER: _ClassVar[int]
    BASIS_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    LAYOUT_FIELD_NUMBER: _ClassVar[int]
    LEARNED_FIELD_NUMBER: _ClassVar[int]
    CONTINUOUS_FIELD_NUMBER: _ClassVar[int]
    states: int
    actions: _containers.RepeatedScalarFieldContainer[str]
    stimuli: _containers.RepeatedScalarFieldContainer[str]
    pairs: int
    transitions: int
    deterministic: bool
    basis: BasisSummary
    features: int
    layout: GridLayout
    learned: LearnedSummary
    continuous: ContinuousModel
    def __init__(self, states: _Optional[int] = ..., actions: _Optional[_Iterable[str]] = ..., stimuli: _Optional[_Iterable[str]] = ..., pairs: _Optional[int] = ..., transitions: _Optional[int] = ..., deterministic: _Optional[bool] = ..., basis: _Optional[_Union[BasisSummary, _Mapping]] = ..., features: _Optional[int] = ..., layout: _Optional[_Union[GridLayout, _Mapping]] = ..., learned: _Optional[_Union[LearnedSummary, _Mapping]] = ..., continuous: _Optional[_Union[ContinuousModel, _Mapping]] = ...) -> None: ...

class LearnedSummary(_message.Message):
    __slots__ = ("known_after", "optimism", "max_transitions")
    KNOWN_AFTER_FIELD_NUMBER: _ClassVar[int]
    OPTIMISM_FIELD_NUMBER: _ClassVar[int]
    MAX_TRANSITIONS_FIELD_NUMBER: _ClassVar[int]
    known_after: int
    optimism: Optimism
    max_transitions: int
    def __init__(self, known_after: _Optional[int] = ..., optimism: _Optional[_Union[Optimism, str]] = ..., max_transitions: _Optional[int] = ...) -> None: ...

class GridLayout(_message.Message):
    __slots__ = ("rows", "cols", "cells", "marks")
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    CELLS_FIELD_NUMBER: _ClassVar[int]
    MARKS_FIELD_NUMBER: _ClassVar[int]
    rows: int
    cols: int
    cells: _containers.RepeatedCompositeFieldContainer[GridCell]
    marks: _containers.RepeatedCompositeFieldContainer[GridMark]
    def __init__(self, rows: _Optional[int] = ..., cols: _Optional[int] = ..., cells: _Optional[_Iterable[_Union[GridCell, _Mapping]]] = ..., marks: _Optional[_Iterable[_Union[GridMark, _Mapping]]] = ...) -> None: ...

class GridCell(_message.Message):
    __slots__ = ("row", "col")
    ROW_FIELD_NUMBER: _ClassVar[int]
    COL_FIELD_NUMBER: _ClassVar[int]
    row: int
    col: int
    def __init__(self, row: _Optional[int] = ..., col: _Optional[int] = ...) -> None: ...

class GridMark(_message.Message):
    __slots__ = ("mark", "state")
    MARK_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    mark: str
    state: int
    def __init__(self, mark: _Optional[str] = ..., state: _Optional[int] = ...) -> None: ...

class SessionStats(_message.Message):
    __slots__ = ("lstdq_error", "lambda1_estimate", "condition_1_holds", "constant_stimuli", "factorisation_reuses", "factorisations", "continuous")
    LSTDQ_ERROR_FIELD_NUMBER: _ClassVar[int]
    LAMBDA1_ESTIMATE_FIELD_NUMBER: _ClassVar[int]
    CONDITION_1_HOLDS_FIELD_NUMBER: _ClassVar[int]
    CONSTANT_STIMULI_FIELD_NUMBER: _ClassVar[int]
    FACTORISATION_REUSES_FIELD_NUMBER: _ClassVar[int]
    FACTORISATIONS_FIELD_NUMBER: _ClassVar[int]
    CONTINUOUS_FIELD_NUMBER: _ClassVar[int]
    lstdq_error: float
    lambda1_estimate: float
    condition_1_holds: bool
    constant_stimuli: _containers.RepeatedScalarFieldContainer[int]
    factorisation_reuses: int
    factorisations: int
    continuous: ContinuousStats
    def __init__(self, lstdq_error: _Optional[float] = ..., lambda1_estimate: _Optional[float] = ..., condition_1_holds: _Optional[bool] = ..., constant_stimuli: _Optional[_Iterable[int]] = ..., factorisation_reuses: _Optional[int] = ..., factorisations: _Optional[int] = ..., continuous: _Optional[_Union[ContinuousStats, _Mapping]] = ...) -> None: ...

class ContinuousStats(_message.Message):
    __slots__ = ("clipped", "samples", "slots", "updates", "rebuilds", "basis_builds")
    CLIPPED_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    SLOTS_FIELD_NUMBER: _ClassVar[int]
    UPDATES_FIELD_NUMBER: _ClassVar[int]
    REBUILDS_FIELD_NUMBER: _ClassVar[int]
    BASIS_BUILDS_FIELD_NUMBER: _ClassVar[int]
    clipped: int
    samples: int
    slots: int
    updates: int
    rebuilds: int
    basis_builds: int
    def __init__(self, clipped: _Optional[int] = ..., samples: _Optional[int] = ..., slots: _Optional[int] = ..., updates: _Optional[int] = ..., rebuilds: _Optional[int] = ..., basis_builds: _Optional[int] = ...) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("id", "tick", "drive", "policy_version", "state", "model", "agent", "stats", "curiosity", "cost", "next_seq")
    ID_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    DRIVE_FIELD_NUMBER: _ClassVar[int]
    POLICY_VERSION_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    STATS_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    NEXT_SEQ_FIELD_NUMBER: _ClassVar[int]
    id: str
    tick: int
    drive: _containers.RepeatedScalarFieldContainer[float]
    policy_version: int
    state: int
    model: ModelSummary
    agent: EffectiveConfig
    stats: SessionStats
    curiosity: CuriosityInfo
    cost: SessionCost
    next_seq: int
    def __init__(self, id: _Optional[str] = ..., tick: _Optional[int] = ..., drive: _Optional[_Iterable[float]] = ..., policy_version: _Optional[int] = ..., state: _Optional[int] = ..., model: _Optional[_Union[ModelSummary, _Mapping]] = ..., agent: _Optional[_Union[EffectiveConfig, _Mapping]] = ..., stats: _Optional[_Union[SessionStats, _Mapping]] = ..., curiosity: _Optional[_Union[CuriosityInfo, _Mapping]] = ..., cost: _Optional[_Union[SessionCost, _Mapping]] = ..., next_seq: _Optional[int] = ...) -> None: ...

class SessionCost(_message.Message):
    __slots__ = ("bytes", "tick_us")
    BYTES_FIELD_NUMBER: _ClassVar[int]
    TICK_US_FIELD_NUMBER: _ClassVar[int]
    bytes: int
    tick_us: int
    def __init__(self, bytes: _Optional[int] = ..., tick_us: _Optional[int] = ...) -> None: ...

class CuriosityInfo(_message.Message):
    __slots__ = ("samples", "epsilon", "active_source", "active_samples", "all_explained", "modules")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    ACTIVE_SOURCE_FIELD_NUMBER: _ClassVar[int]
    ACTIVE_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    ALL_EXPLAINED_FIELD_NUMBER: _ClassVar[int]
    MODULES_FIELD_NUMBER: _ClassVar[int]
    samples: int
    epsilon: float
    active_source: int
    active_samples: int
    all_explained: bool
    modules: _containers.RepeatedCompositeFieldContainer[FrozenModule]
    def __init__(self, samples: _Optional[int] = ..., epsilon: _Optional[float] = ..., active_source: _Optional[int] = ..., active_samples: _Optional[int] = ..., all_explained: _Optional[bool] = ..., modules: _Optional[_Iterable[_Union[FrozenModule, _Mapping]]] = ...) -> None: ...

class FrozenModule(_message.Message):
    __slots__ = ("source", "frozen_tick", "learned_samples")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    FROZEN_TICK_FIELD_NUMBER: _ClassVar[int]
    LEARNED_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    source: int
    frozen_tick: int
    learned_samples: int
    def __init__(self, source: _Optional[int] = ..., frozen_tick: _Optional[int] = ..., learned_samples: _Optional[int] = ...) -> None: ...

class TickCuriosity(_message.Message):
    __slots__ = ("xi_cur", "epsilon", "modules", "source")
    XI_CUR_FIELD_NUMBER: _ClassVar[int]
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    MODULES_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    xi_cur: float
    epsilon: float
    modules: int
    source: int
    def __init__(self, xi_cur: _Optional[float] = ..., epsilon: _Optional[float] = ..., modules: _Optional[int] = ..., source: _Optional[int] = ...) -> None: ...

class GetSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class ListSessionsRequest(_message.Message):
    __slots__ = ("after", "limit")
    AFTER_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    after: str
    limit: int
    def __init__(self, after: _Optional[str] = ..., limit: _Optional[int] = ...) -> None: ...

class SessionSummary(_message.Message):
    __slots__ = ("id", "tick", "states", "update_mode", "idle_ms")
    ID_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    UPDATE_MODE_FIELD_NUMBER: _ClassVar[int]
    IDLE_MS_FIELD_NUMBER: _ClassVar[int]
    id: str
    tick: int
    states: int
    update_mode: UpdateMode
    idle_ms: int
    def __init__(self, id: _Optional[str] = ..., tick: _Optional[int] = ..., states: _Optional[int] = ..., update_mode: _Optional[_Union[UpdateMode, str]] = ..., idle_ms: _Optional[int] = ...) -> None: ...

class ListSessionsResponse(_message.Message):
    __slots__ = ("sessions", "next")
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    NEXT_FIELD_NUMBER: _ClassVar[int]
    sessions: _containers.RepeatedCompositeFieldContainer[SessionSummary]
    next: str
    def __init__(self, sessions: _Optional[_Iterable[_Union[SessionSummary, _Mapping]]] = ..., next: _Optional[str] = ...) -> None: ...

class DeleteSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class DeleteSessionResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Stimulus(_message.Message):
    __slots__ = ("values",)
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, values: _Optional[_Iterable[float]] = ...) -> None: ...

class Observation(_message.Message):
    __slots__ = ("session_id", "state", "stimulus", "action_name", "action_index", "signal", "signal_source", "observation", "seq")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_FIELD_NUMBER: _ClassVar[int]
    ACTION_NAME_FIELD_NUMBER: _ClassVar[int]
    ACTION_INDEX_FIELD_NUMBER: _ClassVar[int]
    SIGNAL_FIELD_NUMBER: _ClassVar[int]
    SIGNAL_SOURCE_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    state: int
    stimulus: Stimulus
    action_name: str
    action_index: int
    signal: _containers.RepeatedScalarFieldContainer[float]
    signal_source: int
    observation: _containers.RepeatedScalarFieldContainer[float]
    seq: int
    def __init__(self, session_id: _Optional[str] = ..., state: _Optional[int] = ..., stimulus: _Optional[_Union[Stimulus, _Mapping]] = ..., action_name: _Optional[str] = ..., action_index: _Optional[int] = ..., signal: _Optional[_Iterable[float]] = ..., signal_source: _Optional[int] = ..., observation: _Optional[_Iterable[float]] = ..., seq: _Optional[int] = ...) -> None: ...

class Step(_message.Message):
    __slots__ = ("tick", "action", "action_index", "drive", "reward", "policy_version", "curiosity", "replayed")
    TICK_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    ACTION_INDEX_FIELD_NUMBER: _ClassVar[int]
    DRIVE_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    POLICY_VERSION_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    REPLAYED_FIELD_NUMBER: _ClassVar[int]
    tick: int
    action: str
    action_index: int
    drive: _containers.RepeatedScalarFieldContainer[float]
    reward: float
    policy_version: int
    curiosity: TickCuriosity
    replayed: bool
    def __init__(self, tick: _Optional[int] = ..., action: _Optional[str] = ..., action_index: _Optional[int] = ..., drive: _Optional[_Iterable[float]] = ..., reward: _Optional[float] = ..., policy_version: _Optional[int] = ..., curiosity: _Optional[_Union[TickCuriosity, _Mapping]] = ..., replayed: _Optional[bool] = ...) -> None: ...

class ObservationBatch(_message.Message):
    __slots__ = ("observations",)
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    observations: _containers.RepeatedCompositeFieldContainer[Observation]
    def __init__(self, observations: _Optional[_Iterable[_Union[Observation, _Mapping]]] = ...) -> None: ...

class StepBatch(_message.Message):
    __slots__ = ("results",)
    RESULTS_FIELD_NUMBER: _ClassVar[int]
    results: _containers.RepeatedCompositeFieldContainer[StepResult]
    def __init__(self, results: _Optional[_Iterable[_Union[StepResult, _Mapping]]] = ...) -> None: ...

class StepResult(_message.Message):
    __slots__ = ("step", "error")
    STEP_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    step: Step
    error: StepError
    def __init__(self, step: _Optional[_Union[Step, _Mapping]] = ..., error: _Optional[_Union[StepError, _Mapping]] = ...) -> None: ...

class StepError(_message.Message):
    __slots__ = ("status", "code", "message", "owner")
    STATUS_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    OWNER_FIELD_NUMBER: _ClassVar[int]
    status: int
    code: str
    message: str
    owner: str
    def __init__(self, status: _Optional[int] = ..., code: _Optional[str] = ..., message: _Optional[str] = ..., owner: _Optional[str] = ...) -> None: ...

class ObserveRequest(_message.Message):
    __slots__ = ("session_id", "observations")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    observations: _containers.RepeatedCompositeFieldContainer[Observation]
    def __init__(self, session_id: _Optional[str] = ..., observations: _Optional[_Iterable[_Union[Observation, _Mapping]]] = ...) -> None: ...

class ObserveResponse(_message.Message):
    __slots__ = ("steps",)
    STEPS_FIELD_NUMBER: _ClassVar[int]
    steps: _containers.RepeatedCompositeFieldContainer[Step]
    def __init__(self, steps: _Optional[_Iterable[_Union[Step, _Mapping]]] = ...) -> None: ...

class WatchRequest(_message.Message):
    __slots__ = ("session_id", "interval_ms")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    INTERVAL_MS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    interval_ms: int
    def __init__(self, session_id: _Optional[str] = ..., interval_ms: _Optional[int] = ...) -> None: ...

class GetValuesRequest(_message.Message):
    __slots__ = ("session_id", "include")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    INCLUDE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    include: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, session_id: _Optional[str] = ..., include: _Optional[_Iterable[str]] = ...) -> None: ...

class StateValues(_message.Message):
    __slots__ = ("values",)
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, values: _Optional[_Iterable[float]] = ...) -> None: ...

class Policy(_message.Message):
    __slots__ = ("actions",)
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    actions: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, actions: _Optional[_Iterable[str]] = ...) -> None: ...

class PairValue(_message.Message):
    __slots__ = ("state", "action", "value")
    STATE_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    state: int
    action: int
    value: float
    def __init__(self, state: _Optional[int] = ..., action: _Optional[int] = ..., value: _Optional[float] = ...) -> None: ...

class PairValues(_message.Message):
    __slots__ = ("pairs",)
    PAIRS_FIELD_NUMBER: _ClassVar[int]
    pairs: _containers.RepeatedCompositeFieldContainer[PairValue]
    def __init__(self, pairs: _Optional[_Iterable[_Union[PairValue, _Mapping]]] = ...) -> None: ...

class PairVector(_message.Message):
    __slots__ = ("state", "action", "values")
    STATE_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    state: int
    action: int
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, state: _Optional[int] = ..., action: _Optional[int] = ..., values: _Optional[_Iterable[float]] = ...) -> None: ...

class PairVectors(_message.Message):
    __slots__ = ("pairs",)
    PAIRS_FIELD_NUMBER: _ClassVar[int]
    pairs: _containers.RepeatedCompositeFieldContainer[PairVector]
    def __init__(self, pairs: _Optional[_Iterable[_Union[PairVector, _Mapping]]] = ...) -> None: ...

class Values(_message.Message):
    __slots__ = ("tick", "policy_version", "v", "q", "policy", "r", "xi", "curiosity", "known_fraction", "points")
    TICK_FIELD_NUMBER: _ClassVar[int]
    POLICY_VERSION_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    POLICY_FIELD_NUMBER: _ClassVar[int]
    R_FIELD_NUMBER: _ClassVar[int]
    XI_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    KNOWN_FRACTION_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    tick: int
    policy_version: int
    v: StateValues
    q: PairValues
    policy: Policy
    r: PairValues
    xi: PairVectors
    curiosity: CuriosityInfo
    known_fraction: float
    points: _containers.RepeatedCompositeFieldContainer[Point]
    def __init__(self, tick: _Optional[int] = ..., policy_version: _Optional[int] = ..., v: _Optional[_Union[StateValues, _Mapping]] = ..., q: _Optional[_Union[PairValues, _Mapping]] = ..., policy: _Optional[_Union[Policy, _Mapping]] = ..., r: _Optional[_Union[PairValues, _Mapping]] = ..., xi: _Optional[_Union[PairVectors, _Mapping]] = ..., curiosity: _Optional[_Union[CuriosityInfo, _Mapping]] = ..., known_fraction: _Optional[float] = ..., points: _Optional[_Iterable[_Union[Point, _Mapping]]] = ...) -> None: ...

class Point(_message.Message):
    __slots__ = ("x",)
    X_FIELD_NUMBER: _ClassVar[int]
    x: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, x: _Optional[_Iterable[float]] = ...) -> None: ...

class GetHistoryRequest(_message.Message):
    __slots__ = ("session_id", "limit")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    limit: int
    def __init__(self, session_id: _Optional[str] = ..., limit: _Optional[int] = ...) -> None: ...

class HistoryEntry(_message.Message):
    __slots__ = ("tick", "state", "action_index", "drive", "reward", "lstdq_error", "stimulus", "curiosity", "known_fraction", "observation")
    TICK_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    ACTION_INDEX_FIELD_NUMBER: _ClassVar[int]
    DRIVE_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    LSTDQ_ERROR_FIELD_NUMBER: _ClassVar[int]
    STIMULUS_FIELD_NUMBER: _ClassVar[int]
    CURIOSITY_FIELD_NUMBER: _ClassVar[int]
    KNOWN_FRACTION_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    tick: int
    state: int
    action_index: int
    drive: _containers.RepeatedScalarFieldContainer[float]
    reward: float
    lstdq_error: float
    stimulus: Stimulus
    curiosity: TickCuriosity
    known_fraction: float
    observation: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, tick: _Optional[int] = ..., state: _Optional[int] = ..., action_index: _Optional[int] = ..., drive: _Optional[_Iterable[float]] = ..., reward: _Optional[float] = ..., lstdq_error: _Optional[float] = ..., stimulus: _Optional[_Union[Stimulus, _Mapping]] = ..., curiosity: _Optional[_Union[TickCuriosity, _Mapping]] = ..., known_fraction: _Optional[float] = ..., observation: _Optional[_Iterable[float]] = ...) -> None: ...

class History(_message.Message):
    __slots__ = ("entries",)
    ENTRIES_FIELD_NUMBER: _ClassVar[int]
    entries: _containers.RepeatedCompositeFieldContainer[HistoryEntry]
    def __init__(self, entries: _Optional[_Iterable[_Union[HistoryEntry, _Mapping]]] = ...) -> None: ...

class CreateGroupRequest(_message.Message):
    __slots__ = ("model", "agent", "n", "seed")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    N_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    model: Model
    agent: SessionConfig
    n: int
    seed: int
    def __init__(self, model: _Optional[_Union[Model, _Mapping]] = ..., agent: _Optional[_Union[SessionConfig, _Mapping]] = ..., n: _Optional[int] = ..., seed: _Optional[int] = ...) -> None: ...

class GroupInfo(_message.Message):
    __slots__ = ("group_id", "size", "seed", "update_mode", "stimuli", "observation_dim", "member_ids")
    GROUP_ID_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    UPDATE_MODE_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_DIM_FIELD_NUMBER: _ClassVar[int]
    MEMBER_IDS_FIELD_NUMBER: _ClassVar[int]
    group_id: str
    size: int
    seed: int
    update_mode: UpdateMode
    stimuli: int
    observation_dim: int
    member_ids: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, group_id: _Optional[str] = ..., size: _Optional[int] = ..., seed: _Optional[int] = ..., update_mode: _Optional[_Union[UpdateMode, str]] = ..., stimuli: _Optional[int] = ..., observation_dim: _Optional[int] = ..., member_ids: _Optional[_Iterable[str]] = ...) -> None: ...

class GetGroupRequest(_message.Message):
    __slots__ = ("group_id",)
    GROUP_ID_FIELD_NUMBER: _ClassVar[int]
    group_id: str
    def __init__(self, group_id: _Optional[str] = ...) -> None: ...

class DeleteGroupRequest(_message.Message):
    __slots__ = ("group_id",)
    GROUP_ID_FIELD_NUMBER: _ClassVar[int]
    group_id: str
    def __init__(self, group_id: _Optional[str] = ...) -> None: ...

class DeleteGroupResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GroupStepRequest(_message.Message):
    __slots__ = ("group_id", "seq", "states", "observations", "stimuli", "action_taken", "mask", "seqs")
    GROUP_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    STIMULI_FIELD_NUMBER: _ClassVar[int]
    ACTION_TAKEN_FIELD_NUMBER: _ClassVar[int]
    MASK_FIELD_NUMBER: _ClassVar[int]
    SEQS_FIELD_NUMBER: _ClassVar[int]
    group_id: str
    seq: int
    states: _containers.RepeatedScalarFieldContainer[int]
    observations: bytes
    stimuli: bytes
    action_taken: _containers.RepeatedScalarFieldContainer[int]
    mask: _containers.RepeatedScalarFieldContainer[int]
    seqs: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, group_id: _Optional[str] = ..., seq: _Optional[int] = ..., states: _Optional[_Iterable[int]] = ..., observations: _Optional[bytes] = ..., stimuli: _Optional[bytes] = ..., action_taken: _Optional[_Iterable[int]] = ..., mask: _Optional[_Iterable[int]] = ..., seqs: _Optional[_Iterable[int]] = ...) -> None: ...

class GroupStepReply(_message.Message):
    __slots__ = ("seq", "actions", "drives", "rewards", "policy_versions", "statuses", "ticks", "replayed")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    DRIVES_FIELD_NUMBER: _ClassVar[int]
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    POLICY_VERSIONS_FIELD_NUMBER: _ClassVar[int]
    STATUSES_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    REPLAYED_FIELD_NUMBER: _ClassVar[int]
    seq: int
    actions: _containers.RepeatedScalarFieldContainer[int]
    drives: bytes
    rewards: bytes
    policy_versions: _containers.RepeatedScalarFieldContainer[int]
    statuses: _containers.RepeatedCompositeFieldContainer[MemberStatus]
    ticks: _containers.RepeatedScalarFieldContainer[int]
    replayed: _containers.RepeatedScalarFieldContainer[bool]
    def __init__(self, seq: _Optional[int] = ..., actions: _Optional[_Iterable[int]] = ..., drives: _Optional[bytes] = ..., rewards: _Optional[bytes] = ..., policy_versions: _Optional[_Iterable[int]] = ..., statuses: _Optional[_Iterable[_Union[MemberStatus, _Mapping]]] = ..., ticks: _Optional[_Iterable[int]] = ..., replayed: _Optional[_Iterable[bool]] = ...) -> None: ...

class MemberStatus(_message.Message):
    __slots__ = ("index", "status", "code", "message", "expected_seq", "oldest_seq")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_SEQ_FIELD_NUMBER: _ClassVar[int]
    OLDEST_SEQ_FIELD_NUMBER: _ClassVar[int]
    index: int
    status: int
    code: str
    message: str
    expected_seq: int
    oldest_seq: int
    def __init__(self, index: _Optional[int] = ..., status: _Optional[int] = ..., code: _Optional[str] = ..., message: _Optional[str] = ..., expected_seq: _Optional[int] = ..., oldest_seq: _Optional[int] = ...) -> None: ...
