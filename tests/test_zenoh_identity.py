"""Who speaks for a camera host (issue 34): with ``[zenoh] identities`` the solver host's Zenoh session admits a
host's status, detections and clock replies from that host's authenticated identity alone. Real Zenoh peers on
loopback, each logged in with its own user: host A, holding valid credentials, publishes a status and detections
under host B's keys and answers B's clock queries; none of it reaches the solver host, and B's run and clock are
untouched. Without identities (the code before), the same peer takes part in B's run: its status is refused
only as a ``run_conflict`` and its clock replies collide with B's (counted, and B's offset stalls)."""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.io.zenoh_link import access_control, clock_key, detections_key, open_session, status_key
from mocapd.pipeline.remote_cameras import RemoteRig
from mocapd.protocols.remote import (
    CameraState,
    Decoder,
    DetectionsMessage,
    StatusMessage,
    encode_clock,
    encode_detections,
    encode_status,
)
from mocapd.service.config import parse_config

CAMERAS = {"hostA": ["camA"], "hostB": ["camB"]}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _users(folder: Path) -> dict[str, str]:
    """A password file per user and the listener's users file: {user: password file}."""
    files = {}
    lines = []
    for user in ("solver", "hostA", "hostB"):
        (folder / f"pw-{user}").write_text(f"{user}-secret\n", encoding="utf-8")
        files[user] = str(folder / f"pw-{user}")
        lines.append(f"{user}:{user}-secret\n")
    (folder / "users").write_text("".join(lines), encoding="utf-8")
    return files


