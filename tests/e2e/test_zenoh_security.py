"""Zenoh's own security through `--zenoh-config` (ZenohConfig.config_file), on 127.0.0.1 only.

Every test generates its certificates (a CA, a router certificate for 127.0.0.1/localhost, client
certificates, and a second CA that nobody trusts) with `cryptography` in a temporary directory,
starts a router (ZenohBus in router mode, built from a config file) on a free port with multicast
scouting off, and opens client sessions in this process. Each negative case sits next to the
positive case it mirrors, so a setting that silently does nothing fails the test.

What the installed wheel (eclipse-zenoh 1.10.2) does, as checked here:
- TLS (`tls/` endpoints, server certificate checked against `root_ca_certificate`),
- mutual TLS (`enable_mtls`: the router refuses a client certificate from another CA),
- user/password authentication (`transport/auth/usrpwd`, router side `dictionary_file`; a client
  with credentials is refused by a router that has no dictionary, too),
- access control (`access_control` rules/subjects/policies, subjects by username, interface or
  certificate common name; `declare_queryable`/`reply` rules keep a denied session from serving).
Not covered: `transport/auth/pubkey`, `verify_name_on_connect: false`, TLS between peers.
"""

from __future__ import annotations

import contextlib
import datetime
import ipaddress
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from proto.topics import EPISODES_RAW, WEIGHTS_ANNOUNCE, WEIGHTS_LATEST
from services.common.bus.zenoh_bus import ZenohBus, ZenohConfig, load_zenoh_file
from tests.helpers import assert_messages_equal, build_episode, build_weights, find_free_port
from tests.helpers.zenoh_peer import weights_handler

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[2]
STEP_S = 10.0  # any single delivery
REFUSED_OPEN_MS = 2000  # how long a refused client keeps trying before zenoh.open gives up
QUIET_S = 1.5  # how long a message that must not arrive is waited for (after an allowed one arrived)
SERVICE = "test"
USERS = {"actor": "actor-secret", "learner": "learner-secret", "evaluator": "evaluator-secret"}


