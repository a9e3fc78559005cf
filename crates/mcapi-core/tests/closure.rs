//! The crates' layers (docs/architecture.md), enforced on the workspace's
//! *resolved* dependency graph (`cargo metadata`), normal dependencies only
//! (the way `cargo tree -e normal` walks them; tests may reach further):
//!
//! - the core knows nothing of the network: none of the server's, the
//!   store's or the plots' crates is in mcapi-core's closure;
//! - every workspace crate depends only on the workspace crates its row of
//!   [`ALLOWED`] names, so arrows only point down a layer and no crate
//!   reaches one above it (mcapi-cluster never reaches mcapi-server,
//!   mcapi-store and mcapi-shards reach no other mcapi crate);
//! - the tests' helpers ([`DEV_ONLY`]: mcapi-testkit) are only ever a
//!   dev-dependency, never a normal or build one, and are not published.

use std::collections::{HashMap, HashSet};
use std::process::Command;

use serde_json::Value;

/// Crates that would tie the core to async, the network, storage or plots.
const FORBIDDEN: [&str; 10] = [
    "tokio", "axum", "tonic", "hyper", "prost", "tower", "redb", "plotters", "mio", "h2",
];

/// Each workspace crate and the workspace crates it may depend on directly
/// (normal dependencies). A new crate needs a row here.
const ALLOWED: [(&str, &[&str]); 10] = [
    // The binary: CLI wiring only.
    (
        "mcapi",
        &["mcapi-cluster", "mcapi-experiments", "mcapi-server"],
    ),
    ("mcapi-loadgen", &["mcapi-proto"]),
    ("mcapi-cluster", &["mcapi-shards"]),
    (
        "mcapi-server",
        &["mcapi-core", "mcapi-proto", "mcapi-shards", "mcapi-store"],
    ),
    ("mcapi-experiments", &["mcapi-core"]),
    // The tests' helpers (a dev-dependency only: DEV_ONLY).
    ("mcapi-testkit", &["mcapi-core", "mcapi-server"]),
    // The leaves.
    ("mcapi-core", &[]),
    ("mcapi-proto", &[]),
    ("mcapi-shards", &[]),
    ("mcapi-store", &[]),
];

/// Workspace crates that only tests may use: every edge to them is a
/// dev-dependency (a normal or build one would ship test helpers in a
/// binary), and they are not published.
const DEV_ONLY: [&str; 1] = ["mcapi-testkit"];