class Peer:
    """A camera host's Zenoh side, by hand: publishes a status of ``run_id`` as ``claims`` on ``claims``' status key
    every 50 ms and answers ``claims``' clock queries."""

    def __init__(self, session: zenoh.Session, claims: str, run_id: int, *, clock_skew_ns: int = 0) -> None:
        self.session = session
        self.stop = threading.Event()
        self.status = session.declare_publisher(status_key("rig", claims))
        self.detections = session.declare_publisher(detections_key("rig", CAMERAS[claims][0]))

        def answer(q: zenoh.Query) -> None:
            q.reply(q.key_expr, encode_clock(claims, run_id, time.monotonic_ns() + clock_skew_ns))

        self.queryable = session.declare_queryable(clock_key("rig", claims), answer)

        def publish() -> None:
            while not self.stop.wait(0.05):
                now = time.monotonic_ns() + clock_skew_ns
                self.status.put(encode_status(claims, run_id, now, 1.0, [CameraState(CAMERAS[claims][0], 0, True)]))
                dets = Detections2D.empty(17)
                self.detections.put(encode_detections(claims, CAMERAS[claims][0], run_id, 1, now, now, 64, 48, dets))

        self.thread = threading.Thread(target=publish, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.session.close()  # type: ignore[no-untyped-call]


def _zenoh(section: dict[str, Any]) -> Any:
    return parse_config({"zenoh": {"rig": "rig", "status_period_s": 0.05, "clock_period_s": 0.1,
                                   "lost_after_s": 1.0, **section}}).zenoh  # fmt: skip


def _heard(rig: RemoteRig, host: str) -> dict[str, int]:
    """Wait until ``host``'s status has been heard; what was refused from it until then. A clock reply that
    overtakes the host's first status is refused (``clock_before_status``): the honest host's own start-up race,
    counted before the attacker connects, so the tests compare what is refused after."""
    deadline = time.monotonic() + 30.0
    while rig.status()[host]["run_id"] is None:
        assert time.monotonic() < deadline, rig.status()[host]
        time.sleep(0.05)
    return dict(rig.status()[host]["rejected"])


def _close(peers: list[Peer], rig: RemoteRig) -> None:
    """Stop the peers' threads, close their sessions (a host may run several peers on one) and the rig."""
    for p in peers:
        p.stop.set()
    for p in peers:
        p.thread.join()
    for s in {id(p.session): p.session for p in peers}.values():
        s.close()  # type: ignore[no-untyped-call]
    rig.close()


@pytest.fixture
def attack(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[RemoteRig, list[bytes], dict[str, int]]]:
    """The solver host's RemoteRig (identities on or off: ``request.param``), host B honest, host A publishing its
    own status and B's; yields the rig and every payload the solver's session received on host B's keys."""
    pw = _users(tmp_path)
    endpoint = f"tcp/127.0.0.1:{_port()}"
    identities = {h: f"user:{h}" for h in CAMERAS} if request.param else {}
    z = _zenoh({"listen": [endpoint], "user": "solver", "password_file": pw["solver"],
                "users_file": str(tmp_path / "users"), "identities": identities})  # fmt: skip
    rig = RemoteRig(z, sorted(CAMERAS), cameras=CAMERAS)
    session = rig.start()
    seen: list[bytes] = []
    b_keys = (status_key("rig", "hostB"), detections_key("rig", "camB"))

    def on_sample(sample: zenoh.Sample) -> None:
        if str(sample.key_expr) in b_keys:
            seen.append(sample.payload.to_bytes())

    session.declare_subscriber("mocapd/rig/**", on_sample)
    peers: list[Peer] = []

    def host(user: str) -> zenoh.Session:
        return open_session(_zenoh({"listen": [], "connect": [endpoint], "user": user, "password_file": pw[user]}))

    try:
        peers.append(Peer(host("hostB"), "hostB", run_id=0xB))
        before = _heard(rig, "hostB")
        a = host("hostA")
        peers.append(Peer(a, "hostA", run_id=0xA))
        # Host A speaking for host B on B's keys, 30 s in the future of B's clock (a clock reply that agrees with
        # its own status messages, so plausible on its own).
        peers.append(Peer(a, "hostB", run_id=0x666, clock_skew_ns=30_000_000_000))
        time.sleep(3.0)
        yield rig, seen, before
    finally:
        _close(peers, rig)


@pytest.mark.parametrize("attack", [True], indirect=True)
def test_a_host_cannot_publish_or_answer_for_another_host(
    attack: tuple[RemoteRig, list[bytes], dict[str, int]],
) -> None:
    rig, seen, before = attack
    st = rig.status()
    b, a = st["hostB"], st["hostA"]
    assert b["run_id"] == f"{0xB:016x}" and b["restarts"] == 0 and b["round_trips"] > 0, b
    assert b["rejected"] == before, b  # A's status, detections and clock replies never reached the solver host
    assert abs(b["clock_offset_ms"]) < 100, b  # B's own clock (one machine: offset 0), not A's 30 s
    runs = _runs(seen)
    assert runs == {0xB}  # on B's keys only B's own messages arrived
    assert a["run_id"] == f"{0xA:016x}" and a["round_trips"] > 0 and a["identity"] == "user:hostA", a


@pytest.mark.parametrize("attack", [False], indirect=True)
def test_without_identities_another_host_gets_into_a_hosts_keys(
    attack: tuple[RemoteRig, list[bytes], dict[str, int]],
) -> None:
    """The same peers without ``identities``: what the session admitted before (and on loopback still does)."""
    rig, seen, _ = attack
    b = rig.status()["hostB"]
    assert b["rejected"].get("run_conflict", 0) > 0  # A's status for B got through and was refused by its run id
    assert _runs(seen) == {0xB, 0x666}


def _runs(payloads: list[bytes]) -> set[int]:
    out = set()
    for data in payloads:
        msg = Decoder().decode(data)
        assert isinstance(msg, StatusMessage | DetectionsMessage)
        out.add(msg.run_id)
    return out


def test_access_control_admits_each_host_on_its_own_keys_only() -> None:
    acl = access_control("rig", {"hostA": "user:hostA", "hostB": "cert:hostB.studio"}, CAMERAS)
    assert acl["default_permission"] == "deny"
    subjects = {s["id"]: s for s in acl["subjects"]}
    rules = {r["id"]: r for r in acl["rules"]}
    for policy in acl["policies"][1:]:
        subject = subjects[policy["subjects"][0]]
        keys = [k for r in policy["rules"] for k in rules[r]["key_exprs"]]
        assert all(rules[r]["flows"] == ["ingress"] for r in policy["rules"])
        if subject.get("usernames") == ["hostA"]:
            assert sorted(keys) == sorted([status_key("rig", "hostA"), detections_key("rig", "camA"),
                                           clock_key("rig", "hostA")])  # fmt: skip
        else:
            assert subject["cert_common_names"] == ["hostB.studio"]
            assert "mocapd/rig/camA/detections" not in keys


def test_a_solver_host_off_loopback_names_every_camera_hosts_identity(tmp_path: Path) -> None:
    pw = _users(tmp_path)
    base: dict[str, Any] = {"listen": ["tcp/10.9.8.7:7447"], "user": "solver", "password_file": pw["solver"],
            "users_file": str(tmp_path / "users")}  # fmt: skip
    cameras: Any = [{"name": c, "source": "zenoh", "host": h} for h, cs in CAMERAS.items() for c in cs]
    with pytest.raises(ConfigError, match=r"zenoh.identities .*missing: hostB\), e.g. hostB = \"user:hostB\""):
        parse_config({"zenoh": {**base, "identities": {"hostA": "user:hostA"}}, "cameras": cameras})
    loopback = {**base, "listen": ["tcp/127.0.0.1:7447"], "identities": {"hostA": "user:hostA"}}
    with pytest.raises(ConfigError, match=r"leaves out camera host\(s\) hostB: the session admits"):
        parse_config({"zenoh": loopback, "cameras": cameras})
    ok = parse_config({"zenoh": {**base, "identities": {h: f"user:{h}" for h in CAMERAS}}, "cameras": cameras})
    assert ok.zenoh.identities == {"hostA": "user:hostA", "hostB": "user:hostB"}
    with pytest.raises(ConfigError, match="users_file"):  # a user name this side does not check is no identity
        parse_config({"zenoh": {"identities": {"hostA": "user:hostA"}}})
    with pytest.raises(ConfigError, match="mutual TLS"):
        parse_config({"zenoh": {**base, "identities": {"hostA": "cert:hostA"}}})
    with pytest.raises(ConfigError, match=r"identities\.hostA"):
        parse_config({"zenoh": {**base, "identities": {"hostA": "hostA\nuser:x"}}})


def _certificates(folder: Path) -> None:
    """A throw-away CA and certificates for the solver and hosts A and B (CN = the name; openssl)."""

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=mocapd-test-ca")  # fmt: skip
    (folder / "ext").write_text("subjectAltName=IP:127.0.0.1\n", encoding="utf-8")
    for name in ("solver", "hostA", "hostB"):
        ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj",
            f"/CN={name}")  # fmt: skip
        ssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
            f"{name}.pem", "-days", "2", "-extfile", "ext")  # fmt: skip


