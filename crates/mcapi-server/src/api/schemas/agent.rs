//! The schemas of the agent's configuration (`SessionConfig`), its
//! stimulus rate and its curiosity channel, built from the parameter
//! tables: the core's [`AGENT_PARAMS`] and [`CURIOSITY_PARAMS`] and the
//! service's [`SESSION_PARAMS`]. Each property's bounds, default and
//! description come from its entry, so the document cannot drift from what
//! the core checks.
//!
//! [`SESSION_PARAMS`]: crate::service::agent_config::SESSION_PARAMS

use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{OneOfBuilder, Schema, Type};

use super::builders::{array, closed, integer, nullable_ref, number, reference, typed};
use crate::service::Limits;
use crate::service::agent_config::session_options;
use mcapi_core::curiosity::MAX_SIGNAL_DIM;
use mcapi_core::params::{CURIOSITY_PARAMS, Kind, Max, Param, table};

/// The value of the server limit set by `flag` (a [`Max::Limit`] of the
/// tables), `None` for a flag this server does not have.
pub fn limit_of(limits: &Limits, flag: &str) -> Option<u64> {
    let value = match flag {
        "--max-history" => limits.max_history,
        "--max-curiosity-window" => limits.max_curiosity_window,
        "--max-roc-centres" => limits.max_roc_centres,
        "--max-signal-sources" => limits.max_signal_sources,
        _ => return None,
    };
    Some(u64::try_from(value).unwrap_or(u64::MAX))
}

/// The description of a parameter: its doc, its default (and unit), and
/// `(limit)` when a server limit bounds it.
pub fn describe(p: &Param) -> String {
    let unit = match p.default {
        mcapi_core::params::spec::Default::Real(_)
        | mcapi_core::params::spec::Default::Integer(_)
            if !p.unit.is_empty() =>
        {
            format!(" {}", p.unit)
        }
        _ => String::new(),
    };
    let limit = match p.kind {
        Kind::Integer {
            max: Max::Limit { .. },
            ..
        } => " (limit)",
        _ => "",
    };
    format!("{}; default {}{unit}{limit}", p.doc, p.default_text())
}

/// The schema of one parameter's value, `null` allowed when `nullable`.
fn property(p: &Param, nullable: bool, limits: &Limits) -> RefOr<Schema> {
    let description = describe(p);
    match p.kind {
        Kind::Real { lower, upper } => number(lower, upper, nullable, &description).into(),
        Kind::Integer { min, max } => {
            let max = match max {
                Max::Value(v) => v,
                Max::Limit { flag, hard } => limit_of(limits, flag).unwrap_or(hard).min(hard),
            };
            integer(min, max, nullable, &description).into()
        }
        Kind::PerStimulus { lower, upper } => array(
            number(lower, upper, false, "one entry"),
            0,
            limits.max_stimuli,
            nullable,
            &description,
        )
        .into(),
        Kind::RealOrName { .. } => nullable_ref(&p.type_name(), &description),
        Kind::Choice(names) => {
            let mut values: Vec<serde_json::Value> = names.iter().map(|&n| n.into()).collect();
            if nullable {
                values.push(serde_json::Value::Null);
            }
            typed(Type::String, nullable)
                .enum_values(Some(values))
                .description(Some(description))
                .into()
        }
        Kind::Object(schema) => nullable_ref(schema, &description),
    }
}

/// The schema of a [`Kind::RealOrName`] parameter's value: a constant or
/// one of the names.
fn real_or_name(p: &Param) -> Option<RefOr<Schema>> {
    let Kind::RealOrName {
        lower,
        upper,
        names,
    } = p.kind
    else {
        return None;
    };
    Some(
        OneOfBuilder::new()
            .item(number(lower, upper, false, "a constant"))
            .item(
                typed(Type::String, false)
                    .enum_values(Some(names.to_vec()))
                    .description(Some("a named rule")),
            )
            .description(Some(describe(p)))
            .into(),
    )
}

/// The agent schemas, by component name, for these limits.
pub(super) fn schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let config = session_options().fold(
        closed("The agent's configuration; every field is optional (null = absent)."),
        |o, p| o.property(p.name, property(p, true, limits)),
    );
    let curiosity_params = CURIOSITY_PARAMS.iter().fold(
        closed(
            "The curiosity channel's constants (docs/algorithm.md §7); each defaults to the \
             reproduction's value.",
        ),
        |o, p| o.property(p.name, property(p, false, limits)),
    );
    let curiosity = closed(
        "A curiosity channel (docs/algorithm.md §7): the server appends a stimulus dimension \
         `curiosity`, last, computed from the raw `signal` of observations.",
    )
    .property(
        "signal_dim",
        integer(
            1,
            MAX_SIGNAL_DIM as u64,
            false,
            "dimension m of the raw signal (2 for the paper's Eq. 6)",
        ),
    )
    .property("params", reference("CuriosityParams"))
    .required("signal_dim");
    let mut out = vec![
        ("SessionConfig", config.into()),
        ("CuriosityConfig", curiosity.into()),
        ("CuriosityParams", curiosity_params.into()),
    ];
    out.extend(real_or_name(&table::STIMULUS_RATE).map(|s| ("StimulusRate", s)));
    out
}
