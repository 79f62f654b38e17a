"""deploy/docker-compose.yml against the code: the services `mea run` starts, each command parsed by
its own `mea` subcommand's flag parser into the config services/plan.py derives for `mea run`, the
healthchecks on the ports those configs serve /metrics on, the actors' restart wrapper, the run-key
one-liner, and `docker-compose config` where docker-compose is installed."""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from proto.seeds import actor_seed_base
from services import plan
from services.augmenter.config import AugmenterConfig
from services.cli import COMMANDS
from services.common import run_key
from services.common.bus.zenoh_bus import ZenohConfig
from services.common.config import ServiceConfig
from services.common.metrics import DEFAULT_PORTS
from services.learner.config import GASV2_PRESETS, preset_name
from services.run_config import RunConfig
from services.variants import network_group, variant

pytestmark = pytest.mark.contract

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "docker-compose.yml"
GPU = DEPLOY / "docker-compose.gpu.yml"
ENV_EXAMPLE = DEPLOY / ".env.example"

ACTORS = [f"actor-{i}" for i in range(4)]
MEA_SERVICES = {"router", "learner", "augmenter", "evaluator", "inference", *ACTORS}
SERVICES = {"init", "prometheus", "grafana", *MEA_SERVICES}
KIND = {"serve": "inference"}  # `mea` subcommand -> service kind (DEFAULT_PORTS, instance ids)
RUN_SERVICES = ("learner", "augmenter", "evaluator", "actor")  # what `mea run` starts (plan.py)


def read_env(path: Path) -> dict[str, str]:
    """KEY=VALUE lines (no quotes, no expansion), as .env.example is written."""
    env = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, sep, value = line.partition("=")
            assert sep, f"{path.name}: not KEY=VALUE: {line!r}"
            env[key.strip()] = value.strip()
    return env


_VAR = re.compile(r"\$(?:(\$)|\{(\w+)(?:(:?[-?])([^}]*))?\}|(\w+))")


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """Compose's variable substitution: $$, ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?err}, $VAR.
    A variable neither set nor defaulted fails the test (compose would substitute "" and warn)."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        dollar, name, op, arg, bare = m.groups()
        if dollar:
            return "$"
        name = name or bare
        if op in (":-", "-") and (name not in env or (op == ":-" and not env[name])):
            return arg
        assert name in env, f"${{{name}}} is not set in {ENV_EXAMPLE.name} and has no default"
        return env[name]

    return _VAR.sub(sub, value)


def load(path: Path, env: dict[str, str] | None = None) -> dict:
    data = yaml.safe_load(path.read_text())
    return interpolate(data, read_env(ENV_EXAMPLE) if env is None else env)


def mea_argv(svc: dict) -> list[str]:
    """The `mea` argv of a service: its command after the image's entrypoint `mea`, or after the
    actors' wrapper (which ends in `exec mea "$@"`, $0 being the 4th entry)."""
    entry = svc.get("entrypoint")
    if entry is not None:
        assert entry[:2] == ["/bin/sh", "-c"] and entry[2].rstrip().endswith('exec mea "$@"'), entry
        assert entry[3:] == ["mea"], entry
    return [str(a) for a in svc["command"]]


def parse_command(argv: list[str]) -> tuple[str, Any]:
    """(subcommand, config) from `mea` argv: the subcommand's own main(), with its run() replaced so
    nothing starts."""
    command, rest = argv[0], argv[1:]
    assert command in COMMANDS, f"`mea {command}` is not a mea command"
    module = importlib.import_module(COMMANDS[command][0])
    captured = []
    original = module.run
    module.run = lambda cfg, *a, **kw: captured.append(cfg) or 0
    try:
        assert module.main(rest) == 0
    except SystemExit as exc:  # tyro/argparse refused a flag: show which command
        pytest.fail(f"mea {command} {' '.join(rest)}: flags refused (exit {exc.code})")
    finally:
        module.run = original
    return command, captured[0]


def learner_preset_of_run(preset: str) -> str:
    """The `mea run --learner-preset` whose learner preset is ``preset`` (GASv2 presets map back)."""
    return next((k for k in GASV2_PRESETS if preset_name("gasv2", k) == preset), preset)


