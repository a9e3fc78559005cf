//! The one table of the agent's parameters and the one table of the
//! curiosity channel's constants. Each parameter is declared here once:
//! its name, kind and range, default, unit and a one-line doc.
//!
//! [`AgentParams::check`](super::AgentParams::check) and
//! [`CuriosityParams::check`](crate::CuriosityParams::check) validate
//! against these entries; the server builds its OpenAPI schema from them;
//! the tables of docs/sessions.md and the Python client's options are
//! generated from them, and the server's tests fail when the proto, the
//! OpenAPI document, the docs or the Python client disagree with them.
//! Adding a parameter: CONTRIBUTING.md, "Adding an agent parameter".

use super::spec::{Bound, Default, Kind, Max, Param};
use crate::curiosity::{MAX_CENTRES, MAX_SOURCES_LIMIT, MAX_WINDOW};
use crate::error::MAX_STIMULUS;

/// The smallest priority ρ: Λ = diag(1/ρ) then has entries of at most 1e6,
/// and with stimuli within ±[`MAX_STIMULUS`] every Λξ, reward and Q value
/// stays far from overflowing f64.
pub const MIN_PRIORITY: f64 = 1e-6;

/// The largest gain g of Eq. 7: g times a difference of errors stays
/// finite, and the clip bounds ξ_cur anyway.
pub const MAX_CURIOSITY_GAIN: f64 = 1e6;

/// The largest clip of ξ_cur in Eq. 7: the curiosity dimension the server
/// computes stays far inside the stimulus limit ([`MAX_STIMULUS`]) that a
/// client's own stimuli must keep.
pub const MAX_CURIOSITY_CLIP: f64 = 1e6;
const _: () = assert!(MAX_CURIOSITY_CLIP <= MAX_STIMULUS);

/// MCA learning rate η of Eq. 1; at most 0.5 by condition (1).
pub const ETA: Param = Param {
    name: "eta",
    kind: Kind::Real {
        lower: Bound::Excl(0.0),
        upper: Bound::Incl(0.5),
    },
    default: Default::Real(0.01),
    unit: "",
    doc: "MCA learning rate η of Eq. 1",
    see: "algorithm.md#23-drive-eqs-1-2-lines-6-7",
};

/// Discount γ.
pub const GAMMA: Param = Param {
    name: "gamma",
    kind: Kind::Real {
        lower: Bound::Incl(0.0),
        upper: Bound::Excl(1.0),
    },
    default: Default::Real(0.95),
    unit: "",
    doc: "discount γ",
    see: "",
};

/// Priorities ρ, one per stimulus dimension; Λ = diag(1/ρ). At least
/// [`MIN_PRIORITY`], so Λ's entries stay at most 1e6.
pub const PRIORITIES: Param = Param {
    name: "priorities",
    kind: Kind::PerStimulus {
        lower: Bound::Incl(MIN_PRIORITY),
        upper: Bound::Incl(1.0),
    },
    default: Default::AllOnes,
    unit: "",
    doc: "priorities ρ, one per stimulus dimension, a curiosity dimension included (Λ = diag(1/ρ))",
    see: "",
};

/// The learning rate of Ξ (Algorithm 1, line 5).
pub const STIMULUS_RATE: Param = Param {
    name: "stimulus_rate",
    kind: Kind::RealOrName {
        lower: Bound::Excl(0.0),
        upper: Bound::Incl(1.0),
        names: &["sample_mean"],
    },
    default: Default::Name("sample_mean"),
    unit: "",
    doc: "how Ξ learns: the sample mean of each pair, or a constant rate",
    see: "algorithm.md#22-stimulus-function-line-5",
};

/// σ of the optimistic initialisation Ξ ~ N(0, σ²); at most the largest
/// stimulus a client may send ([`MAX_STIMULUS`]), so Ξ starts on the scale
/// of what it will learn.
pub const OPTIMISTIC_SD: Param = Param {
    name: "optimistic_sd",
    kind: Kind::Real {
        lower: Bound::Incl(0.0),
        upper: Bound::Incl(MAX_STIMULUS),
    },
    default: Default::Real(0.3),
    unit: "",
    doc: "σ of the optimistic initial draw of Ξ",
    see: "algorithm.md#3-initialisation",
};

/// Ridge λ, added to A only when A is singular. The planner calls A
/// singular when a pivot of its LU factorisation is below 1e-12 of the
/// largest, so a smaller ridge could never make it regular; the upper end
/// keeps A + λI and its inverse finite.
pub const RIDGE: Param = Param {
    name: "ridge",
    kind: Kind::Real {
        lower: Bound::Incl(1e-12),
        upper: Bound::Incl(1e6),
    },
    default: Default::Real(1e-6),
    unit: "",
    doc: "ridge λ added to A only when A is singular",
    see: "algorithm.md#26-policy-update-line-9-and-the-next-action-line-10",
};

/// ε of ε-greedy exploration (our addition; off by default).
pub const EPSILON: Param = Param {
    name: "epsilon",
    kind: Kind::Real {
        lower: Bound::Incl(0.0),
        upper: Bound::Incl(1.0),
    },
    default: Default::Real(0.0),
    unit: "",
    doc: "ε of ε-greedy exploration",
    see: "",
};

