"""Zenoh transport security as shipped in deploy/secure/, on real Zenoh sessions in-process.

The router is deploy/secure/router.json5 itself, with only this test's certificate paths,
password file and loopback port put in; the clients are the templates of
deploy/secure/clients/ filled in as the README says.  So what passes here is the example an
operator deploys: mutual TLS, user/password and the access-control rules.

Certificates are made at run time (``trustme``): a CA, the router's certificate for
127.0.0.1, one client certificate per subject of router.json5, and an impostor CA.

A refused message leaves no trace, so every "nothing arrives" here comes with a positive
control that arrives after it on the same path (see :func:`test_radar_cannot_put_anywhere_else`).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import string
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import trustme
import zenoh

from service.engine import EngineConfig
from service.pipeline.partition import Partition
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions
from service.wire.keys import Keys
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, wait_for

ROOT = Path(__file__).resolve().parents[1]
SECURE = ROOT / "deploy" / "secure"
#: The prefix router.json5's rules are written for.
KEYS = Keys("fusion")
#: The subjects of router.json5: the service, two radars, an operator.
SERVICE, RADAR_A, RADAR_B, OPERATOR = "topofusion", "radar-A", "radar-B", "operator"
#: Long enough for a loopback round trip on a loaded machine; the waits end as soon as the
#: awaited message is there.
WAIT_S = 10.0


@dataclass(frozen=True)
class Pki:
    """The files the router and the clients read, and each user's password."""

    dir: Path
    impostor_dir: Path
    passwords: dict[str, str]


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    ours, impostor = trustme.CA(), trustme.CA()
    out = tmp_path_factory.mktemp("pki")
    ours.cert_pem.write_to_path(str(out / "ca.pem"))
    router = ours.issue_cert("127.0.0.1", "localhost", common_name="localhost")
    router.cert_chain_pems[0].write_to_path(str(out / "router.pem"))
    router.private_key_pem.write_to_path(str(out / "router.key"))
    for subject in (SERVICE, RADAR_A, RADAR_B, OPERATOR):
        cert = ours.issue_cert(f"{subject}.invalid", common_name=subject)
        cert.cert_chain_pems[0].write_to_path(str(out / f"{subject}.pem"))
        cert.private_key_pem.write_to_path(str(out / f"{subject}.key"))
    # Radar A's name on a certificate of another CA: the router must not take it.
    forged_dir = tmp_path_factory.mktemp("impostor")
    ours.cert_pem.write_to_path(str(forged_dir / "ca.pem"))  # it trusts the real router
    forged = impostor.issue_cert(f"{RADAR_A}.invalid", common_name=RADAR_A)
    forged.cert_chain_pems[0].write_to_path(str(forged_dir / f"{RADAR_A}.pem"))
    forged.private_key_pem.write_to_path(str(forged_dir / f"{RADAR_A}.key"))
    passwords = {s: secrets.token_urlsafe(18) for s in (SERVICE, RADAR_A, RADAR_B, OPERATOR)}
    (out / "users.txt").write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    return Pki(out, forged_dir, passwords)


@dataclass(frozen=True)
class Network:
    """The secured router and the client configurations to reach it."""

    pki: Pki
    router: str  # host:port
    configs: Path

    def config_file(
        self,
        template: str,
        password: str,
        radar_id: str = "",
        cert_dir: Path | None = None,
    ) -> Path:
        """``deploy/secure/clients/<template>.json5.in`` filled in, as a JSON5 file."""
        text = string.Template((SECURE / "clients" / f"{template}.json5.in").read_text()).substitute(
            ZENOH_ROUTER=self.router,
            CERT_DIR=str(cert_dir or self.pki.dir),
            ZENOH_PASSWORD=password,
            RADAR_ID=radar_id,
        )
        path = self.configs / f"{template}-{radar_id or 'x'}-{secrets.token_hex(4)}.json5"
        path.write_text(text)
        return path

    def config(self, subject: str, **kw: Any) -> zenoh.Config:
        """The configuration of one of router.json5's subjects, with its own password."""
        kw.setdefault("password", self.pki.passwords[subject])
        if subject.startswith("radar-"):
            kw.setdefault("radar_id", subject.removeprefix("radar-"))
            template = "radar"
        else:
            template = {SERVICE: "service", OPERATOR: "reader"}[subject]
        return zenoh.Config.from_file(str(self.config_file(template, **kw)))