# ------------------------------------------------------------------------------------------------
# certificates
# ------------------------------------------------------------------------------------------------


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _write(path: Path, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> tuple[str, str]:
    path.with_suffix(".pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    path.with_suffix(".key").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return str(path.with_suffix(".pem")), str(path.with_suffix(".key"))


def _certificate(
    cn: str, issuer: x509.Name, public_key: ec.EllipticCurvePublicKey, *, ca: bool
) -> x509.CertificateBuilder:
    """A builder of the certificate of ``cn``, valid from five minutes ago for a day, a CA's or not."""
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(issuer)
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )


class _CA:
    def __init__(self, cn: str) -> None:
        self.key = ec.generate_private_key(ec.SECP256R1())
        self.cert = (
            _certificate(cn, _name(cn), self.key.public_key(), ca=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=True,
                    content_commitment=False,
                    key_encipherment=False,
                    data_encipherment=False,
                    key_agreement=False,
                    key_cert_sign=True,
                    crl_sign=True,
                    encipher_only=False,
                    decipher_only=False,
                ),  # fmt: skip
                critical=True,
            )
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(self.key.public_key()), critical=False)
            .sign(self.key, hashes.SHA256())
        )

    def issue(self, cn: str, *, server: bool) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (
            _certificate(cn, self.cert.subject, key.public_key(), ca=False)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(self.key.public_key()), critical=False
            )
        )
        if server:
            san = [x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")]
            builder = builder.add_extension(x509.SubjectAlternativeName(san), critical=False)
        return builder.sign(self.key, hashes.SHA256()), key


@dataclass(frozen=True)
class Pki:
    ca: str  # the CA everybody trusts
    router: tuple[str, str]  # certificate, key (SAN 127.0.0.1 and localhost)
    clients: dict[str, tuple[str, str]]  # common name -> certificate, key, signed by `ca`
    rogue_ca: str  # another CA
    rogue_client: tuple[str, str]  # signed by `rogue_ca`, common name "actor"


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    d = tmp_path_factory.mktemp("pki")
    ca, rogue = _CA("mea test CA"), _CA("rogue CA")
    for name, authority in (("ca", ca), ("rogue-ca", rogue)):
        (d / f"{name}.pem").write_bytes(authority.cert.public_bytes(serialization.Encoding.PEM))
    return Pki(
        ca=str(d / "ca.pem"),
        router=_write(d / "router", *ca.issue("router", server=True)),
        clients={cn: _write(d / cn, *ca.issue(cn, server=False)) for cn in ("actor", "learner", "evaluator")},
        rogue_ca=str(d / "rogue-ca.pem"),
        rogue_client=_write(d / "rogue-client", *rogue.issue("actor", server=False)),
    )


# ------------------------------------------------------------------------------------------------
# config files and sessions
# ------------------------------------------------------------------------------------------------


def _file(tmp_path: Path, name: str, conf: dict) -> str:
    path = tmp_path / f"{name}.json5"
    path.write_text(json.dumps(conf, indent=2))  # JSON is JSON5
    return str(path)


def _tls_router(pki: Pki, port: int, *, mtls: bool) -> dict:
    tls = {"listen_certificate": pki.router[0], "listen_private_key": pki.router[1]}
    if mtls:
        tls |= {"root_ca_certificate": pki.ca, "enable_mtls": True}
    return {
        "mode": "router",
        "listen": {"endpoints": [f"tls/127.0.0.1:{port}"]},
        "transport": {"link": {"protocols": ["tls"], "tls": tls}},
    }


def _tls_client(
    port: int, ca: str, cert: tuple[str, str] | None = None, *, wait: bool = True, scheme: str = "tls"
) -> dict:
    tls: dict = {"root_ca_certificate": ca}
    if cert is not None:
        tls |= {"connect_certificate": cert[0], "connect_private_key": cert[1], "enable_mtls": True}
    conf: dict = {
        "mode": "client",
        "connect": {"endpoints": [f"{scheme}/127.0.0.1:{port}"]},
        "transport": {"link": {"tls": tls}},
    }
    if not wait:  # give up after REFUSED_OPEN_MS instead of waiting for the router forever
        conf["connect"]["timeout_ms"] = REFUSED_OPEN_MS
    return conf


def _tcp_client(port: int, user: str | None, password: str | None, *, wait: bool = True) -> dict:
    conf: dict = {"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}}
    if user is not None:
        conf["transport"] = {"auth": {"usrpwd": {"user": user, "password": password}}}
    if not wait:
        conf["connect"]["timeout_ms"] = REFUSED_OPEN_MS
    return conf


def _bus(path: str, namespace: str) -> ZenohBus:
    return ZenohBus(ZenohConfig(config_file=path, namespace=namespace))


@pytest.fixture
def router(tmp_path: Path) -> Iterator:
    """``router(conf_for_port) -> port``: a router from a config file on a free port, closed afterwards."""
    opened: list[ZenohBus] = []

    def start(make_conf, namespace: str = "sec") -> int:
        last: Exception | None = None
        for _ in range(3):  # the port can be taken between probing and binding
            port = find_free_port()
            path = _file(tmp_path, f"router-{port}", make_conf(port))
            try:
                opened.append(ZenohBus(ZenohConfig(mode="router", config_file=path, namespace=namespace)))
            except zenoh.ZError as exc:
                last = exc
                continue
            return port
        raise RuntimeError(f"no router: {last}")

    yield start
    for bus in reversed(opened):
        bus.close()


@contextlib.contextmanager
def _sessions(*paths: str) -> Iterator[list[ZenohBus]]:
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(_bus(path, "sec")) for path in paths]


def _refused(path: str, namespace: str = "sec") -> str:
    """Open a session that must be refused; returns zenoh's error text (fails if it opens)."""
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError) as err:
        _bus(path, namespace).close()
    assert time.monotonic() - t0 < REFUSED_OPEN_MS / 1000 + STEP_S
    return str(err.value)


def _ready(sub_bus: ZenohBus, instance: str, *others: ZenohBus) -> None:
    """``sub_bus`` has declared its subscriptions and queryables; its token, once ``others`` see it,
    says those declarations have reached them too."""
    sub_bus.declare_alive(SERVICE, instance)
    for bus in others:
        watch = bus.watch_alive(SERVICE)
        assert watch.wait_for(lambda alive: (SERVICE, instance) in alive, timeout=STEP_S), "no token"


def _exchange(a: ZenohBus, b: ZenohBus, seed: int) -> None:
    """``a`` publishes an episode that ``b`` receives intact."""
    sub = b.subscribe(EPISODES_RAW, source="a")
    _ready(b, f"b-{seed}", a)
    sent = build_episode(T=3, seed=seed, actor_id="a")
    a.publish(EPISODES_RAW, sent, source="a")
    got = sub.recv(timeout=STEP_S)
    assert got is not None, "the episode did not arrive"
    assert_messages_equal(got.message, sent)
    sub.close()