/// Seed of the agent's ChaCha RNG.
pub const SEED: Param = Param {
    name: "seed",
    kind: Kind::Integer {
        min: 0,
        max: Max::Value(u64::MAX),
    },
    default: Default::Drawn,
    unit: "",
    doc: "seed of the session's RNG (returned, so a session can be made again)",
    see: "",
};

/// The agent's parameters, in the order of [`super::AgentParams`]'s fields.
pub const AGENT_PARAMS: [Param; 8] = [
    ETA,
    GAMMA,
    PRIORITIES,
    STIMULUS_RATE,
    OPTIMISTIC_SD,
    RIDGE,
    EPSILON,
    SEED,
];

const fn real(
    name: &'static str,
    lower: Bound,
    upper: Bound,
    default: f64,
    doc: &'static str,
) -> Param {
    Param {
        name,
        kind: Kind::Real { lower, upper },
        default: Default::Real(default),
        unit: "",
        doc,
        see: "",
    }
}

const fn integer(
    name: &'static str,
    min: u64,
    max: Max,
    default: u64,
    unit: &'static str,
    doc: &'static str,
) -> Param {
    Param {
        name,
        kind: Kind::Integer { min, max },
        default: Default::Integer(default),
        unit,
        doc,
        see: "",
    }
}

/// The curiosity channel's constants (docs/algorithm.md §7), in the order
/// of [`crate::CuriosityParams`]'s fields. Defaults are the paper's where
/// it gives one and the reproduction's otherwise (the field docs of
/// `CuriosityParams` say which and why).
pub const CURIOSITY_PARAMS: [Param; 16] = [
    integer(
        "max_centres",
        2,
        Max::Limit {
            flag: "--max-roc-centres",
            hard: MAX_CENTRES as u64,
        },
        3,
        "centres",
        "N_max, the most centres ROC keeps",
    ),
    real(
        "beta",
        Bound::Excl(0.0),
        Bound::Incl(1.0),
        0.01,
        "β, the smallest step of a ROC centre",
    ),
    integer(
        "tau",
        1,
        Max::Limit {
            flag: "--max-curiosity-window",
            hard: MAX_WINDOW as u64,
        },
        20,
        "samples",
        "τ, the recent ROC errors averaged into ε (a window the server allocates for every module)",
    ),
    integer(
        "lag",
        1,
        Max::Limit {
            flag: "--max-curiosity-window",
            hard: MAX_WINDOW as u64,
        },
        20,
        "samples",
        "L, the look-back of Eq. 7 (a history the server allocates for every module)",
    ),
    real(
        "eta_c",
        Bound::Excl(0.0),
        Bound::Excl(1.0),
        0.03,
        "η_c, the MCA rate of the slow-feature direction",
    ),
    real(
        "gain",
        Bound::Excl(0.0),
        Bound::Incl(MAX_CURIOSITY_GAIN),
        800.0,
        "g, the gain of Eq. 7",
    ),
    real(
        "clip",
        Bound::Excl(0.0),
        Bound::Incl(MAX_CURIOSITY_CLIP),
        12.0,
        "the upper clip of ξ_cur in Eq. 7",
    ),
    real(
        "delta",
        Bound::Excl(0.0),
        Bound::None,
        0.3,
        "δ, the error below which a module freezes",
    ),
    integer(
        "freeze_after",
        1,
        Max::Value(u32::MAX as u64),
        100,
        "samples",
        "consecutive learned samples with ε < δ before a freeze",
    ),
    real(
        "explain_below",
        Bound::Excl(0.0),
        Bound::None,
        0.3,
        "the window mean of errors below which a frozen module explains a source",
    ),
    integer(
        "explain_min_samples",
        1,
        Max::Value(u64::MAX),
        20,
        "samples",
        "the samples of a source a frozen module needs to explain it",
    ),
    real(
        "dt",
        Bound::Excl(0.0),
        Bound::None,
        0.08,
        "the signal clock's step (the experiment's signal generator; a session's signals come from its client)",
    ),
    real(
        "floor_rel",
        Bound::Incl(0.0),
        Bound::Excl(1.0),
        1e-3,
        "whitening floor, relative part",
    ),
    real(
        "floor_abs",
        Bound::Excl(0.0),
        Bound::None,
        1e-8,
        "whitening floor, absolute part",
    ),
    real(
        "initial_error",
        Bound::Incl(0.0),
        Bound::None,
        1.0,
        "the fill of a fresh module's error window",
    ),
    integer(
        "max_sources",
        1,
        Max::Limit {
            flag: "--max-signal-sources",
            hard: MAX_SOURCES_LIMIT as u64,
        },
        64,
        "sources",
        "signal sources are numbered 0..max_sources",
    ),
];

/// The curiosity constant called `name`.
pub fn curiosity_param(name: &str) -> Option<&'static Param> {
    CURIOSITY_PARAMS.iter().find(|p| p.name == name)
}
