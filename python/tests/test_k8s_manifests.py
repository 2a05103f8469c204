"""deploy/k8s: the Kubernetes manifests are valid and say what deploy/docker-compose.yml says.

* Schema: every object in deploy/k8s/*.yaml validates, offline, against the Kubernetes OpenAPI
  schemas of K8S_VERSION that the `kubernetes-validate` package ships (strict: unknown fields are
  errors, so a misspelt key fails here instead of being dropped by the API server); so does the
  output of `kubectl kustomize deploy/k8s` where kubectl is installed (skipped otherwise).
* Wiring: kustomization.yaml lists every manifest (but the token Secret's template), Services select
  the server pod and name ports it has, probes are grpc probes on the gRPC ports, the token comes
  from the mounted Secret, the run volume and the shared-memory volumes are where the contract puts
  them.
* Compose: the same images, ports, run paths, demo path, config and RFCL_* env names as
  deploy/docker-compose.yml, role by role (curriculum server, learner, demos, actor, eval actor).
  The manifests are also checked against the deploy contract's values (CONTRACT), so the test says
  something before the compose file exists; it is skipped only for the compose comparison.

No network and no cluster: schemas come from the installed package, YAML is parsed with PyYAML.
"""
from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

kubernetes_validate = pytest.importorskip(
    "kubernetes_validate", reason="pip install -r python/requirements.txt (kubernetes-validate)"
)

ROOT = Path(__file__).resolve().parents[2]
K8S_DIR = ROOT / "deploy" / "k8s"
COMPOSE = ROOT / "deploy" / "docker-compose.yml"

# The Kubernetes version whose schemas the manifests must satisfy (native grpc probes need 1.27+).
K8S_VERSION = "1.30.0"

TOKEN_SECRET = "rfcl-token"
TOKEN_DIR = "/var/run/secrets/rfcl"
TOKEN_FILE = f"{TOKEN_DIR}/token"
# The Secret's template, deliberately not applied by kustomize (it would reset the real token).
SECRET_TEMPLATE = "secret.yaml"

# The deploy contract, role by role: what both deploy/k8s and deploy/docker-compose.yml must say.
CONFIG = "/opt/rfcl/configs/pointmaze_test.yml"
RUN_DIR = "/runs/pointmaze"
DEMOS = "/runs/demos/pointmaze.h5"
CONTRACT = {
    "curriculum": {
        "image": "rfcl-curriculum:local",
        "--port": "50051",
        "--dashboard-port": "8080",
        "--config": CONFIG,
        "--run-dir": RUN_DIR,
        "train.dataset_path": DEMOS,
        "run volume mount": "/runs",
    },
    "learner": {
        "image": "rfcl:local",
        "--port": "50052",
        "--metrics-port": "9090",
        "--config": CONFIG,
        "--run-dir": RUN_DIR,
        "train.dataset_path": DEMOS,
        "curriculum port": "50051",
        "run volume mount": "/runs",
    },
    "demos": {
        "image": "rfcl:local",
        "--env": "pointmaze",
        "-n": "5",
        "--out": DEMOS,
        "run volume mount": "/runs",
    },
    "actor": {"image": "rfcl:local", "learner port": "50052", "--eval": False},
    "eval_actor": {"image": "rfcl:local", "learner port": "50052", "--eval": True},
}
# RFCL_* variables each role must set (compose and k8s alike; values differ by platform).
CONTRACT_ENV = {
    "curriculum": {"RFCL_TOKEN_FILE"},
    "learner": {"RFCL_TOKEN_FILE"},
    "actor": {"RFCL_TOKEN_FILE"},
    "eval_actor": {"RFCL_TOKEN_FILE"},
}
# Every RFCL_* name the binaries read (a name outside this set is a typo).
KNOWN_ENV = {
    "RFCL_TOKEN", "RFCL_TOKEN_FILE", "RFCL_LEARNER", "RFCL_CURRICULUM", "RFCL_ACTOR_ID",
    "RFCL_TLS_CERT", "RFCL_TLS_KEY", "RFCL_TLS_CA",
}
# Container ports by role (k8s containerPort; compose ports/expose targets must be among them).
CONTRACT_PORTS = {"curriculum": {50051, 8080}, "learner": {50052, 9090}}
GRPC_PORT = {"curriculum": 50051, "learner": 50052}
# Service name -> ports it must offer.
CONTRACT_SERVICES = {"rfcl-curriculum": {50051, 8080}, "rfcl-learner": {50052}}
# Flags and overrides compared between platforms (when either side has them).
FLAGS = ["--port", "--dashboard-port", "--metrics-port", "--config", "--run-dir", "--env", "-n",
         "--out", "--envs"]