def settings_for(run: RunConfig) -> dict[str, str]:
    """The env-file settings that stand for what plan.py derives from ``run``'s task and variant."""
    v = variant(run.variant)
    preset = plan.learner_preset(run)
    augment = AugmenterConfig().augment
    return {
        "TASK": run.task,
        "VARIANT": run.variant,
        "SEED": str(run.seed),
        "ACTOR_SEED_BASE": str(actor_seed_base(run.seed, run.resumes)),
        "ENV_STEPS": str(run.env_steps),
        "DEMOS": str(run.resolved_demos()),
        "RANDOM_STEPS": str(run.resolved_random_steps()),
        "DEPTH_IMAGE_FLAG": "--depth-image" if v.depth_image else "--no-depth-image",
        "LEARNER_PRESET": preset,
        "LEARNER_DEVICE": run.learner_device,
        # a GASv2 learner has no symmetry group: it drops the flag (learner.config.without_foreign_group)
        "NET_GROUP": "c4" if v.algorithm == "gasv2" else network_group(run.task),
        "OBSERVATION": v.observation,
        "AUGMENT_OBSERVATION": augment.observation if v.observation == "dsa" else v.observation,
        "MEA_ON": run.resolved_mea_on() if v.mea else "none",
        "SUCCESS_ROTATIONS": str(run.resolved_success_rotations()),
        "EVAL_EVERY": str(run.eval_every),
        "EVAL_EPISODES": str(run.eval_episodes),
        "FINAL_EVAL_EPISODES": str(run.final_eval_episodes),
    }


def run_of(env: dict[str, str]) -> RunConfig:
    """The `mea run` an env file stands for."""
    return RunConfig(
        task=env["TASK"],
        variant=env["VARIANT"],
        learner_preset=learner_preset_of_run(env["LEARNER_PRESET"]),
        learner_device=env["LEARNER_DEVICE"],
        seed=int(env["SEED"]),
        env_steps=int(env["ENV_STEPS"]),
        demos=int(env["DEMOS"]),
        eval_every=int(env["EVAL_EVERY"]),
        eval_episodes=int(env["EVAL_EPISODES"]),
        final_eval_episodes=int(env["FINAL_EVAL_EPISODES"]),
        namespace=env["NAMESPACE"],
        run_dir=Path(env["RUN_DIR"]),
    )


def expected_service(name: str, kind: str, env: dict[str, str]) -> ServiceConfig:
    """Identity, transport, metrics and logs every mea service in compose gets."""
    if kind == "router":  # of its zenoh section only the namespace and the config file are used
        zenoh = ZenohConfig(namespace=env["NAMESPACE"])
    else:
        zenoh = ZenohConfig(mode="client", connect=(env["ZENOH_CONNECT"],), namespace=env["NAMESPACE"])
    return ServiceConfig(
        instance_id=name if kind == "actor" else f"{kind}-0",
        zenoh=zenoh,
        metrics_port=9110 if kind == "actor" else -1,
        metrics_addr="0.0.0.0",
        log_format=env["LOG_FORMAT"],
        run_key_file=env["RUN_KEY_FILE"],
    )


def differences(got: Any, expected: Any, prefix: str = "") -> list[str]:
    """The fields (dotted) where two configs differ, with both values."""
    if dataclasses.is_dataclass(got) and type(got) is type(expected):
        out = []
        for f in dataclasses.fields(got):
            out += differences(getattr(got, f.name), getattr(expected, f.name), f"{prefix}{f.name}.")
        return out
    return [] if got == expected else [f"{prefix.rstrip('.')}: compose {got!r}, plan {expected!r}"]


def metrics_port(kind: str, cfg: Any) -> int:
    port = cfg.service.metrics_port
    if port < 0:
        port = DEFAULT_PORTS[kind] + (cfg.index if kind == "actor" else 0)
    return port


