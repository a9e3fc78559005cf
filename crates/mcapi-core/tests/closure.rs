//! The core knows nothing of the network (docs/architecture.md), and the crate
//! boundary enforces it: this test reads the workspace's *resolved*
//! dependency graph (`cargo metadata`) and walks mcapi-core's normal
//! dependencies, transitively, the way `cargo tree -p mcapi-core -e normal`
//! does. None of the server's, the store's or the plots' crates may appear.

use std::collections::{HashMap, HashSet};
use std::process::Command;

use serde_json::Value;

/// Crates that would tie the core to async, the network, storage or plots.
const FORBIDDEN: [&str; 10] = [
    "tokio", "axum", "tonic", "hyper", "prost", "tower", "redb", "plotters", "mio", "h2",
];

fn metadata() -> Value {
    let cargo = option_env!("CARGO").unwrap_or("cargo");
    let out = Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--offline", "--locked"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "cargo metadata failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("cargo metadata prints JSON")
}

/// The names of every package mcapi-core reaches through normal
/// (non-dev, non-build) dependency edges.
fn normal_closure(meta: &Value) -> HashSet<String> {
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
        .find(|(_, name)| **name == "mcapi-core")
        .map(|(id, _)| *id)
        .expect("mcapi-core is a workspace package");

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
            if normal && seen.insert(pkg) {
                todo.push(pkg);
            }
        }
    }
    seen.into_iter().map(|id| names[id].to_owned()).collect()
}

#[test]
fn core_dependency_closure_has_no_runtime_network_storage_or_plotting_crate() {
    let closure = normal_closure(&metadata());
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
