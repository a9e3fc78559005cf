//! The schemas of a continuous model (docs/sessions.md, "Continuous
//! worlds"): its box, its basis and how its sample store is cut, every
//! bound read from the core's constants.

use serde_json::json;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{OneOfBuilder, Schema, Type};

use super::builders::{
    Bound, array, closed, integer, non_blank_name, nullable_ref, number, reference, typed,
};
use crate::service::Limits;
use mcapi_core::continuous::basis::{
    MAX_CENTRES_PER_DIM, MAX_ORDER, MAX_PVF_K, MAX_PVF_NEIGHBOURS, MAX_PVF_NODES,
    MAX_STATE_FEATURES, MAX_TILES_PER_DIM, MAX_TILINGS,
};
use mcapi_core::continuous::grid::{MAX_GRID_CELLS, MAX_GRID_NEIGHBOURS, MAX_GRID_REACH};
use mcapi_core::continuous::model::{
    MAX_ACTIONS, MAX_CELLS_PER_DIM, MAX_KNOWN_AFTER, MAX_PER_CELL, MAX_SAMPLES,
};
use mcapi_core::continuous::space::{MAX_COORDINATE, MAX_DIM};

/// The continuous-model schemas, by component name, for these limits.
pub(super) fn schemas(limits: &Limits) -> Vec<(&'static str, RefOr<Schema>)> {
    let max_name = limits.max_name_bytes;
    let corner = |what: &str| {
        array(
            number(
                Bound::Incl(-MAX_COORDINATE),
                Bound::Incl(MAX_COORDINATE),
                false,
                "a coordinate (|x| ≤ 1e12)",
            ),
            1,
            MAX_DIM,
            false,
            what,
        )
    };
    let space = closed("The box observations live in: `low[i] < high[i]` in every dimension.")
        .property(
            "low",
            corner("the lower corner, one coordinate per dimension"),
        )
        .property("high", corner("the upper corner, as long as `low`"))
        .required("low")
        .required("high");
    let kind = |k: &str| typed(Type::String, false).enum_values(Some([k]));
    let fourier = closed(
        "The Fourier basis: cos(π c·s) for every integer vector c in {0..order}^d with at \
         most `max_coupling` non-zero entries (k ≤ the feature bounds).",
    )
    .property("kind", kind("fourier"))
    .property(
        "order",
        integer(1, u64::from(MAX_ORDER), false, "highest frequency"),
    )
    .property(
        "max_coupling",
        integer(
            1,
            MAX_DIM as u64,
            true,
            "most dimensions one term couples (at most d; default d)",
        ),
    )
    .required("kind")
    .required("order");
    let rbf = closed("Normalised Gaussians on a grid of `centres_per_dim`^d centres.")
        .property("kind", kind("rbf"))
        .property(
            "centres_per_dim",
            integer(
                2,
                u64::from(MAX_CENTRES_PER_DIM),
                false,
                "centres per dimension",
            ),
        )
        .property(
            "width",
            number(
                Bound::Incl(0.05),
                Bound::Incl(10.0),
                true,
                "σ in grid spacings (default 1)",
            ),
        )
        .required("kind")
        .required("centres_per_dim");
    let tiles = closed(
        "Tile coding: `tilings` offset grids of `tiles_per_dim`^d tiles, hashed into `table` \
         features.",
    )
    .property("kind", kind("tiles"))
    .property(
        "tilings",
        integer(1, u64::from(MAX_TILINGS), false, "number of tilings"),
    )
    .property(
        "tiles_per_dim",
        integer(
            1,
            u64::from(MAX_TILES_PER_DIM),
            false,
            "tiles per dimension of one tiling",
        ),
    )
    .property(
        "table",
        integer(
            1,
            MAX_STATE_FEATURES as u64,
            true,
            "size of the hashed table, at least `tilings` (default: the exact count when it \
             fits)",
        ),
    )
    .required("kind")
    .required("tilings")
    .required("tiles_per_dim");
    let pvf = closed(
        "Proto-value functions of a graph over the observations seen so far (its nodes \
         a subsample, its edges the observed transitions), extended to any observation by \
         the Nyström formula and rebuilt as coverage grows (docs/algorithm.md §9.2).",
    )
    .property("kind", kind("pvf"))
    .property(
        "k",
        integer(
            1,
            u64::from(MAX_PVF_K),
            false,
            "eigenvectors, the features per action (at most `nodes`)",
        ),
    )
    .property(
        "nodes",
        integer(
            2,
            u64::from(MAX_PVF_NODES),
            true,
            "most graph nodes (default 800)",
        ),
    )
    .property(
        "neighbours",
        integer(
            1,
            u64::from(MAX_PVF_NEIGHBOURS),
            true,
            "most neighbours of a node (default 16)",
        ),
    )
    .required("kind")
    .required("k");
    let grid = closed(
        "No features: a grid of `cells_per_dim`^d cells over the box, planned on exactly, \
         each (cell, action)'s successor learned from the `neighbours` nearest moves within \
         `reach` cells (docs/algorithm.md §9.8). At most 4096 cells and 16384 (cell, action) \
         pairs.",
    )
    .property("kind", kind("grid"))
    .property(
        "cells_per_dim",
        integer(
            2,
            MAX_GRID_CELLS as u64,
            false,
            "cells per dimension (cells_per_dim^d at most 4096)",
        ),
    )
    .property(
        "neighbours",
        integer(
            1,
            u64::from(MAX_GRID_NEIGHBOURS),
            true,
            "moves kept per (cell, action) (default 5)",
        ),
    )
    .property(
        "reach",
        number(
            Bound::Incl(1.0),
            Bound::Incl(MAX_GRID_REACH),
            true,
            "how far a move teaches, in cells (default 3.5)",
        ),
    )
    .required("kind")
    .required("cells_per_dim");
    let basis = OneOfBuilder::new()
        .item(fourier)
        .item(rbf)
        .item(tiles)
        .item(pvf)
        .item(grid)
        .description(Some(
            "The basis over the space (default: by dimension, shown in the session's \
             summary: a grid for d ≤ 2). At most 4096 features per action and 2048 over all \
             actions.",
        ));
    let count = |max: u32, what: &str| integer(1, u64::from(max), true, what);
    let samples = closed("How the sample store is cut; every field optional.")
        .property(
            "cells_per_dim",
            count(
                MAX_CELLS_PER_DIM,
                "cells per dimension of the grid that counts visits",
            ),
        )
        .property(
            "per_cell",
            count(MAX_PER_CELL, "transitions kept per (cell, action)"),
        )
        .property("max", count(MAX_SAMPLES, "transitions kept in all"))
        .property(
            "known_after",
            count(
                MAX_KNOWN_AFTER,
                "visits after which a (cell, action) pair is known",
            ),
        );
    let model = closed(
        "A continuous world: observations are vectors in a box, and the transitions are \
         always learned from what the session observes (docs/algorithm.md §9).",
    )
    .property("observation_space", reference("ObservationSpace"))
    .property(
        "actions",
        array(
            non_blank_name(max_name, "an action name"),
            1,
            MAX_ACTIONS,
            false,
            "the action names, distinct",
        ),
    )
    .property(
        "stimuli",
        array(
            non_blank_name(max_name, "a stimulus name"),
            1,
            limits.max_stimuli,
            false,
            "the names of the stimulus dimensions, distinct (limit)",
        ),
    )
    .property(
        "basis",
        nullable_ref(
            "ContinuousBasis",
            "the basis; absent or null for the default by dimension",
        ),
    )
    .property(
        "out_of_bounds",
        typed(Type::String, false)
            .enum_values(Some(["clip", "refuse"]))
            .description(Some(
                "what an observation outside the box does: clipped into it and counted \
                 (default), or refused with 400 `invalid_observation`",
            )),
    )
    .property("samples", reference("SampleParams"))
    .required("observation_space")
    .required("actions")
    .required("stimuli")
    .examples([json!({
        "observation_space": {"low": [0, 0], "high": [1, 1]},
        "actions": ["north", "south", "east", "west"],
        "stimuli": ["food", "water", "rest"],
        "basis": {"kind": "fourier", "order": 5}
    })]);
    vec![
        ("ContinuousModel", model.into()),
        ("ObservationSpace", space.into()),
        ("ContinuousBasis", basis.into()),
        ("SampleParams", samples.into()),
    ]
}