OVERRIDES = ["train.dataset_path"]


# ------------------------------------------------------------------------------------ loading
def manifest_files() -> list[Path]:
    return sorted(p for p in K8S_DIR.glob("*.yaml") if p.name != "kustomization.yaml")


def load_docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def all_objects() -> list[tuple[str, dict]]:
    return [(p.name, d) for p in manifest_files() for d in load_docs(p)]


def objects_of(kind: str) -> list[dict]:
    return [d for _, d in all_objects() if d["kind"] == kind]


def kustomization() -> dict:
    return yaml.safe_load((K8S_DIR / "kustomization.yaml").read_text())


def applied_objects() -> list[dict]:
    """What `kubectl apply -k deploy/k8s` creates (the Secret template is not among them)."""
    return [d for f in kustomization()["resources"] for d in load_docs(K8S_DIR / f)]


def object_ids() -> list[str]:
    return [f"{f}:{d['kind']}/{d['metadata']['name']}" for f, d in all_objects()]


# ------------------------------------------------------------------- (a) schema validation
def test_there_are_manifests():
    kinds = {d["kind"] for _, d in all_objects()}
    assert {"Namespace", "Secret", "StatefulSet", "Deployment", "Service"} <= kinds, kinds


@pytest.mark.parametrize("obj", [d for _, d in all_objects()], ids=object_ids())
def test_manifest_validates_against_kubernetes_schema(obj):
    try:
        validated = kubernetes_validate.validate(obj, K8S_VERSION, strict=True)
    except kubernetes_validate.ValidationError as e:
        where = ".".join(str(p) for p in e.path) or "(top level)"
        pytest.fail(f"{obj['kind']}/{obj['metadata']['name']} is invalid for Kubernetes "
                    f"{K8S_VERSION} at {where}: {e.message}")
    except kubernetes_validate.SchemaNotFoundError as e:
        pytest.fail(e.message)
    # kubernetes-validate falls back to the newest schema not newer than the one asked for.
    assert validated == ".".join(K8S_VERSION.split(".")[:2]), validated


def test_schema_validation_rejects_a_bad_manifest():
    """Guards the test itself: a misspelt field and a wrong type are caught."""
    [sts] = objects_of("StatefulSet")
    bad = yaml.safe_load(yaml.safe_dump(sts))
    bad["spec"]["template"]["spec"]["containers"][0]["imagePullPolcy"] = "Always"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, K8S_VERSION, strict=True)
    bad = yaml.safe_load(yaml.safe_dump(sts))
    bad["spec"]["replicas"] = "one"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, K8S_VERSION, strict=True)


