"""Two hosts as two network namespaces joined by a veth pair (deploy/multihost.md, run as written
there): host B runs `mea run --services learner augmenter evaluator` (its embedded router listens
on every interface), host A runs `mea router --connect tcp/B:7447` and one `mea actor`, both with
the run's key (copied from B) and namespace, Zenoh endpoints on the veth addresses, multicast
scouting off. Episodes cross from A to B's learner, weights flow back to A's actor; then the veth is
taken down for longer than Zenoh's lease (10 s: both sides declare the session dead) and brought
up again: nothing crashes or restarts, A's router reconnects by itself (a router retries its
`connect` endpoints after a session closes) and training resumes with the same processes.

Needs root (`ip netns`, veth); skipped otherwise. Each process's /metrics is read from inside its
namespace (`ip netns exec NS python -c ...`)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parents[2]
NAMESPACE = "multihost"
LEASE_SECONDS = 10.0  # Zenoh's default transport/link/tx/lease (10,000 ms)
DOWN_SECONDS = LEASE_SECONDS + 8  # past the lease: both routers drop the session, A's must reconnect
PORTS = {"router": 9100, "launcher": 9100, "learner": 9101, "augmenter": 9102, "evaluator": 9103,
         "actor": 9110}  # fmt: skip
"""Default /metrics ports: each namespace is a host of its own, so the defaults never collide."""
SCRAPE = (
    "import sys, urllib.request\n"
    "try:\n"
    "    r = urllib.request.urlopen(f'http://127.0.0.1:{sys.argv[1]}/metrics', timeout=3)\n"
    "    sys.stdout.write(r.read().decode())\n"
    "except OSError:\n"
    "    sys.exit(3)\n"
)


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20, check=check)


class Hosts:
    """Namespaces ``mea-a-<pid>`` and ``mea-b-<pid>``, a veth pair between them on 10.x.y.1/.2 (x, y
    from the pid), loopback up in each; every process started here is in its own process group."""

    def __init__(self, tmp: Path) -> None:
        pid = os.getpid()
        self.a, self.b = f"mea-a-{pid}", f"mea-b-{pid}"
        self.veth_a, self.veth_b = f"mha{pid}", f"mhb{pid}"  # at most 10 of IFNAMSIZ's 15 characters
        net = f"10.{100 + (pid >> 8) % 150}.{pid % 256}"
        self.addr_a, self.addr_b = f"{net}.1", f"{net}.2"
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        self.created: list[str] = []

    def create(self) -> None:
        for ns in (self.a, self.b):
            res = _ip("netns", "add", ns, check=False)
            if res.returncode != 0:
                pytest.skip(f"`ip netns add {ns}` failed (no network namespaces here): {res.stderr.strip()}")
            self.created.append(ns)
        veth = ["type", "veth", "peer", "name", self.veth_b, "netns", self.b]
        _ip("link", "add", self.veth_a, "netns", self.a, *veth)
        for ns, dev, addr in ((self.a, self.veth_a, self.addr_a), (self.b, self.veth_b, self.addr_b)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "link", "set", dev, "up")

    def link(self, up: bool) -> None:
        """The cable: A's end of the veth up or down (B's end loses its carrier with it)."""
        _ip("-n", self.a, "link", "set", self.veth_a, "up" if up else "down")

    def start(self, name: str, ns: str, *args: str) -> subprocess.Popen:
        """``ip netns exec NS python -m services.cli ARGS`` (ip execs, so the pid is python's)."""
        log = self.tmp / f"{name}.log"
        env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
        cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "services.cli", *args]
        with log.open("w") as out:
            p = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
        self.procs[name], self.logs[name] = p, log
        return p

    def tails(self, n: int = 2500) -> str:
        return "\n".join(
            f"--- {k} (rc={p.poll()}) ---\n{self.logs[k].read_text()[-n:]}" for k, p in self.procs.items()
        )

    def metrics(self, ns: str, port: int) -> dict[str, list[tuple[dict, float]]] | None:
        """Samples by name at 127.0.0.1:PORT/metrics inside ``ns`` (None: not served yet)."""
        res = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", SCRAPE, str(port)],
                             capture_output=True, text=True, timeout=20)  # fmt: skip
        if res.returncode != 0:
            return None
        out: dict[str, list[tuple[dict, float]]] = {}
        for fam in text_string_to_metric_families(res.stdout):
            for s in fam.samples:
                out.setdefault(s.name, []).append((s.labels, s.value))
        return out

    def value(self, ns: str, port: int, name: str, default: float = -1.0, **labels: str) -> float:
        m = self.metrics(ns, port) or {}
        vals = [v for lab, v in m.get(name, []) if all(lab.get(k) == x for k, x in labels.items())]
        return sum(vals) if vals else default

    def pid_of(self, ns: str, port: int) -> int | None:
        m = self.metrics(ns, port) or {}
        info = m.get("mea_service_info", [])
        return int(info[0][0]["pid"]) if info else None

    def stop(self, name: str, timeout: float) -> int | None:
        """SIGTERM (as Ctrl-C would: `mea run` stops its own children), wait up to ``timeout`` s."""
        p = self.procs[name]
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def cleanup(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(10)
        for ns in self.created:
            # whatever is still inside (a child that left its process group) is ours: the namespace is
            # this test's own
            res = _ip("netns", "pids", ns, check=False)
            for pid in res.stdout.split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
            _ip("netns", "del", ns, check=False)  # its veth end goes with it


def _alive(hosts: Hosts, what: str) -> None:
    dead = {k: p.returncode for k, p in hosts.procs.items() if p.poll() is not None}
    assert not dead, f"{what}: processes exited {dead}\n{hosts.tails()}"


def _wait(what: str, hosts: Hosts, cond, timeout: float, every: float = 2.0):
    """Poll ``cond()`` until it returns something truthy; every process must stay alive meanwhile."""
    deadline = time.monotonic() + timeout
    while True:
        _alive(hosts, what)
        got = cond()
        if got:
            return got
        assert time.monotonic() < deadline, f"{what}: not within {timeout:.0f} s\n{hosts.tails()}"
        time.sleep(every)


@pytest.mark.timeout(240)
@pytest.mark.parametrize("host_a", ["services", "mea-run"])
def test_training_across_two_namespaces_survives_a_cable_pull(tmp_path, host_a):
    """``host_a``: A runs `mea router --connect` and `mea actor` by hand ("services"), or one
    `mea run --services actor --connect tcp/B:7447` whose embedded router meshes with B's ("mea-run")."""
    if os.geteuid() != 0:
        pytest.skip("needs root: creates network namespaces and a veth pair (`ip netns`, `ip link`)")
    if shutil.which("ip") is None:
        pytest.skip("needs iproute2's `ip` to create network namespaces")
    hosts = Hosts(tmp_path)
    t0 = time.monotonic()
    timeline: list[tuple[float, str, dict]] = []

    def mark(event: str, **data) -> None:
        timeline.append((round(time.monotonic() - t0, 1), event, data))
        print(f"[{timeline[-1][0]:6.1f} s] {event} {json.dumps(data)}", flush=True)

    try:
        hosts.create()
        a, b = hosts.a, hosts.b
        run_b, dir_a = tmp_path / "host-b" / "run", tmp_path / "host-a"
        dir_a.mkdir(parents=True)
        mark("namespaces", a=f"{a} {hosts.addr_a}", b=f"{b} {hosts.addr_b}")

        # host B: router (every interface) + learner, augmenter, evaluator; creates RUN_DIR/run.key
        launcher = hosts.start("host-b", b, "run", "--services", "learner", "augmenter", "evaluator",
                               "--listen", "tcp/0.0.0.0:7447", "--namespace", NAMESPACE, "--run-dir", str(run_b),
                               "--task", "block_pull", "--learner-preset", "smoke", "--env-steps", "0",
                               "--eval-every", "100000", "--eval-episodes", "1", "--final-eval-episodes", "1",
                               "--stop-grace-seconds", "15", "--log-format", "text")  # fmt: skip
        _wait("B's run key", hosts, lambda: (run_b / "run.key").exists(), 60, every=0.5)
        key_a = dir_a / "run.key"  # the key's trip to host A (scp in deploy/multihost.md), owner-only
        shutil.copyfile(run_b / "run.key", key_a)
        key_a.chmod(0o600)
        mark("run key copied to A")

        # host A: a router meshed with B's, and one actor (demo first, then the learned policy)
        common = ["--service.zenoh.namespace", NAMESPACE, "--service.run-key-file", str(key_a), "--service.log-format", "text"]  # fmt: skip
        if host_a == "services":
            router = hosts.start("host-a-router", a, "router", "--listen", "tcp/127.0.0.1:7447",
                                 "--connect", f"tcp/{hosts.addr_b}:7447", *common)  # fmt: skip
            actor = hosts.start("host-a-actor", a, "actor", "--task", "block_pull", "--policy", "learned",
                                "--demos", "1", "--index", "0", "--service.instance-id", "actor-0",
                                "--service.zenoh.mode", "client", "--service.zenoh.connect", "tcp/127.0.0.1:7447",
                                *common)  # fmt: skip
        else:  # the run's key goes into A's run dir, where `mea run` looks for it
            (dir_a / "run").mkdir()
            shutil.copyfile(key_a, dir_a / "run" / "run.key")
            (dir_a / "run" / "run.key").chmod(0o600)
            router = hosts.start("host-a", a, "run", "--services", "actor", "--connect", f"tcp/{hosts.addr_b}:7447",
                                 "--listen", "tcp/127.0.0.1:7447", "--namespace", NAMESPACE, "--run-dir",
                                 str(dir_a / "run"), "--task", "block_pull", "--demos", "1", "--env-steps", "0",
                                 "--log-format", "text")  # fmt: skip
            actor = None  # a child of A's launcher: known by the pid serving its /metrics

        def learner_steps() -> float:
            return hosts.value(b, PORTS["learner"], "mea_learner_env_steps")

        def actor_version() -> float:
            return hosts.value(a, PORTS["actor"], "mea_policy_version")

        # (a) episodes from A reach B's learner; weights come back to A's actor
        _wait("A's episodes in B's learner", hosts, lambda: learner_steps() > 0, 150)
        _wait("B's weights at A's actor", hosts, lambda: actor_version() > 0, 90)
        raw_in = hosts.value(b, PORTS["learner"], "mea_learner_episodes_in_total", kind="raw")
        mark(
            "flowing",
            learner_env_steps=learner_steps(),
            actor_policy_version=actor_version(),
            raw_episodes_in=raw_in,
        )
        assert raw_in >= 1
        actor_pid = actor.pid if actor is not None else hosts.pid_of(a, PORTS["actor"])
        pids = {
            "launcher": launcher.pid, "router-a": router.pid, "actor": actor_pid,
            **{svc: hosts.pid_of(b, PORTS[svc]) for svc in ("learner", "augmenter", "evaluator")},
        }  # fmt: skip
        assert hosts.pid_of(a, PORTS["actor"]) == actor_pid and None not in pids.values(), pids

        # (b) the cable is pulled for longer than the lease
        steps_down, version_down = learner_steps(), actor_version()
        hosts.link(up=False)
        down_at = time.monotonic()
        mark("link down", learner_env_steps=steps_down, actor_policy_version=version_down)
        time.sleep(DOWN_SECONDS / 2)  # what was in flight (the augmenter's queue on B) lands meanwhile
        _alive(hosts, "during the outage")
        steps_mid, version_mid = learner_steps(), actor_version()
        time.sleep(max(0.0, DOWN_SECONDS - (time.monotonic() - down_at)))
        steps_late, version_late = learner_steps(), actor_version()
        actor_steps_late = hosts.value(a, PORTS["actor"], "mea_actor_env_steps_total")
        mark("still down", seconds=round(time.monotonic() - down_at, 1), learner_env_steps=[steps_mid, steps_late],
             actor_policy_version=[version_mid, version_late], actor_env_steps=actor_steps_late)  # fmt: skip
        # nothing crosses a dead link: the learner's env steps and the actor's weights stand still
        assert steps_late == steps_mid and version_late == version_mid, (steps_mid, steps_late, version_mid)
        hosts.link(up=True)
        up_at = time.monotonic()
        mark("link up")

        # training resumes by itself: more env steps at the learner, newer weights at the actor
        _wait("learner env steps after the link came back", hosts, lambda: learner_steps() > steps_late, 120)
        resumed = time.monotonic() - up_at
        _wait("newer weights at A's actor", hosts, lambda: actor_version() > version_late, 90)
        steps_after, version_after = learner_steps(), actor_version()
        mark("resumed", seconds_after_up=round(resumed, 1), learner_env_steps=steps_after,
             actor_policy_version=version_after)  # fmt: skip
        assert steps_after > steps_late >= steps_down > 0 and version_after > version_late

        # the very same processes: nothing exited, nothing was restarted
        now = {svc: hosts.pid_of(b, PORTS[svc]) for svc in ("learner", "augmenter", "evaluator")}
        assert now == {k: pids[k] for k in now}, (pids, now)
        assert hosts.pid_of(a, PORTS["actor"]) == pids["actor"]
        _alive(hosts, "after the outage")
        assert hosts.value(b, PORTS["launcher"], "mea_launcher_service_restarts_total", default=0.0) == 0
        # A's router and actor sealed with the copied key: B's launcher and learner refused nothing
        unauth = {port: hosts.value(b, port, "mea_bus_unauthenticated_messages_total", default=0.0)
                  for port in (PORTS["launcher"], PORTS["learner"])}  # fmt: skip
        assert set(unauth.values()) == {0.0}, unauth

        # a clean stop: A first, then B (its summary: every episode recorded once, no exits)
        for name in ("host-a-actor", "host-a-router") if host_a == "services" else ("host-a",):
            hosts.stop(name, 20)
        rc = hosts.stop("host-b", 60)
        summary = json.loads((run_b / "summary.json").read_text())
        learner = summary["instances"]["learner-0"]["counters"]
        mark("stopped", launcher_rc=rc, episodes_recorded=summary["episodes_recorded"],
             learner_env_steps=learner["env_steps"], learner_rejected=learner.get("rejected"))  # fmt: skip
        assert rc == 0, hosts.tails()
        assert all(v["exitcode"] in (None, 0) for v in summary["instances"].values()), summary
        assert summary["episodes_recorded"] >= 2 and learner["env_steps"] >= steps_after
    finally:
        hosts.cleanup()
        (tmp_path / "timeline.json").write_text(json.dumps(timeline, indent=1))
    assert not any(ns in _ip("netns", "list").stdout for ns in (hosts.a, hosts.b))