def readme_rows() -> list[dict[str, str]]:
    """The variant table of deploy/README.md, one dict per row keyed by its header."""
    lines = [line for line in (DEPLOY / "README.md").read_text().splitlines() if line.startswith("| TASK |")]
    assert len(lines) == 1, "deploy/README.md: one table headed | TASK | ..."
    text = (DEPLOY / "README.md").read_text().split(lines[0], 1)[1]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = []
    for line in text.splitlines()[2:]:
        if not line.startswith("|"):
            break
        rows.append(
            dict(zip(header, (c.strip().strip("`") for c in line.strip("|").split("|")), strict=True))
        )
    return rows


# ------------------------------------------------------------------------------------------- (a)


def test_services_volumes_and_healthchecks():
    compose = load(COMPOSE)
    services = compose["services"]
    assert set(services) == SERVICES
    assert set(compose["volumes"]) == {"runs", "prometheus-data", "grafana-data"}
    env = read_env(ENV_EXAMPLE)
    for name in MEA_SERVICES | {"init"}:
        svc = services[name]
        assert svc["image"] == env["MEA_IMAGE"], name
        assert "runs:/runs" in svc["volumes"], f"{name}: the run directory's volume"
    assert services["init"]["build"]["context"] == ".." and services["init"]["restart"] == "no"
    for name in MEA_SERVICES:
        svc = services[name]
        assert svc["depends_on"]["init"] == {"condition": "service_completed_successfully"}, name
        if name != "router":
            assert svc["depends_on"]["router"] == {"condition": "service_healthy"}, name
        assert svc["init"] is True and svc["restart"] == "on-failure", name
        assert f"{env['ZENOH_DIR']}:/etc/mea/zenoh:ro" in svc["volumes"], name
    for name in SERVICES - {"init"}:
        test = services[name]["healthcheck"]["test"]
        assert test[0] == "CMD" and len(test) > 1, name
    prom = services["prometheus"]
    assert "./prometheus:/etc/prometheus:ro" in prom["volumes"]
    assert "--config.file=/etc/prometheus/prometheus.yml" in prom["command"]
    assert prom["image"].startswith("prom/prometheus:")
    graf = services["grafana"]
    assert graf["image"].startswith("grafana/grafana-oss:")
    assert "./grafana/provisioning:/etc/grafana/provisioning:ro" in graf["volumes"]
    assert "./grafana/dashboards:/var/lib/grafana/dashboards:ro" in graf["volumes"]
    assert services["router"]["ports"] == [f"{env['ROUTER_BIND']}:{env['ROUTER_PORT']}:7447"]


def test_every_variable_is_in_env_example():
    used = set()
    for path in (COMPOSE, GPU):
        used |= {m.group(2) or m.group(5) for m in _VAR.finditer(path.read_text()) if not m.group(1)}
    env = read_env(ENV_EXAMPLE)
    assert used - set(env) == set(), "variables the compose files use but .env.example does not set"
    # ACTOR_STARTS_FILE and the wrapper's own variables are $$-escaped: the container's shell expands them
    assert set(env) - used - {"COMPOSE_PROJECT_NAME", "COMPOSE_PROFILES"} == set(), "settings nothing uses"


def test_actor_profiles_count_up():
    services = load(COMPOSE)["services"]
    assert "profiles" not in services["actor-0"]
    for i, name in enumerate(ACTORS[1:], start=1):
        assert services[name]["profiles"] == [f"actors-{n}" for n in range(i + 1, len(ACTORS) + 1)], name
    assert re.fullmatch(r"actors-[1-4]", read_env(ENV_EXAMPLE)["COMPOSE_PROFILES"])