def test_kustomization_lists_every_manifest_but_the_secret_template():
    k = kustomization()
    assert k["apiVersion"] == "kustomize.config.k8s.io/v1beta1" and k["kind"] == "Kustomization"
    listed = k["resources"]
    assert len(listed) == len(set(listed)), f"kustomization.yaml lists a file twice: {listed}"
    for f in listed:
        assert (K8S_DIR / f).is_file(), f"kustomization.yaml lists {f}, which does not exist"
    expected = {p.name for p in manifest_files()} - {SECRET_TEMPLATE}
    assert set(listed) == expected, (
        f"kustomization.yaml resources {sorted(listed)} != manifests {sorted(expected)} "
        f"({SECRET_TEMPLATE} is to stay out: applying it resets the real token)")
    namespaces = {d["metadata"]["name"] for d in objects_of("Namespace")}
    assert k["namespace"] in namespaces
    for f, d in all_objects():
        if d["kind"] != "Namespace":
            assert d["metadata"].get("namespace") == k["namespace"], (
                f"{f}: {d['kind']}/{d['metadata']['name']} namespace "
                f"{d['metadata'].get('namespace')!r} != kustomization's {k['namespace']!r}")
    deployments = {d["metadata"]["name"]: d for d in applied_objects() if d["kind"] == "Deployment"}
    for r in k.get("replicas", []):
        assert r["name"] in deployments, f"kustomization.yaml replicas names {r['name']}"
        assert deployments[r["name"]]["spec"]["replicas"] == r["count"], (
            f"replicas of {r['name']}: kustomization.yaml {r['count']}, "
            f"Deployment {deployments[r['name']]['spec']['replicas']}")


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl not installed")
def test_kustomize_build_validates():
    """What `kubectl apply -k` would send (kustomize runs offline, client side)."""
    built = subprocess.run(["kubectl", "kustomize", str(K8S_DIR)], capture_output=True, text=True,
                           timeout=60)
    assert built.returncode == 0, f"kubectl kustomize deploy/k8s failed: {built.stderr}"
    objects = [d for d in yaml.safe_load_all(built.stdout) if d]
    assert sorted((d["kind"], d["metadata"]["name"]) for d in objects) == sorted(
        (d["kind"], d["metadata"]["name"]) for d in applied_objects())
    for d in objects:
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)


# ---------------------------------------------------------------- roles (both platforms)
_VAR = r"[A-Za-z_][A-Za-z0-9_]*"


def interpolate(s: str) -> str:
    """Compose's own variable syntax, as when nothing is set in the environment: ${X:-d} and
    ${X-d} -> d, ${X} and $X -> "", and $$ -> $ (left for the container's shell)."""
    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        return m.group("default") or ""
    return re.sub(rf"\$\$|\$\{{(?P<name>{_VAR})(?::?-(?P<default>[^}}]*))?\}}|\${_VAR}", sub, s)


def expand(s: str, env: dict[str, str | None]) -> str:
    """The container shell's (or Kubernetes' $(X)) expansion of the variables `env` sets;
    others stay as they are."""
    def sub(m: re.Match) -> str:
        name = m.group("b") or m.group("p") or m.group("k8s")
        if name not in env:
            return m.group(0)
        value = env[name] or ""
        if not value and m.group("default") is not None:
            return m.group("default")
        return value
    return re.sub(rf"\$\{{(?P<b>{_VAR})(?::?-(?P<default>[^}}]*))?\}}|\$\((?P<k8s>{_VAR})\)"
                  rf"|\$(?P<p>{_VAR})", sub, s)


def as_argv(value) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return shlex.split(value)
    return [str(v) for v in value]


def flag(cmd: str, name: str) -> str | None:
    """The value of `name VALUE` or `name=VALUE` anywhere in a command line (sh -c scripts too)."""
    m = re.search(rf"(?:^|\s){re.escape(name)}(?:=|\s+)['\"]?([^\s'\";|&)]+)", cmd)
    return m.group(1) if m else None


def override(cmd: str, key: str) -> str | None:
    m = re.search(rf"(?:^|\s)['\"]?{re.escape(key)}=['\"]?([^\s'\";|&)]+)", cmd)
    return m.group(1) if m else None


def port_of(address: str | None) -> str | None:
    if not address:
        return None
    m = re.search(r":(\d+)/?$", address)
    return m.group(1) if m else None


def role_of(argv: list[str], hint: str) -> str | None:
    cmd = " ".join(argv)
    program = Path(argv[0]).name if argv and not argv[0].startswith("-") else ""
    if "demos generate" in cmd:
        return "demos"
    if program in ("curriculum-server", "learner", "actor"):
        role = {"curriculum-server": "curriculum"}.get(program, program)
    else:  # the binary comes from the image's entrypoint: go by the name or the image
        role = next((r for k, r in (("curriculum", "curriculum"), ("learner", "learner"),
                                    ("actor", "actor"), ("demo", "demos")) if k in hint), None)
    if role == "actor" and re.search(r"(?:^|\s)--eval(?:\s|$)", cmd):
        return "eval_actor"
    return role


