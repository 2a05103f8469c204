//! The workspace's dependency rule (docs/DESIGN.md, "Crates"): services meet only over the wire,
//! so no service crate depends on another, and no library depends on a service. Checked over
//! `cargo metadata`, every dependency kind included (normal, build, dev), so a test or an example
//! cannot quietly pull one service into another either. The test kit (`rfcl-testkit`) is test
//! support: any crate may take it, as a dev-dependency only, and it uses no service crate.

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

/// The crates that build a service binary.
const SERVICES: [&str; 3] = ["rfcl-curriculum", "rfcl-learner", "rfcl-actor"];

/// The cross-process test helpers: every crate may have it, as a dev-dependency only.
const TESTKIT: &str = "rfcl-testkit";

/// Every workspace crate and the workspace crates it may depend on. The launcher (`rfcl`) is the
/// one crate allowed to use the services' libraries: it runs them in-process for `rfcl bench` and
/// `rfcl eval` (what it reads from a running service is the wire's, see
/// [`the_launcher_reads_no_service_s_dashboard`]).
fn allowed() -> BTreeMap<&'static str, BTreeSet<&'static str>> {
    // rfcl-runtime: what a binary's main() does (logging, tokio runtime, signals, exit status).
    let libs = [
        "rfcl-proto",
        "rfcl-core",
        "rfcl-shm",
        "rfcl-policy",
        "rfcl-runtime",
    ];
    let set = |names: &[&'static str]| names.iter().copied().collect::<BTreeSet<_>>();
    BTreeMap::from([
        ("rfcl-core", set(&[])),
        ("rfcl-shm", set(&[])),
        ("rfcl-runtime", set(&[])),
        // Test support: a dev-dependency of any crate (checked apart from this table).
        (TESTKIT, set(&["rfcl-core", "rfcl-proto"])),
        ("rfcl-proto", set(&["rfcl-core"])),
        ("rfcl-policy", set(&["rfcl-core"])),
        ("rfcl-probe", set(&["rfcl-proto", "rfcl-runtime"])),
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

/// The dependencies of `graph` outside the rule: not in `allowed`, or on [`TESTKIT`] as anything
/// but a dev-dependency.
fn breaches(
    graph: &BTreeMap<String, BTreeSet<(String, String)>>,
    allowed: &BTreeMap<&'static str, BTreeSet<&'static str>>,
) -> Vec<String> {
    let mut breaches = Vec::new();
    for (krate, deps) in graph {
        for (dep, kind) in deps {
            if dep == TESTKIT {
                if kind != "dev" {
                    breaches.push(format!(
                        "{krate} -> {dep} ({kind}; the test kit is a dev-dependency only)"
                    ));
                }
            } else if !allowed[krate.as_str()].contains(dep.as_str()) {
                breaches.push(format!("{krate} -> {dep} ({kind})"));
            }
        }
    }
    breaches
}

#[test]
fn the_test_kit_is_only_ever_a_dev_dependency() {
    let allowed = allowed();
    let graph = |kind: &str| {
        BTreeMap::from([(
            "rfcl-learner".to_string(),
            BTreeSet::from([(TESTKIT.to_string(), kind.to_string())]),
        )])
    };
    assert!(breaches(&graph("dev"), &allowed).is_empty());
    for kind in ["normal", "build"] {
        assert_eq!(
            breaches(&graph(kind), &allowed),
            [format!(
                "rfcl-learner -> rfcl-testkit ({kind}; the test kit is a dev-dependency only)"
            )]
        );
    }
    // And the kit itself uses no service.
    for service in SERVICES {
        assert!(!allowed[TESTKIT].contains(service));
    }
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
    let breaches = breaches(&graph, &allowed);
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

/// What the launcher reads from a running curriculum server is `rfcl_core::run_state::RunState`
/// (GetState), never the dashboard's view: a page can change without touching `rfcl train`'s
/// progress and summary or `rfcl demos select`.
#[test]
fn the_launcher_reads_no_service_s_dashboard() {
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut offenders = Vec::new();
    let mut dirs = vec![src];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).expect("read src/") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).expect("read a source file");
                if text.contains("rfcl_curriculum::dashboard") || text.contains("DashboardView") {
                    offenders.push(path.display().to_string());
                }
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "these launcher files use the curriculum server's dashboard types; read \
         rfcl_core::run_state::RunState (GetState) instead: {offenders:?}"
    );
}