# ------------------------------------------------------------------------------------------------
# (a) TLS and mutual TLS
# ------------------------------------------------------------------------------------------------


@pytest.mark.timeout(90)
def test_tls_clients_exchange_and_untrusted_peers_are_refused(router, pki: Pki, tmp_path: Path) -> None:
    port = router(lambda p: _tls_router(pki, p, mtls=False))
    client = _file(tmp_path, "client", _tls_client(port, pki.ca))
    with _bus(client, "sec") as a, _bus(client, "sec") as b:
        assert len(list(a.session.info.routers_zid())) == 1, "not connected to the router"
        _exchange(a, b, seed=1)

    # a client that trusts another CA refuses the router's certificate
    _refused(_file(tmp_path, "wrong-ca", _tls_client(port, pki.rogue_ca, wait=False)))
    # plain TCP to the TLS port gets no session
    _refused(_file(tmp_path, "plain", _tls_client(port, pki.ca, wait=False, scheme="tcp")))


@pytest.mark.timeout(90)
def test_mtls_refuses_a_client_certificate_from_another_ca(router, pki: Pki, tmp_path: Path) -> None:
    port = router(lambda p: _tls_router(pki, p, mtls=True))
    good = [_file(tmp_path, cn, _tls_client(port, pki.ca, pki.clients[cn])) for cn in ("actor", "learner")]
    with _bus(good[0], "sec") as a, _bus(good[1], "sec") as b:
        _exchange(a, b, seed=2)

    rogue = _file(tmp_path, "rogue", _tls_client(port, pki.ca, pki.rogue_client, wait=False))
    _refused(rogue)
    # with mTLS on, a client without any certificate is refused too
    _refused(_file(tmp_path, "anonymous", _tls_client(port, pki.ca, wait=False)))


# ------------------------------------------------------------------------------------------------
# (b) user/password authentication
# ------------------------------------------------------------------------------------------------


def _usrpwd_router(tmp_path: Path, port: int) -> dict:
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    return {
        "mode": "router",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(users)}}},
    }


@pytest.mark.timeout(90)
def test_usrpwd_admits_the_right_password_only(router, tmp_path: Path) -> None:
    port = router(lambda p: _usrpwd_router(tmp_path, p))
    actor = _file(tmp_path, "actor", _tcp_client(port, "actor", USERS["actor"]))
    learner = _file(tmp_path, "learner", _tcp_client(port, "learner", USERS["learner"]))
    with _bus(actor, "sec") as a, _bus(learner, "sec") as b:
        _exchange(a, b, seed=3)

    _refused(_file(tmp_path, "wrong", _tcp_client(port, "actor", "not-the-password", wait=False)))
    _refused(_file(tmp_path, "unknown", _tcp_client(port, "mallory", USERS["actor"], wait=False)))
    _refused(_file(tmp_path, "none", _tcp_client(port, None, None, wait=False)))

    # the check is mutual: credentials do not open a session with a router that does not check them
    plain = router(lambda p: {"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{p}"]}})
    _refused(_file(tmp_path, "unchecked", _tcp_client(plain, "actor", USERS["actor"], wait=False)))
    with _sessions(_file(tmp_path, "anonymous", _tcp_client(plain, None, None))) as [anonymous]:
        assert len(list(anonymous.session.info.routers_zid())) == 1


# ------------------------------------------------------------------------------------------------
# (c) access control
# ------------------------------------------------------------------------------------------------

NO_WEIGHTS_RULE = {
    "id": "no-weights-put",
    "messages": ["put"],
    "flows": ["ingress"],
    "permission": "deny",
    "key_exprs": ["mea/v1/**/weights/**"],
}


def _acl(subject: dict) -> dict:
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [NO_WEIGHTS_RULE],
        "subjects": [{"id": "denied", **subject}],
        "policies": [
            {"id": "workers-publish-no-weights", "rules": ["no-weights-put"], "subjects": ["denied"]}
        ],
    }