def router_config(pki: Pki, port: int) -> zenoh.Config:
    """deploy/secure/router.json5 with this test's files and port, everything else as shipped."""
    conf = zenoh.Config.from_file(str(SECURE / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    tls = "transport/link/tls"
    conf.insert_json5(f"{tls}/root_ca_certificate", json.dumps(str(pki.dir / "ca.pem")))
    conf.insert_json5(f"{tls}/listen_certificate", json.dumps(str(pki.dir / "router.pem")))
    conf.insert_json5(f"{tls}/listen_private_key", json.dumps(str(pki.dir / "router.key")))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(pki.dir / "users.txt")))
    return conf


@contextlib.contextmanager
def secured_router(pki: Pki, configs: Path) -> Iterator[Network]:
    """The router of router.json5 on a free loopback port, closed after."""
    port = free_port()
    router = zenoh.open(router_config(pki, port))
    try:
        yield Network(pki, f"127.0.0.1:{port}", configs)
    finally:
        router.close()


@pytest.fixture(scope="module")
def net(pki: Pki, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Network]:
    with secured_router(pki, tmp_path_factory.mktemp("zenoh-configs")) as network:
        yield network


@contextlib.contextmanager
def opened(*configs: zenoh.Config) -> Iterator[list[zenoh.Session]]:
    """Sessions on ``configs``, all closed on the way out (an open session hangs the exit)."""
    with contextlib.ExitStack() as stack:
        sessions = []
        for conf in configs:
            s = zenoh.open(conf)
            stack.callback(s.close)
            sessions.append(s)
        yield sessions