def facts(image: str, argv: list[str], env: dict[str, str], run_mounts: set[str]) -> dict:
    """What is compared between platforms, from one container or compose service."""
    cmd = " ".join(argv)
    if "demos generate" in cmd:  # in a shell script: only the command's own flags
        cmd = cmd[cmd.index("demos generate"):]
    out: dict = {"image": image}
    for name in FLAGS:
        if (v := flag(cmd, name)) is not None:
            out[name] = v
    for key in OVERRIDES:
        if (v := override(cmd, key)) is not None:
            out[key] = v
    if (c := flag(cmd, "--curriculum")) is not None:
        out["curriculum port"] = port_of(c)
    learner = flag(cmd, "--connect") or env.get("RFCL_LEARNER")
    if learner is not None:
        out["learner port"] = port_of(learner)
    if role_of(argv, "") in ("actor", "eval_actor") or "learner port" in out:
        out["--eval"] = bool(re.search(r"(?:^|\s)--eval(?:\s|$)", cmd))
    # The mount holding the run directory / demo file.
    paths = [out.get(k) for k in ("--run-dir", "--out", "train.dataset_path") if out.get(k)]
    holding = sorted(m for m in run_mounts if any(p == m or p.startswith(m.rstrip("/") + "/")
                                                  for p in paths))
    if holding:
        out["run volume mount"] = holding[-1]
    return out


class Role:
    def __init__(self, where: str, facts: dict, env: dict[str, str], ports: set[int]):
        self.where, self.facts, self.env, self.ports = where, facts, env, ports


def k8s_roles() -> dict[str, list[Role]]:
    roles: dict[str, list[Role]] = {}
    for w in applied_objects():
        if w["kind"] not in ("StatefulSet", "Deployment"):
            continue
        pod = w["spec"]["template"]["spec"]
        claims = {c["metadata"]["name"] for c in w["spec"].get("volumeClaimTemplates", [])}
        claims |= {v["name"] for v in pod.get("volumes", []) if "persistentVolumeClaim" in v}
        for c in pod.get("initContainers", []) + pod["containers"]:
            env = {e["name"]: e.get("value") for e in c.get("env", [])}
            argv = [expand(a, env) for a in as_argv(c.get("command")) + as_argv(c.get("args"))]
            role = role_of(argv, c["name"])
            if role is None:
                continue
            mounts = {m["mountPath"] for m in c.get("volumeMounts", []) if m["name"] in claims}
            ports = {p["containerPort"] for p in c.get("ports", [])}
            where = f"deploy/k8s {w['kind']}/{w['metadata']['name']} container {c['name']}"
            roles.setdefault(role, []).append(Role(where, facts(c["image"], argv, env, mounts),
                                                   env, ports))
    return roles


def compose_ports(svc: dict) -> set[int]:
    ports = set()
    for p in svc.get("ports", []) + svc.get("expose", []):
        if isinstance(p, dict):
            ports.add(int(p["target"]))
        else:
            target = interpolate(str(p)).split("/")[0].rsplit(":", 1)[-1]
            if "-" not in target:
                ports.add(int(target))
    return ports


def compose_named_mounts(svc: dict, named: set[str]) -> set[str]:
    mounts = set()
    for v in svc.get("volumes", []):
        if isinstance(v, dict):
            if v.get("type", "volume") == "volume" and v.get("source") in named:
                mounts.add(v["target"])
        else:
            parts = interpolate(str(v)).split(":")
            if len(parts) >= 2 and parts[0] in named:
                mounts.add(parts[1])
    return mounts