/// The resolved graph, as `cargo metadata` prints it (`--locked`: the lock
/// file's versions). Offline first; a fresh machine's cache lacks the
/// manifests of crates that only other platforms build (cargo metadata lists
/// every platform's), so then once more with the registry.
fn metadata() -> Value {
    let cargo = option_env!("CARGO").unwrap_or("cargo");
    let run = |offline: bool| {
        let mut args = vec!["metadata", "--format-version", "1", "--locked"];
        if offline {
            args.push("--offline");
        }
        Command::new(cargo)
            .args(args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .output()
            .expect("cargo metadata runs")
    };
    let mut out = run(true);
    if !out.status.success() {
        out = run(false);
    }
    assert!(
        out.status.success(),
        "cargo metadata failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("cargo metadata prints JSON")
}

/// The names of the packages `root` depends on through normal (non-dev,
/// non-build) edges: directly, or (`transitive`) through any path.
fn normal_deps(meta: &Value, root: &str, transitive: bool) -> HashSet<String> {
    let names: HashMap<&str, &str> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| {
            (
                p["id"].as_str().expect("id"),
                p["name"].as_str().expect("name"),
            )
        })
        .collect();
    let nodes: HashMap<&str, &Value> = meta["resolve"]["nodes"]
        .as_array()
        .expect("resolve.nodes")
        .iter()
        .map(|n| (n["id"].as_str().expect("node id"), n))
        .collect();
    let root = names
        .iter()
        .find(|(_, name)| **name == root)
        .map(|(id, _)| *id)
        .unwrap_or_else(|| panic!("{root} is a workspace package"));

    let mut seen = HashSet::from([root]);
    let mut todo = vec![root];
    while let Some(id) = todo.pop() {
        for dep in nodes[id]["deps"].as_array().expect("deps") {
            let normal = dep["dep_kinds"]
                .as_array()
                .expect("dep_kinds")
                .iter()
                .any(|k| k["kind"].is_null());
            let pkg = dep["pkg"].as_str().expect("pkg");
            if normal && seen.insert(pkg) && transitive {
                todo.push(pkg);
            }
        }
    }
    seen.remove(root);
    seen.into_iter().map(|id| names[id].to_owned()).collect()
}

#[test]
fn core_dependency_closure_has_no_runtime_network_storage_or_plotting_crate() {
    let closure = normal_deps(&metadata(), "mcapi-core", true);
    // The walk found the core's own dependencies, so it walked the right graph.
    for expected in ["nalgebra", "rand", "serde"] {
        assert!(
            closure.contains(expected),
            "{expected} missing from {closure:?}"
        );
    }
    let mut found: Vec<&String> = closure
        .iter()
        .filter(|name| {
            FORBIDDEN
                .iter()
                .any(|f| *name == f || name.starts_with(&format!("{f}-")))
        })
        .collect();
    found.sort();
    assert!(
        found.is_empty(),
        "mcapi-core's normal dependencies reach {found:?}: the core must stay free of async, network, storage and plots"
    );
}

/// The names of the workspace's crates.
fn workspace_crates(meta: &Value) -> HashSet<String> {
    let members: HashSet<&str> = meta["workspace_members"]
        .as_array()
        .expect("workspace_members")
        .iter()
        .map(|m| m.as_str().expect("member id"))
        .collect();
    meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .filter(|p| members.contains(p["id"].as_str().expect("id")))
        .map(|p| p["name"].as_str().expect("name").to_owned())
        .collect()
}

#[test]
fn every_crate_depends_only_on_the_workspace_crates_of_its_layer() {
    let meta = metadata();
    let crates = workspace_crates(&meta);
    let mut listed: Vec<&str> = ALLOWED.iter().map(|(name, _)| *name).collect();
    listed.sort_unstable();
    let mut members: Vec<&str> = crates.iter().map(String::as_str).collect();
    members.sort_unstable();
    assert_eq!(
        members, listed,
        "every workspace crate needs exactly one row in ALLOWED"
    );
    let mut wrong = Vec::new();
    for (name, allowed) in ALLOWED {
        let mut found: Vec<String> = normal_deps(&meta, name, false)
            .into_iter()
            .filter(|d| crates.contains(d) && !allowed.contains(&d.as_str()))
            .collect();
        found.sort();
        if !found.is_empty() {
            wrong.push(format!("{name} -> {found:?}"));
        }
    }
    assert!(
        wrong.is_empty(),
        "workspace dependencies outside the layers (ALLOWED): {wrong:?}"
    );
}

#[test]
fn the_tool_the_store_and_the_shard_map_reach_no_crate_above_them() {
    let meta = metadata();
    let crates = workspace_crates(&meta);
    // (crate, workspace crates its whole closure may contain)
    let cases: [(&str, &[&str]); 4] = [
        ("mcapi-cluster", &["mcapi-shards"]),
        ("mcapi-loadgen", &["mcapi-proto"]),
        ("mcapi-store", &[]),
        ("mcapi-shards", &[]),
    ];
    for (name, may) in cases {
        let mut reached: Vec<String> = normal_deps(&meta, name, true)
            .into_iter()
            .filter(|d| crates.contains(d) && !may.contains(&d.as_str()))
            .collect();
        reached.sort();
        assert!(reached.is_empty(), "{name} reaches {reached:?}");
    }
}

#[test]
fn the_tests_helpers_are_only_ever_a_dev_dependency() {
    let meta = metadata();
    let names: HashMap<&str, &str> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| {
            (
                p["id"].as_str().expect("id"),
                p["name"].as_str().expect("name"),
            )
        })
        .collect();
    let mut wrong = Vec::new();
    let mut dev_users = HashSet::new();
    for node in meta["resolve"]["nodes"].as_array().expect("resolve.nodes") {
        let user = names[node["id"].as_str().expect("node id")];
        for dep in node["deps"].as_array().expect("deps") {
            let name = names[dep["pkg"].as_str().expect("pkg")];
            if !DEV_ONLY.contains(&name) {
                continue;
            }
            for kind in dep["dep_kinds"].as_array().expect("dep_kinds") {
                match kind["kind"].as_str() {
                    Some("dev") => {
                        dev_users.insert(format!("{user} -> {name}"));
                    }
                    other => wrong.push(format!("{user} -> {name} ({other:?})")),
                }
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "test helpers as a normal (None) or build dependency: {wrong:?}"
    );
    // The walk saw the edges it checks: the server's tests and the
    // binary's use the helpers.
    for user in ["mcapi-server", "mcapi"] {
        assert!(
            dev_users.contains(&format!("{user} -> mcapi-testkit")),
            "{user} dev-depends on mcapi-testkit: {dev_users:?}"
        );
    }
    for package in meta["packages"].as_array().expect("packages") {
        let name = package["name"].as_str().expect("name");
        if DEV_ONLY.contains(&name) {
            // `publish = false` reads as an empty list of registries.
            assert_eq!(
                package["publish"],
                serde_json::json!([]),
                "{name} has `publish = false`"
            );
        }
    }
}
