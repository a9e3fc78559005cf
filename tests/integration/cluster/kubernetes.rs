//! The committed Kubernetes ConfigMap (deploy/k8s/) is what
//! `mcapi cluster` writes (`make k8s-configmap`).

use std::path::Path;
use std::process::Command;

use mcapi_cluster::haproxy::find_haproxy;
use mcapi_shards::ShardMap;

use super::{haproxy_or_skip, stderr};

/// The text of `key: |` in a generated ConfigMap, de-indented.
fn configmap_block(yaml: &str, key: &str) -> String {
    let head = format!("\n  {key}: |\n");
    let start = yaml
        .find(&head)
        .unwrap_or_else(|| panic!("no {key} in the ConfigMap"))
        + head.len();
    let mut out = String::new();
    for line in yaml[start..].lines() {
        if line.is_empty() {
            out.push('\n');
        } else if let Some(l) = line.strip_prefix("    ") {
            out.push_str(l);
            out.push('\n');
        } else {
            break;
        }
    }
    out
}

#[test]
fn the_committed_kubernetes_configmap_is_what_the_command_writes() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("configmap.yaml");
    let run = Command::new("bash")
        .arg(root.join("tools/k8s-configmap.sh"))
        .arg(&out)
        .env("MCAPI_BIN", env!("CARGO_BIN_EXE_mcapi"))
        .env_remove("REPLICAS")
        .env_remove("MAP")
        .output()
        .expect("bash runs");
    assert!(run.status.success(), "k8s-configmap.sh: {}", stderr(&run));
    let generated = std::fs::read_to_string(&out).expect("generated");
    let committed = std::fs::read_to_string(root.join("deploy/k8s/10-mcapi-cluster.yaml"))
        .expect("deploy/k8s/10-mcapi-cluster.yaml");
    assert!(
        generated == committed,
        "deploy/k8s/10-mcapi-cluster.yaml differs from what `bash tools/k8s-configmap.sh` writes now: run it (make k8s-configmap)"
    );

    // The StatefulSet runs exactly the map's replicas.
    let map = ShardMap::parse(&configmap_block(&committed, "mcapi-shards.map")).expect("the map");
    let sts = std::fs::read_to_string(root.join("deploy/k8s/20-replicas.yaml")).expect("sts");
    let replicas: Vec<&str> = sts
        .lines()
        .filter_map(|l| l.strip_prefix("  replicas: "))
        .collect();
    assert_eq!(
        replicas,
        [map.replicas().len().to_string()],
        "StatefulSet replicas"
    );
    for (k, name) in map.replicas().iter().enumerate() {
        assert_eq!(
            name.as_str(),
            format!("mcapi-{k}"),
            "pod names are the replica names"
        );
    }

    // HAProxy accepts the configuration (with its two paths moved here).
    let cfg = configmap_block(&committed, "haproxy.cfg");
    assert!(cfg.contains("resolvers dns init-addr none"), "{cfg}");
    if !haproxy_or_skip("the_committed_kubernetes_configmap_is_what_the_command_writes") {
        return;
    }
    let map_path = dir.path().join("shards.map");
    std::fs::write(&map_path, configmap_block(&committed, "shards.map")).expect("map");
    let local = cfg
        .replace(
            "/usr/local/etc/haproxy/shards.map",
            map_path.to_str().expect("utf-8"),
        )
        .replace(
            "/var/run/haproxy/admin.sock",
            dir.path().join("admin.sock").to_str().expect("utf-8"),
        );
    let cfg_path = dir.path().join("haproxy.cfg");
    std::fs::write(&cfg_path, local).expect("cfg");
    let check = Command::new(find_haproxy().expect("checked"))
        .args(["-c", "-f"])
        .arg(&cfg_path)
        .output()
        .expect("haproxy -c");
    assert!(
        check.status.success(),
        "haproxy refuses the Kubernetes configuration: {}{}",
        String::from_utf8_lossy(&check.stdout),
        stderr(&check)
    );
}