class Heard:
    """Every sample a subscriber gets: ``(key, payload)`` in arrival order."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._lock = threading.Lock()
        self._samples: list[tuple[str, bytes]] = []
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    @property
    def samples(self) -> list[tuple[str, bytes]]:
        with self._lock:
            return list(self._samples)

    def payloads(self, key: str) -> list[bytes]:
        return [p for k, p in self.samples if k == key]

    def wait(self, key: str, payload: bytes) -> None:
        wait_for(lambda: (key, payload) in self.samples, timeout=WAIT_S)


def wait_matched(session: zenoh.Session, key: str) -> None:
    """Wait until ``session`` knows of a subscriber on ``key`` (through the router's rules)."""
    pub = session.declare_publisher(key)
    try:
        wait_for(lambda: pub.matching_status.matching, timeout=WAIT_S)
    finally:
        pub.undeclare()


# --- 1. a radar's own keys ------------------------------------------------------------------


def test_radar_publishes_its_own_site_and_plots_to_the_service(net: Network) -> None:
    with opened(net.config(SERVICE), net.config(RADAR_A)) as (service, radar):
        heard = Heard(service, KEYS.site("*")), Heard(service, KEYS.plots("*"))
        for key, listener in zip((KEYS.site("A"), KEYS.plots("A")), heard, strict=True):
            # A declared publisher, as `topofusion replay` uses: it puts only once it knows of
            # a subscriber, which only the router can tell it.
            pub = radar.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            try:
                wait_for(lambda p=pub: p.matching_status.matching, timeout=WAIT_S)
                pub.put(b'{"radar_id": "A"}')
                listener.wait(key, b'{"radar_id": "A"}')
            finally:
                pub.undeclare()


# --- 2. and nothing else --------------------------------------------------------------------

#: Keys radar A may not put on, and who may (the witness whose put must arrive).
FORBIDDEN_TO_RADAR_A = {
    "another radar's plots": (KEYS.plots("B"), RADAR_B),
    "another radar's site": (KEYS.site("B"), RADAR_B),
    "an AIS source's reports": (KEYS.ais("A"), None),
    "its own tracks (an output)": (KEYS.tracks("A"), SERVICE),
    "a pair set": (KEYS.pairs("A", "B"), SERVICE),
    "the rejections": (KEYS.errors, SERVICE),
    "the system tracks": (KEYS.system_tracks, SERVICE),
    "the bias estimate": (KEYS.biases, SERVICE),
}


@pytest.mark.parametrize("what", list(FORBIDDEN_TO_RADAR_A))
def test_radar_cannot_put_anywhere_else(net: Network, what: str) -> None:
    """Radar A puts on a key it may not use, then on its own plots.  Radar A's messages travel
    one TLS link in order, and the router handles them in order: once the second reaches the
    service, the first has been dropped or forwarded, and a forwarded one is queued to its
    listener before anything put later.  So when the witness's put (one that may be made on
    that key) arrives at the listener, the radar's forged one would be there before it."""
    key, witness = FORBIDDEN_TO_RADAR_A[what]
    # An input key is heard by the service, an output key by the operator.
    listener_subject = SERVICE if KEYS.classify(key) is not None else OPERATOR
    subjects = [RADAR_A, listener_subject] + ([SERVICE] if listener_subject != SERVICE else [])
    if witness is not None and witness not in subjects:
        subjects.append(witness)
    with opened(*(net.config(s) for s in subjects)) as sessions:
        by = dict(zip(subjects, sessions, strict=True))
        radar, service = by[RADAR_A], by[SERVICE]
        listener = Heard(by[listener_subject], key)
        control = Heard(service, KEYS.plots("A"))
        if witness is not None:
            wait_matched(by[witness], key)  # the listener's subscription is in place
        wait_matched(radar, KEYS.plots("A"))

        put_json(radar, key, b"forged by radar A")
        put_json(radar, KEYS.plots("A"), b"control")
        control.wait(KEYS.plots("A"), b"control")
        if witness is not None:
            pub = by[witness].declare_publisher(key)
            try:
                wait_for(lambda: pub.matching_status.matching, timeout=WAIT_S)
                pub.put(b"genuine")
                listener.wait(key, b"genuine")
            finally:
                pub.undeclare()
        assert listener.payloads(key) == ([b"genuine"] if witness is not None else [])


def test_radar_cannot_subscribe_or_query(net: Network) -> None:
    """A radar's subscription to another radar's plots hears nothing, its query no answer."""
    with opened(net.config(RADAR_A), net.config(RADAR_B), net.config(SERVICE)) as (radar_a, radar_b, service):
        spy = Heard(radar_a, KEYS.plots("B"))
        control = Heard(service, KEYS.plots("*"))
        service.declare_queryable(KEYS.status, lambda q: q.reply(KEYS.status, b"status"))
        # A round trip on radar A's link after its subscription: the router has taken it.
        wait_matched(radar_a, KEYS.plots("A"))
        wait_matched(radar_b, KEYS.plots("B"))
        put_json(radar_b, KEYS.plots("B"), b"plots of B")
        control.wait(KEYS.plots("B"), b"plots of B")
        replies = list(radar_a.get(KEYS.status, timeout=1.0))
        assert [r.ok.payload.to_bytes() for r in replies if r.ok is not None] == []
        assert spy.samples == []


# --- 3. only the service answers the service's queries --------------------------------------


def _payloads(replies: Any) -> list[bytes]:
    return sorted(r.ok.payload.to_bytes() for r in replies if r.ok is not None)


def _get(session: zenoh.Session, selector: str, destination: zenoh.Locality | None = None) -> list[bytes]:
    # Every queryable that the router routes the query to, every reply: a rogue's would show.
    return _payloads(
        session.get(
            selector,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=WAIT_S,
            allowed_destination=destination,
        )
    )


@pytest.mark.parametrize("rogue_subject", [RADAR_A, OPERATOR])
def test_only_the_service_answers_status_and_pairs(net: Network, rogue_subject: str) -> None:
    with opened(net.config(rogue_subject), net.config(SERVICE), net.config(OPERATOR)) as (
        rogue,
        service,
        reader,
    ):
        service.declare_queryable(KEYS.status, lambda q: q.reply(KEYS.status, b"service"))
        service.declare_queryable(KEYS.pairs_all, lambda q: q.reply(KEYS.pairs("A", "B"), b"service"))
        asked: list[str] = []

        def rogue_answer(query: zenoh.Query) -> None:
            asked.append(str(query.selector))
            key = KEYS.status if str(query.key_expr) == KEYS.status else KEYS.pairs("A", "B")
            query.reply(key, b"rogue")

        rogue.declare_queryable(KEYS.status, rogue_answer)
        rogue.declare_queryable(KEYS.pairs_all, rogue_answer)
        # A message the rogue may send, after its declarations on the same link: once it has
        # gone through, the router has taken (or refused) the declarations.
        if rogue_subject == OPERATOR:
            wait_for(lambda: _get(rogue, KEYS.status, zenoh.Locality.REMOTE) == [b"service"], timeout=WAIT_S)
        else:
            control = Heard(service, KEYS.plots("A"))
            wait_matched(rogue, KEYS.plots("A"))
            put_json(rogue, KEYS.plots("A"), b"control")
            control.wait(KEYS.plots("A"), b"control")

        wait_for(lambda: _get(reader, KEYS.status) == [b"service"], timeout=WAIT_S)
        for selector in (KEYS.status, KEYS.pairs_all, KEYS.pairs("A", "*"), KEYS.pairs("A", "B")):
            assert _get(reader, selector) == [b"service"], selector
        assert asked == [], "the router sent the rogue a query"


# --- 4. who may not connect at all -----------------------------------------------------------


def _spoilt(net: Network, how: str) -> zenoh.Config:
    if how == "no client certificate":
        conf = net.config(RADAR_A)
        conf.insert_json5("transport/link/tls/enable_mtls", "false")
        conf.insert_json5("transport/link/tls/connect_certificate", "null")
        conf.insert_json5("transport/link/tls/connect_private_key", "null")
        return conf
    if how == "a certificate of another CA":
        return net.config(RADAR_A, cert_dir=net.pki.impostor_dir)
    if how == "a wrong password":
        return net.config(RADAR_A, password=net.pki.passwords[RADAR_A] + "x")
    if how == "another user's password":
        return net.config(RADAR_A, password=net.pki.passwords[RADAR_B])
    if how == "an unknown user":
        conf = net.config(RADAR_A)
        conf.insert_json5("transport/auth/usrpwd/user", '"radar-Z"')
        return conf
    if how == "no user":
        conf = net.config(RADAR_A)
        conf.insert_json5("transport/auth/usrpwd/user", "null")
        conf.insert_json5("transport/auth/usrpwd/password", "null")
        return conf
    raise AssertionError(how)


@pytest.mark.parametrize(
    "how",
    [
        "no client certificate",
        "a certificate of another CA",
        "a wrong password",
        "another user's password",
        "an unknown user",
        "no user",
    ],
)
def test_client_without_its_credentials_cannot_connect(net: Network, how: str) -> None:
    with opened(net.config(RADAR_A)):
        pass  # the same client with its credentials connects
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(_spoilt(net, how)).close()


def test_password_with_another_subjects_certificate_gives_nothing(net: Network) -> None:
    """Radar A's user and password over radar B's certificate: the session opens (both are
    valid) but matches no subject of the access control, so every message is refused."""
    mixed = net.config(RADAR_A)
    mixed.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(net.pki.dir / "radar-B.pem")))
    mixed.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(net.pki.dir / "radar-B.key")))
    with opened(net.config(SERVICE), net.config(RADAR_A)) as (service, radar):
        heard = Heard(service, KEYS.plots("*"))
        wait_matched(radar, KEYS.plots("A"))
        with opened(mixed) as (impostor,):
            for key in (KEYS.plots("A"), KEYS.plots("B")):
                put_json(impostor, key, b"impostor")
        # Closing drains the impostor's link: its puts are at the router before the control
        # is even put.
        put_json(radar, KEYS.plots("A"), b"control")
        heard.wait(KEYS.plots("A"), b"control")
        assert [p for _, p in heard.samples] == [b"control"]