def compose_roles(compose: dict) -> dict[str, list[Role]]:
    named = set((compose.get("volumes") or {}).keys())
    roles: dict[str, list[Role]] = {}
    for name, svc in (compose.get("services") or {}).items():
        env_raw = svc.get("environment") or {}
        if isinstance(env_raw, list):
            env = dict(e.split("=", 1) if "=" in e else (e, None) for e in map(str, env_raw))
        else:
            env = {k: None if v is None else str(v) for k, v in env_raw.items()}
        env = {k: interpolate(v) if v is not None else None for k, v in env.items()}
        # Compose interpolates first (a string command is split after), then the container's
        # shell expands the variables the service sets (command: [sh, -c, "... $$RFCL_X"]).
        argv = []
        for key in ("entrypoint", "command"):
            raw = svc.get(key)
            words = (shlex.split(interpolate(raw)) if isinstance(raw, str)
                     else [interpolate(str(w)) for w in raw or []])
            argv += [expand(w, env) for w in words]
        image = interpolate(str(svc.get("image", "")))
        role = role_of(argv, f"{name} {image}")
        if role is None:
            continue
        where = f"deploy/docker-compose.yml service {name}"
        roles.setdefault(role, []).append(
            Role(where, facts(image or "<no image:>", argv, env, compose_named_mounts(svc, named)),
                 env, compose_ports(svc)))
    return roles


# ------------------------------------------------------------- (b) k8s vs the contract
def test_k8s_roles_match_the_contract():
    roles = k8s_roles()
    problems = []
    for role, expected in CONTRACT.items():
        if role not in roles:
            problems.append(f"{role}: no container in deploy/k8s runs it")
            continue
        for r in roles[role]:
            for field, want in expected.items():
                got = r.facts.get(field, "<absent>")
                if got != want:
                    problems.append(f"{r.where}: {field} is {got!r}, the contract says {want!r}")
            for var in CONTRACT_ENV.get(role, ()):
                if var not in r.env:
                    problems.append(f"{r.where}: env {var} is not set")
            if "RFCL_TOKEN" in r.env:
                problems.append(f"{r.where}: RFCL_TOKEN puts the token in the manifest: "
                                f"use RFCL_TOKEN_FILE={TOKEN_FILE}")
            if r.env.get("RFCL_TOKEN_FILE", TOKEN_FILE) != TOKEN_FILE:
                problems.append(f"{r.where}: RFCL_TOKEN_FILE is {r.env['RFCL_TOKEN_FILE']!r}, "
                                f"the contract says {TOKEN_FILE!r}")
            for var in set(r.env) - KNOWN_ENV:
                if var.startswith("RFCL_"):
                    problems.append(f"{r.where}: env {var} is not one rfcl reads")
            if not CONTRACT_PORTS.get(role, set()) <= r.ports:
                problems.append(f"{r.where}: containerPorts {sorted(r.ports)}, the contract "
                                f"needs {sorted(CONTRACT_PORTS[role])}")
    assert not problems, "\n".join(problems)


def test_k8s_actors_reach_the_services_by_name():
    services = {s["metadata"]["name"]: {p["port"] for p in s["spec"]["ports"]}
                for s in objects_of("Service")}
    for name, ports in CONTRACT_SERVICES.items():
        assert name in services, f"no Service {name}"
        assert ports <= services[name], f"Service {name} ports {sorted(services[name])}, needs {sorted(ports)}"
    roles = k8s_roles()
    for role in ("actor", "eval_actor"):
        for r in roles[role]:
            for var, service in (("RFCL_LEARNER", "rfcl-learner:50052"),
                                 ("RFCL_CURRICULUM", "rfcl-curriculum:50051")):
                assert r.env.get(var) == service, f"{r.where}: {var} is {r.env.get(var)!r}, expected {service!r}"


# ------------------------------------------------------------------- (b) k8s vs compose
@pytest.fixture(scope="module")
def compose():
    if not COMPOSE.exists():
        pytest.skip(f"{COMPOSE.relative_to(ROOT)} does not exist yet: nothing to compare with")
    return yaml.safe_load(COMPOSE.read_text())