def test_with_mutual_tls_a_host_is_its_certificates_name(tmp_path: Path) -> None:
    """The same attack over mutual TLS, identities by certificate name: host A's certificate, signed by the rig's
    CA like B's, does not let it speak for B; ``zenoh_links`` shows the two hosts' certificate names."""
    _certificates(tmp_path)
    endpoint = f"tls/127.0.0.1:{_port()}"

    def tls(name: str) -> dict[str, str]:
        return {"tls_root_ca": str(tmp_path / "ca.pem"), "tls_cert": str(tmp_path / f"{name}.pem"),
                "tls_key": str(tmp_path / f"{name}.key")}  # fmt: skip

    z = _zenoh({"listen": [endpoint], **tls("solver"), "identities": {h: f"cert:{h}" for h in CAMERAS}})
    rig = RemoteRig(z, sorted(CAMERAS), cameras=CAMERAS)
    rig.start()
    peers: list[Peer] = []
    try:
        b = open_session(_zenoh({"listen": [], "connect": [endpoint], **tls("hostB")}))
        peers.append(Peer(b, "hostB", run_id=0xB))
        before = _heard(rig, "hostB")
        a = open_session(_zenoh({"listen": [], "connect": [endpoint], **tls("hostA")}))
        peers += [Peer(a, "hostA", run_id=0xA), Peer(a, "hostB", run_id=0x666, clock_skew_ns=30_000_000_000)]
        time.sleep(3.0)
        st = rig.status()
        assert st["hostB"]["run_id"] == f"{0xB:016x}" and st["hostB"]["rejected"] == before, st["hostB"]
        assert st["hostB"]["round_trips"] > 0 and abs(st["hostB"]["clock_offset_ms"]) < 100, st["hostB"]
        assert st["hostA"]["run_id"] == f"{0xA:016x}" and st["hostA"]["identity"] == "cert:hostA"
        assert rig.links() == ["cert:hostA", "cert:hostB"]
    finally:
        _close(peers, rig)