# --- the certificate script -------------------------------------------------------------------


@pytest.mark.skipif(
    shutil.which("openssl") is None or shutil.which("bash") is None, reason="make-certs.sh needs openssl"
)
def test_make_certs_script_makes_certificates_zenoh_accepts(tmp_path: Path) -> None:
    """deploy/secure/make-certs.sh's files, as the README uses them: the router's certificate
    names the host clients connect to, each client's names its subject."""
    certs = tmp_path / "certs"
    subprocess.run(
        ["bash", str(SECURE / "make-certs.sh"), str(certs), "localhost", SERVICE, RADAR_A],
        env={**os.environ, "ROUTER_SANS": "IP:127.0.0.1"},
        check=True,
        capture_output=True,
    )
    assert (certs / "ca.key").stat().st_mode & 0o077 == 0, "private keys are the owner's only"
    passwords = {s: secrets.token_urlsafe(18) for s in (SERVICE, RADAR_A)}
    (certs / "users.txt").write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    with (
        secured_router(Pki(certs, certs, passwords), tmp_path) as network,
        opened(network.config(SERVICE), network.config(RADAR_A)) as (service, radar),
    ):
        heard = Heard(service, KEYS.plots("*"))
        wait_matched(radar, KEYS.plots("A"))
        put_json(radar, KEYS.plots("A"), b"plots")
        heard.wait(KEYS.plots("A"), b"plots")