def test_compose_and_k8s_agree(compose):
    """Images, ports, config, run/demo paths and the --eval split, role by role."""
    k8s, comp = k8s_roles(), compose_roles(compose)
    problems = []
    for role in CONTRACT:
        if role not in comp:
            problems.append(f"{role}: no service in deploy/docker-compose.yml runs it "
                            f"(deploy/k8s: {[r.where for r in k8s.get(role, [])]})")
            continue
        if role not in k8s:
            problems.append(f"{role}: deploy/k8s does not run it "
                            f"(compose: {[r.where for r in comp[role]]})")
            continue
        for c in comp[role]:
            for k in k8s[role]:
                for field in sorted(set(c.facts) | set(k.facts)):
                    cv, kv = c.facts.get(field, "<absent>"), k.facts.get(field, "<absent>")
                    if cv != kv:
                        problems.append(f"{role} {field}: {k.where} has {kv!r}, "
                                        f"{c.where} has {cv!r}")
                extra = c.ports - k.ports
                if extra:
                    problems.append(f"{role} container ports: {c.where} has {sorted(c.ports)}, "
                                    f"{k.where} has {sorted(k.ports)} (missing {sorted(extra)})")
    assert not problems, "deploy/k8s and deploy/docker-compose.yml differ:\n" + "\n".join(problems)


def test_compose_env_names_are_used_in_k8s(compose):
    """Every variable of the rfcl binaries (KNOWN_ENV) a compose service sets, the k8s container
    of that role sets too (values differ by platform: secret paths and service host names).
    Compose's own template variables (RFCL_CONFIG, RFCL_DEMOS, ... expanded in its commands) are
    compared as the flag values they become, in test_compose_and_k8s_agree."""
    k8s, comp = k8s_roles(), compose_roles(compose)
    problems = []
    for role, services in comp.items():
        for c in services:
            names = set(c.env) & KNOWN_ENV
            for k in k8s.get(role, []):
                missing = sorted(names - set(k.env))
                if missing:
                    problems.append(f"{role} env {missing}: {c.where} sets "
                                    f"{sorted(names)}, {k.where} sets {sorted(k.env)}")
            for var in ("RFCL_TOKEN", ):
                if var in c.env:
                    problems.append(f"{c.where}: {var} puts the token in the compose file")
    for role, wanted in CONTRACT_ENV.items():
        for c in comp.get(role, []):
            if not wanted <= set(c.env):
                problems.append(f"{c.where}: sets {sorted(c.env)}, the contract needs {sorted(wanted)}")
    assert not problems, "\n".join(problems)


# ---------------------------------------------------------------------- k8s wiring
def server_pod() -> tuple[dict, dict]:
    [sts] = [d for d in applied_objects() if d["kind"] == "StatefulSet"]
    return sts, sts["spec"]["template"]["spec"]


def test_services_select_the_server_pod_and_name_its_ports():
    sts, pod = server_pod()
    labels = sts["spec"]["template"]["metadata"]["labels"]
    assert sts["spec"]["selector"]["matchLabels"].items() <= labels.items()
    port_names = {p["name"]: p["containerPort"] for c in pod["containers"] for p in c.get("ports", [])}
    services = {s["metadata"]["name"]: s for s in objects_of("Service")}
    headless = services[sts["spec"]["serviceName"]]
    assert headless["spec"].get("clusterIP") == "None", "the StatefulSet's Service must be headless"
    for name, svc in services.items():
        assert svc["spec"]["selector"].items() <= labels.items(), f"Service {name} selects no pod"
        for p in svc["spec"]["ports"]:
            target = p.get("targetPort", p["port"])
            number = port_names.get(target, target)
            assert number in port_names.values(), f"Service {name} port {p['port']} -> {target}: no such container port"
            assert number == p["port"], f"Service {name} port {p['port']} -> container port {number}"