def _check_denied_put(denied: ZenohBus, allowed: ZenohBus, listener: ZenohBus) -> None:
    """``denied`` cannot put on weights/**, though its episodes arrive; ``allowed`` can."""
    weights = listener.subscribe(WEIGHTS_ANNOUNCE, source="*")
    episodes = listener.subscribe(EPISODES_RAW, source="*")
    _ready(listener, "listener", denied, allowed)
    ann = build_weights(3, nbytes=1024).announcement(1024)

    denied.publish(WEIGHTS_ANNOUNCE, ann, source="denied")  # dropped by the router
    ep = build_episode(T=3, seed=7, actor_id="denied")
    denied.publish(EPISODES_RAW, ep, source="denied")
    got = episodes.recv(timeout=STEP_S)
    assert got is not None and got.parts == {"source": "denied"}, "the allowed episode did not arrive"
    assert_messages_equal(got.message, ep)

    allowed.publish(WEIGHTS_ANNOUNCE, ann, source="allowed")
    got = weights.recv(timeout=STEP_S)
    assert got is not None, "the allowed weights announcement did not arrive"
    assert got.parts == {"source": "allowed"}, "a denied weights announcement was delivered"
    assert got.message == ann
    late = weights.recv(timeout=QUIET_S)
    assert late is None, f"a denied weights announcement was delivered: {late.key if late else ''}"
    assert listener.stats.bad["weights_announce"] == 0


@pytest.mark.timeout(90)
def test_acl_by_username_denies_weights_put(router, tmp_path: Path) -> None:
    def conf(port: int) -> dict:
        return _usrpwd_router(tmp_path, port) | {"access_control": _acl({"usernames": ["actor"]})}

    port = router(conf)
    files = {u: _file(tmp_path, u, _tcp_client(port, u, USERS[u])) for u in USERS}
    with _sessions(files["actor"], files["learner"], files["evaluator"]) as (actor, learner, evaluator):
        _check_denied_put(actor, learner, evaluator)


@pytest.mark.timeout(90)
def test_acl_by_certificate_common_name_denies_weights_put(router, pki: Pki, tmp_path: Path) -> None:
    def conf(port: int) -> dict:
        return _tls_router(pki, port, mtls=True) | {"access_control": _acl({"cert_common_names": ["actor"]})}

    port = router(conf)
    files = {cn: _file(tmp_path, cn, _tls_client(port, pki.ca, pki.clients[cn])) for cn in pki.clients}
    with _sessions(files["actor"], files["learner"], files["evaluator"]) as (actor, learner, evaluator):
        _check_denied_put(actor, learner, evaluator)


@pytest.mark.timeout(90)
def test_acl_by_interface_denies_weights_put_on_loopback(router, tmp_path: Path) -> None:
    """Every session here comes in on `lo`: the rule holds for all of them, the other topics pass."""

    def conf(port: int) -> dict:
        base = {"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}}
        return base | {"access_control": _acl({"interfaces": ["lo"]})}

    port = router(conf)
    client = _file(tmp_path, "client", _tcp_client(port, None, None))
    with _bus(client, "sec") as a, _bus(client, "sec") as b:
        weights = b.subscribe(WEIGHTS_ANNOUNCE, source="*")
        _exchange(a, b, seed=8)  # episodes pass
        _ready(b, "weights-sub", a)
        a.publish(WEIGHTS_ANNOUNCE, build_weights(1, nbytes=64).announcement(64), source="a")
        assert weights.recv(timeout=QUIET_S) is None, "a weights announcement passed the loopback rule"


# ------------------------------------------------------------------------------------------------
# the example files in deploy/zenoh
# ------------------------------------------------------------------------------------------------


@pytest.mark.timeout(90)
def test_deploy_examples_work_with_generated_certificates(router, pki: Pki, tmp_path: Path) -> None:
    """deploy/zenoh/{tls-router,tls-client}.json5 with their paths and endpoints replaced: mTLS plus
    user/password; the actor may neither announce nor serve weights, the learner may."""
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))

    def rewritten(name: str, values: dict[str, object]) -> dict:
        conf = load_zenoh_file(str(ROOT / "deploy" / "zenoh" / name))
        for key, value in values.items():
            conf.insert_json5(key, json.dumps(value))
        return json.loads(str(conf))

    def router_conf(port: int) -> dict:
        return rewritten(
            "tls-router.json5",
            {
                "listen/endpoints": [f"tls/127.0.0.1:{port}"],
                "transport/link/tls/listen_certificate": pki.router[0],
                "transport/link/tls/listen_private_key": pki.router[1],
                "transport/link/tls/root_ca_certificate": pki.ca,
                "transport/auth/usrpwd/dictionary_file": str(users),
            },
        )

    port = router(router_conf)

    def client(user: str) -> str:
        conf = rewritten(
            "tls-client.json5",
            {
                "connect/endpoints": [f"tls/127.0.0.1:{port}"],
                "transport/link/tls/root_ca_certificate": pki.ca,
                "transport/link/tls/connect_certificate": pki.clients[user][0],
                "transport/link/tls/connect_private_key": pki.clients[user][1],
                "transport/auth/usrpwd/user": user,
                "transport/auth/usrpwd/password": USERS[user],
            },
        )
        return _file(tmp_path, f"example-{user}", conf)

    with _sessions(client("actor"), client("learner"), client("evaluator")) as (actor, learner, evaluator):
        _check_denied_put(actor, learner, evaluator)

        # nor may the actor serve weights: its queryable never reaches the evaluator
        blob = build_weights(5, nbytes=2048)
        for bus, source in ((actor, "actor"), (learner, "learner")):
            bus.serve(WEIGHTS_LATEST, weights_handler(blob.encode(), 5), source=source)
            _ready(bus, f"{source}-serving", evaluator)
        reply = evaluator.query(WEIGHTS_LATEST, timeout=STEP_S, source="learner")
        assert reply is not None and reply.message.digest == blob.digest, "the learner's weights"
        assert evaluator.query(WEIGHTS_LATEST, timeout=QUIET_S, source="actor") is None