# --- 5. the real service behind the secured router ------------------------------------------


@contextlib.contextmanager
def services(net: Network, partitions: list[Partition]) -> Iterator[list[ServiceNode]]:
    """Service nodes on the service's own config file (``--zenoh-config``), stopped after."""
    path = net.config_file("service", net.pki.passwords[SERVICE])
    nodes: list[ServiceNode] = []
    try:
        for partition in partitions:
            node = ServiceNode(
                EngineConfig(partition=partition), ZenohOptions(config_file=path), correlation_process=False
            )
            nodes.append(node)
            node.start()
        yield nodes
    finally:
        for node in nodes:
            node.stop()


def _status(reader: zenoh.Session) -> dict[str, Any]:
    replies = [r.ok for r in reader.get(KEYS.status, timeout=WAIT_S) if r.ok is not None]
    return json.loads(replies[0].payload.to_bytes()) if replies else {}


@pytest.mark.parametrize("count", [1, 2], ids=["one worker", "two partitioned workers"])
def test_service_serves_radars_through_the_secured_router(net: Network, count: int) -> None:
    """Radars A and B, each with its own credentials, feed the real service (one worker, or
    two partitioned workers exchanging their liveliness, statuses and tables); the operator
    hears its tracks and its status counts every batch."""
    stream = scenario_messages("two-radar", duration_s=30.0)
    batches = {rid: sum(k == KEYS.plots(rid) for k, _ in stream) for rid in "AB"}
    partitions = [Partition(k, count) for k in range(1, count + 1)]
    with (
        services(net, partitions) as nodes,
        opened(net.config(RADAR_A), net.config(RADAR_B), net.config(OPERATOR)) as (a, b, reader),
    ):
        tracks = Heard(reader, KEYS.tracks("*"))
        wait_for(lambda: all(n.ready for n in nodes), timeout=WAIT_S)
        if count > 1:
            wait_for(lambda: not any(n.status()["partition"]["missing"] for n in nodes), timeout=WAIT_S)
        for radar, rid in ((a, "A"), (b, "B")):
            wait_matched(radar, KEYS.plots(rid))
            wait_matched(radar, KEYS.site(rid))
        radars = {KEYS.site("A"): a, KEYS.plots("A"): a, KEYS.site("B"): b, KEYS.plots("B"): b}
        for key, payload in stream:  # in data-time order, each by its own radar
            put_json(radars[key], key, payload)

        def counted(status: dict[str, Any]) -> dict[str, int]:
            return {r["radar_id"]: r["batches"] for r in status.get("radars", [])}

        # The operator's `get`, and what GET /status serves (partitioned: every worker's view of
        # the whole network, the others' part as of their last status message).
        wait_for(lambda: counted(_status(reader)) == batches, timeout=30)
        wait_for(lambda: all(counted(n.status()) == batches for n in nodes), timeout=WAIT_S)
        # Each radar's performance (contract §5.3) is the service's queryable too, asked by the
        # operator: the rules let it through as they let `get fusion/status` through.
        heard = [
            json.loads(r.ok.payload.to_bytes())["radar_id"]
            for r in reader.get(KEYS.performance_all, timeout=WAIT_S)
            if r.ok is not None
        ]
        assert set(heard) == {"A", "B"}, heard

        # The router told the service of the operator's subscriber: the publisher of each
        # radar's TrackBatches matches it (a new publisher puts its first outputs whatever its
        # matching status says, so the outputs heard alone would not prove it), and the
        # operator hears them. (Outputs are put with congestion control DROP, so a loaded
        # machine may lose a few: the test does not count on every one.)
        def matched(rid: str) -> bool:
            pubs = [n._publishers.get(KEYS.tracks(rid)) for n in nodes]
            return any(p is not None and p[0].matching_status.matching for p in pubs)

        wait_for(lambda: all(matched(rid) for rid in "AB"), timeout=WAIT_S)
        wait_for(lambda: all(tracks.payloads(KEYS.tracks(rid)) for rid in "AB"), timeout=WAIT_S)
