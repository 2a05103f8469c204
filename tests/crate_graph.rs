//! The workspace's dependency rule (docs/DESIGN.md, "Crates"): services meet only over the wire,
//! so no service crate depends on another, and no library depends on a service. Checked over
//! `cargo metadata`, every dependency kind included (normal, build, dev), so a test or an example
//! cannot quietly pull one service into another either.

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

/// The crates that build a service binary.
const SERVICES: [&str; 3] = ["rfcl-curriculum", "rfcl-learner", "rfcl-actor"];

/// Every workspace crate and the workspace crates it may depend on. The launcher (`rfcl`) is the
/// one crate allowed to use the services' libraries: it runs them in-process for `rfcl bench` and
/// `rfcl eval`, and reads the dashboard's JSON with the curriculum server's own types.
fn allowed() -> BTreeMap<&'static str, BTreeSet<&'static str>> {
    let libs = ["rfcl-proto", "rfcl-core", "rfcl-shm", "rfcl-policy"];
    let set = |names: &[&'static str]| names.iter().copied().collect::<BTreeSet<_>>();
    BTreeMap::from([
        ("rfcl-core", set(&[])),
        ("rfcl-shm", set(&[])),
        ("rfcl-proto", set(&["rfcl-core"])),
        ("rfcl-policy", set(&["rfcl-core"])),
        ("rfcl-probe", set(&["rfcl-proto"])),
        ("rfcl-curriculum", set(&libs)),
        ("rfcl-learner", set(&libs)),
        ("rfcl-actor", set(&libs)),
        ("rfcl", set(&[&libs[..], &SERVICES[..]].concat())),
    ])
}

fn workspace_dependencies() -> BTreeMap<String, BTreeSet<(String, String)>> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--format-version",
            "1",
            "--no-deps",
            "--offline",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run cargo metadata");
    assert!(
        out.status.success(),
        "cargo metadata: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).expect("cargo metadata JSON");
    let members: BTreeSet<String> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| p["name"].as_str().expect("package name").to_string())
        .collect();
    meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let deps = p["dependencies"]
                .as_array()
                .expect("dependencies")
                .iter()
                .filter_map(|d| {
                    let name = d["name"].as_str()?.to_string();
                    let kind = d["kind"].as_str().unwrap_or("normal").to_string();
                    members.contains(&name).then_some((name, kind))
                })
                .collect();
            (p["name"].as_str().unwrap().to_string(), deps)
        })
        .collect()
}

#[test]
fn services_meet_only_over_the_wire() {
    let allowed = allowed();
    let graph = workspace_dependencies();
    let names: BTreeSet<&str> = graph.keys().map(String::as_str).collect();
    let expected: BTreeSet<&str> = allowed.keys().copied().collect();
    assert_eq!(
        names, expected,
        "workspace crates changed: say in this test and docs/DESIGN.md where the new one sits"
    );
    let mut breaches = Vec::new();
    for (krate, deps) in &graph {
        for (dep, kind) in deps {
            if !allowed[krate.as_str()].contains(dep.as_str()) {
                breaches.push(format!("{krate} -> {dep} ({kind})"));
            }
        }
    }
    assert!(
        breaches.is_empty(),
        "dependencies outside the rule in docs/DESIGN.md: {breaches:?}"
    );
    for service in SERVICES {
        let others: Vec<_> = graph[service]
            .iter()
            .filter(|(d, _)| SERVICES.contains(&d.as_str()))
            .collect();
        assert!(
            others.is_empty(),
            "{service} depends on another service: {others:?}"
        );
    }
}