def test_grpc_services_have_grpc_probes_on_their_ports():
    _, pod = server_pod()
    roles = {role_of(as_argv(c.get("command")) + as_argv(c.get("args")), c["name"]): c
             for c in pod["containers"]}
    for role, port in GRPC_PORT.items():
        c = roles[role]
        for probe in ("readinessProbe", "livenessProbe"):
            assert probe in c, f"{c['name']}: no {probe}"
            assert c[probe].get("grpc", {}).get("port") == port, (
                f"{c['name']} {probe}: {c[probe]} is not a grpc probe on port {port}")


def test_token_comes_from_the_mounted_secret():
    [secret] = objects_of("Secret")
    assert secret["metadata"]["name"] == TOKEN_SECRET
    placeholder = secret["stringData"]["token"]
    # proto/src/auth.rs: 16+ visible ASCII characters. The placeholder must not be a usable token.
    usable = len(placeholder.strip()) >= 16 and all(33 <= ord(ch) <= 126 for ch in placeholder.strip())
    assert not usable, "the Secret template's placeholder would be accepted as a token"
    for w in applied_objects():
        if w["kind"] not in ("StatefulSet", "Deployment"):
            continue
        pod = w["spec"]["template"]["spec"]
        volumes = {v["name"]: v for v in pod.get("volumes", [])}
        for c in pod["containers"]:
            where = f"{w['metadata']['name']}/{c['name']}"
            env = {e["name"]: e for e in c.get("env", [])}
            assert env.get("RFCL_TOKEN_FILE", {}).get("value") == TOKEN_FILE, where
            assert "RFCL_TOKEN" not in env, where
            argv = " ".join(as_argv(c.get("command")) + as_argv(c.get("args")))
            assert "token" not in argv.lower(), f"{where}: the token is never a command-line argument"
            [mount] = [m for m in c.get("volumeMounts", []) if m["mountPath"] == TOKEN_DIR]
            assert mount.get("readOnly") is True, where
            source = volumes[mount["name"]]["secret"]
            assert source["secretName"] == TOKEN_SECRET, where
            assert {"key": "token", "path": "token"} in source.get("items", [{"key": "token", "path": "token"}]), where
        assert pod.get("automountServiceAccountToken") is False, w["metadata"]["name"]
        # Service links would inject RFCL_LEARNER_PORT, RFCL_CURRICULUM_SERVICE_HOST, ...
        assert pod.get("enableServiceLinks") is False, w["metadata"]["name"]


def test_server_pod_volumes():
    sts, pod = server_pod()
    [claim] = sts["spec"]["volumeClaimTemplates"]
    volumes = {v["name"]: v for v in pod["volumes"]}
    assert claim["metadata"]["name"] not in volumes
    containers = {c["name"]: c for c in pod.get("initContainers", []) + pod["containers"]}
    mounts = {n: {m["mountPath"]: m["name"] for m in c.get("volumeMounts", [])} for n, c in containers.items()}
    for n in containers:
        assert mounts[n].get("/runs") == claim["metadata"]["name"], f"{n}: /runs is not the run claim"
    [init] = pod["initContainers"]
    script = " ".join(as_argv(init.get("command")) + as_argv(init.get("args")))
    assert f"--out {DEMOS}" in script and re.search(rf"-[fs] {re.escape(DEMOS)}", script), (
        f"demos: {DEMOS} is to be generated unless present: {script}")
    learner = next(n for n, c in containers.items() if role_of(as_argv(c.get("command")), n) == "learner")
    shm = volumes[mounts[learner]["/dev/shm"]]["emptyDir"]
    assert shm.get("medium") == "Memory" and shm.get("sizeLimit"), f"/dev/shm: {shm}"
    assert "emptyDir" in volumes[mounts[learner]["/tmp/iceoryx2"]]


def test_every_container_has_requests_and_limits():
    for w in applied_objects():
        if w["kind"] not in ("StatefulSet", "Deployment"):
            continue
        pod = w["spec"]["template"]["spec"]
        for c in pod.get("initContainers", []) + pod["containers"]:
            res = c.get("resources", {})
            for part in ("requests", "limits"):
                assert {"cpu", "memory"} <= set(res.get(part, {})), (
                    f"{w['metadata']['name']}/{c['name']}: resources.{part} needs cpu and memory")