def test_gpu_override_reserves_a_gpu_for_the_learner():
    gpu = load(GPU)
    assert set(gpu["services"]) == {"learner"}
    learner = gpu["services"]["learner"]
    devices = learner["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
    env = read_env(ENV_EXAMPLE)
    assert learner["build"]["args"]["TORCH_INDEX_URL"] == env["TORCH_GPU_INDEX_URL"]
    assert learner["image"] == env["MEA_GPU_IMAGE"] != env["MEA_IMAGE"]


def test_dockerfile():
    text = (ROOT / "Dockerfile").read_text()
    pin = re.search(r'"torch==([^"]+)"', (ROOT / "pyproject.toml").read_text()).group(1)
    assert f'"torch=={pin}"' in text, "the Dockerfile installs pyproject's torch pin"
    assert "ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu" in text
    assert re.search(
        r"^FROM python:3\.11-slim-bookworm|^ARG PYTHON_IMAGE=python:3\.11-slim-bookworm", text, re.M
    )
    assert re.search(r"^USER mea$", text, re.M) and 'ENTRYPOINT ["mea"]' in text
    ignored = set((ROOT / ".dockerignore").read_text().split())
    assert {"runs", ".venv", ".git", "**/__pycache__", ".pytest_cache"} <= ignored


def test_scrape_targets_are_compose_services(tmp_path):
    """Every target of deploy/prometheus/prometheus.yml is a compose service serving /metrics on that
    port, and the services that always run (and the actors .env.example starts) are scraped."""
    prom_file = DEPLOY / "prometheus" / "prometheus.yml"
    if not prom_file.exists():
        pytest.skip("deploy/prometheus/prometheus.yml not written yet")
    targets = set()
    for job in yaml.safe_load(prom_file.read_text())["scrape_configs"]:
        for sc in job.get("static_configs", []):
            targets |= set(sc["targets"])
    services = load(COMPOSE)["services"]
    ports = {}
    for name in MEA_SERVICES:
        command, cfg = parse_command(mea_argv(services[name]))
        ports[name] = metrics_port(KIND.get(command, command), cfg)
        assert f"http://127.0.0.1:{ports[name]}/metrics" in services[name]["healthcheck"]["test"][-1], name
    for target in targets:
        host, _, port = target.rpartition(":")
        assert ports.get(host) == int(port), f"{target}: no compose service serves /metrics there"
    enabled = int(read_env(ENV_EXAMPLE)["COMPOSE_PROFILES"].split("-")[1])
    always = {"router", "learner", "augmenter", "evaluator", "inference", *ACTORS[:enabled]}
    assert {f"{n}:{ports[n]}" for n in always} <= targets


# ------------------------------------------------------------------------------------------- (b)


def test_env_example_is_its_variant():
    """.env.example's derived settings are what plan.py derives for its TASK, VARIANT and preset."""
    env = read_env(ENV_EXAMPLE)
    expected = settings_for(run_of(env))
    assert {k: env[k] for k in expected} == expected


def test_readme_variant_table_matches_plan():
    rows = readme_rows()
    assert len(rows) >= 5
    for row in rows:
        run = RunConfig(task=row["TASK"], variant=row["VARIANT"],
                        learner_preset=learner_preset_of_run(row["LEARNER_PRESET"]))  # fmt: skip
        expected = settings_for(run)
        assert row == {k: expected[k] for k in row}, f"deploy/README.md row {row['TASK']} {row['VARIANT']}"


def _check_stack(env: dict[str, str]) -> None:
    """Every mea service's command parses with its own subcommand's parser into the config plan.py
    gives `mea run`'s service of the same name (service settings: the compose ones)."""
    services = load(COMPOSE, env)["services"]
    run = run_of(env)
    run_dir = Path(env["RUN_DIR"])
    for name in sorted(MEA_SERVICES):
        command, cfg = parse_command(mea_argv(services[name]))
        kind = KIND.get(command, command)
        assert name.split("-")[0] == kind, f"{name} runs `mea {command}`"
        assert not differences(cfg.service, expected_service(name, kind, env)), name
        if kind == "router":
            assert cfg.listen == (env["ROUTER_LISTEN"],)
            continue
        if kind == "inference":  # follows the learner: no pinned weights, the defaults otherwise
            assert cfg.weights == "" and cfg.limits_file == env["SERVE_LIMITS_FILE"]
            continue
        assert kind in RUN_SERVICES
        index = int(name.split("-")[1]) if kind == "actor" else 0
        expected = plan.config_for(run, run_dir, kind, index)
        if kind == "learner":  # restarted containers resume (plan.restarted does so for `mea run`)
            expected = dataclasses.replace(expected, resume=True)
        diff = differences(dataclasses.replace(cfg, service=expected.service), expected)
        assert not diff, f"{name}: compose's flags differ from services/plan.py: {diff}"


def test_compose_commands_parse_to_mea_run_configs():
    _check_stack(read_env(ENV_EXAMPLE))


@pytest.mark.parametrize(
    "row", readme_rows(), ids=lambda r: f"{r['TASK']}-{r['VARIANT']}-{r['LEARNER_PRESET']}"
)
def test_every_variant_row_gives_mea_runs_configs(row):
    env = read_env(ENV_EXAMPLE) | row | {"SEED": "3", "ENV_STEPS": "5000", "NAMESPACE": "b"}
    env |= settings_for(run_of(env))  # ACTOR_SEED_BASE and the rest follow the seed and budget
    _check_stack(env)


def test_actor_wrapper_restarts_like_mea_run(tmp_path):
    """The actors' entrypoint runs `mea` with the command as is on the first start, and with fresh
    seeds and no demos from the second on (plan.restarted)."""
    if shutil.which("sh") is None:
        pytest.skip("no sh")
    env = read_env(ENV_EXAMPLE)
    actor = load(COMPOSE)["services"]["actor-0"]
    fake = tmp_path / "bin" / "mea"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\nprintf "%s\\n" "$@"\n')
    fake.chmod(0o755)
    starts = tmp_path / "run" / "actors" / "actor-0.starts"
    shell_env = {"PATH": f"{fake.parent}:{os.environ['PATH']}", "ACTOR_STARTS_FILE": str(starts)}
    argvs = []
    for _ in range(3):
        out = subprocess.run(actor["entrypoint"] + mea_argv(actor), env=shell_env, capture_output=True,
                             text=True, timeout=30, check=True)  # fmt: skip
        argvs.append(out.stdout.splitlines())
    assert argvs[0] == mea_argv(actor)
    assert starts.read_text().strip() == "3"
    spec = plan.ChildSpec(
        "actor", "actor-0", "", config=plan.config_for(run_of(env), Path(env["RUN_DIR"]), "actor", 0)
    )
    for n in (1, 2):
        _, cfg = parse_command(argvs[n])
        expected = plan.restarted(spec, n).config
        assert not differences(dataclasses.replace(cfg, service=expected.service), expected)
        assert cfg.demos == 0 and cfg.incarnation == n


def test_init_makes_the_run_key(tmp_path):
    init = load(COMPOSE)["services"]["init"]
    assert init["entrypoint"] == ["python", "-c"]
    run_dir, key_file = tmp_path / "runs" / "r", tmp_path / "runs" / "r" / "run.key"
    env = {**os.environ, "RUN_DIR": str(run_dir), "RUN_KEY_FILE": str(key_file), "PYTHONPATH": str(ROOT)}
    out = [subprocess.run([sys.executable, "-c", *init["command"]], env=env, capture_output=True, text=True,
                          timeout=60, check=True) for _ in range(2)]  # fmt: skip
    key = run_key.load(key_file)
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
    assert out[0].stdout == out[1].stdout == f"run key {run_key.describe(key)} {key_file}\n"  # kept
    env |= {"RUN_DIR": str(tmp_path / "noauth"), "RUN_KEY_FILE": ""}
    out = subprocess.run([sys.executable, "-c", *init["command"]], env=env, capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    assert out.stdout == "bus not authenticated\n" and (tmp_path / "noauth").is_dir()


# ------------------------------------------------------------------------------------------- (c)


@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, GPU]], ids=["cpu", "gpu"])
def test_docker_compose_config(files):
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("docker-compose not installed: .ci/run installs it from the distribution's packages "
                    "where apt is available")  # fmt: skip
    args = [exe, *(a for f in files for a in ("-f", str(f))), "--env-file", str(ENV_EXAMPLE)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("COMPOSE_")}
    out = subprocess.run([*args, "config"], capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert out.returncode == 0, out.stderr
    assert "WARNING" not in out.stderr, out.stderr
    resolved = yaml.safe_load(out.stdout)
    assert set(resolved["services"]) == SERVICES
    names = subprocess.run([*args, "config", "--services"], capture_output=True, text=True, timeout=120,
                           cwd=ROOT, env=env, check=True)  # fmt: skip
    assert set(names.stdout.split()) == SERVICES