# ------------------------------------------------------------------------------------------------
# precedence and errors (no network)
# ------------------------------------------------------------------------------------------------


def test_file_wins_for_keys_it_sets_and_fields_fill_the_rest(tmp_path: Path) -> None:
    path = _file(
        tmp_path,
        "c",
        {
            "mode": "client",
            "connect": {"endpoints": ["tls/127.0.0.1:7447"]},
            "transport": {"link": {"protocols": ["tls"], "tls": {"root_ca_certificate": "/ca.pem"}}},
        },
    )
    conf = ZenohConfig(config_file=path).to_zenoh()
    get = lambda key: json.loads(conf.get_json(key))  # noqa: E731
    assert get("mode") == "client"
    assert get("connect/endpoints") == ["tls/127.0.0.1:7447"]
    assert get("transport/link/protocols") == ["tls"]
    assert get("transport/link/tls/root_ca_certificate") == "/ca.pem"
    assert get("scouting/multicast/enabled") is False  # filled in from the fields
    assert get("connect/timeout_ms") == {"client": -1}  # the file's mode decides the client wait
    assert get("listen/endpoints") == []  # a client listens nowhere

    # the same flags without a file: the project's defaults
    plain = ZenohConfig().to_zenoh()
    assert json.loads(plain.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]

    # a flag that agrees with the file is fine; one that contradicts it is an error naming both
    assert ZenohConfig(mode="client", config_file=path).to_zenoh().get_json("mode") == '"client"'
    with pytest.raises(ValueError, match=r"connect \[\"tcp/10.0.0.1:7447\"\] contradicts connect/endpoints"):
        ZenohConfig(connect=("tcp/10.0.0.1:7447",), config_file=path)
    with pytest.raises(ValueError, match=rf"mode \"router\" contradicts mode = \"client\" .*{path}"):
        ZenohConfig(mode="router", config_file=path)


def test_bad_config_files_are_named_in_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"Zenoh config file .*missing.json5: no such file"):
        ZenohConfig(config_file=str(tmp_path / "missing.json5"))
    broken = tmp_path / "broken.json5"
    broken.write_text('{ mode: "client", ')
    with pytest.raises(ValueError, match=r"Zenoh config file .*broken.json5 is not a valid Zenoh config"):
        ZenohConfig(config_file=str(broken))
    unknown = tmp_path / "unknown.json5"
    unknown.write_text("{ transport: { link: { tls: { root_ca: 'x' } } } }")
    with pytest.raises(ValueError, match=r"unknown\.json5 is not a valid Zenoh config: .*root_ca"):
        ZenohConfig(config_file=str(unknown))


def test_router_cli_reports_a_bad_file_without_traceback(tmp_path: Path, capsys) -> None:
    from services import router as router_cli

    with pytest.raises(SystemExit) as exit_:
        router_cli.main(["--zenoh-config", str(tmp_path / "missing.json5")])
    assert exit_.value.code == 2
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())  # unwrap tyro's box
    assert "Zenoh config file" in err and "missing.json5: no such file" in err, err
    assert "Traceback" not in err

    client = _file(tmp_path, "client", {"mode": "client"})
    assert router_cli.main(["--service.zenoh.config-file", client]) == 2
    err = capsys.readouterr().err
    assert err.startswith('mea router: zenoh mode "router" contradicts mode = "client"')
    assert "Traceback" not in err
