"""Zenoh TLS misconfigurations said in one line before a session opens (issue 45): with a wrong CA, an expired or
not yet valid certificate, a key of another certificate or a PEM file that is none, check-config said ok and
detect-host printed "ready ... publishing", while Zenoh made no link and said nothing. At run time, what only the
other side can tell is said on both sides: the camera host without a link, the solver host of the hosts it never
heard from. Certificates by openssl (setup/steps/23-openssl.sh), dates set with ``openssl ca``."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest

from mocapd.errors import ConfigError
from mocapd.io.tls_files import check_tls_files

_CA_CONFIG = """[ca]
default_ca = test
[test]
database = index.txt
new_certs_dir = .
serial = serial
default_md = sha256
policy = any
copy_extensions = copy
[any]
commonName = supplied
"""


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("pki")

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    for ca in ("ca", "other-ca"):
        ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{ca}.key", "-out", f"{ca}.pem", "-days",
            "2", "-subj", f"/CN={ca}")  # fmt: skip
    (folder / "ca.cnf").write_text(_CA_CONFIG, encoding="utf-8")
    (folder / "index.txt").write_text("", encoding="utf-8")
    (folder / "serial").write_text("01\n", encoding="utf-8")
    dates = {
        "good": ("20200101000000Z", "20991231000000Z"),
        "expired": ("20200101000000Z", "20200102000000Z"),
        "future": ("20980101000000Z", "20991231000000Z"),
        "stranger": ("20200101000000Z", "20991231000000Z"),
    }
    for name, (start, end) in dates.items():
        ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj",
            f"/CN={name}")  # fmt: skip
        ca = "other-ca" if name == "stranger" else "ca"
        ssl("ca", "-batch", "-config", "ca.cnf", "-cert", f"{ca}.pem", "-keyfile", f"{ca}.key", "-in",
            f"{name}.csr", "-out", f"{name}.pem", "-startdate", start, "-enddate", end, "-notext")  # fmt: skip
    (folder / "garbage.pem").write_text("-----BEGIN CERTIFICATE-----\nnot base64 at all\n-----END CERTIFICATE-----\n")
    return folder


def test_good_files_pass(pki: Path) -> None:
    check_tls_files(str(pki / "ca.pem"), str(pki / "good.pem"), str(pki / "good.key"))
    check_tls_files(str(pki / "ca.pem"), "", "")  # a CA alone: a connector without a certificate of its own


@pytest.mark.parametrize(
    ("ca", "cert", "key", "said"),
    [
        ("other-ca.pem", "good.pem", "good.key", r"tls_cert = .*good\.pem.*refused by tls_root_ca .*local issuer"),
        ("ca.pem", "stranger.pem", "stranger.key", r"tls_cert = .*stranger\.pem.*refused .*local issuer"),
        ("ca.pem", "expired.pem", "expired.key", r"expired\.pem.*refused .*certificate has expired"),
        ("ca.pem", "future.pem", "future.key", r"future\.pem.*refused .*certificate is not yet valid"),
        ("ca.pem", "good.pem", "expired.key", r"tls_key = .*expired\.key.*not the key of tls_cert"),
        ("garbage.pem", "good.pem", "good.key", r"tls_root_ca = .*garbage\.pem.*no CA certificate read"),
        ("ca.pem", "garbage.pem", "good.key", r"garbage\.pem.*not a PEM certificate and its key"),
        ("ca.pem", "good.pem", "garbage.pem", r"not a PEM certificate and its key"),
        ("ca.pem", "good.pem", "missing.key", r"zenoh\.tls_key .*missing\.key: no such file"),
    ],
)
def test_each_misconfiguration_is_one_line(pki: Path, ca: str, cert: str, key: str, said: str) -> None:
    with pytest.raises(ConfigError, match=said) as exc:
        check_tls_files(str(pki / ca), str(pki / cert), str(pki / key))
    assert "\n" not in str(exc.value)


def test_a_camera_host_says_when_it_has_no_link(tmp_path: Path) -> None:
    """The runtime half: a host whose certificate the solver host's CA did not sign has no link, which Zenoh does
    not report (detect-host printed "ready ... publishing" and nothing else). The link watch of detect-host says it
    in one warning, once; a host the solver accepts is said linked. Real Zenoh sessions over TLS on loopback."""
    import time

    from mocapd.io.zenoh_link import LinkWatch, open_session
    from mocapd.service.config import parse_config
    from tests.test_camera_hosts import _certificates, free_port

    _certificates(tmp_path)  # ca.pem, solver and hostA signed by it; other/ca.pem: someone else's CA
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "other/host.key", "-out",
                    "other/host.pem", "-days", "2", "-subj", "/CN=hostA"], cwd=tmp_path, check=True,
                   capture_output=True)  # fmt: skip
    endpoint = f"tls/127.0.0.1:{free_port()}"
    ca = str(tmp_path / "ca.pem")
    tables: dict[str, dict[str, object]] = {
        "solver": {
            "listen": [endpoint],
            "tls_cert": str(tmp_path / "solver.pem"),
            "tls_key": str(tmp_path / "solver.key"),
        },
        "accepted": {"tls_cert": str(tmp_path / "hostA.pem"), "tls_key": str(tmp_path / "hostA.key")},
        "refused": {"tls_cert": str(tmp_path / "other" / "host.pem"), "tls_key": str(tmp_path / "other" / "host.key")},
    }
    sessions: dict[str, Any] = {}
    for name, table in tables.items():
        ends: dict[str, object] = {} if name == "solver" else {"listen": [], "connect": [endpoint]}
        sessions[name] = open_session(parse_config({"zenoh": {**ends, "tls_root_ca": ca, **table}}).zenoh)
    said: dict[str, list[tuple[str, str]]] = {"accepted": [], "refused": []}
    try:
        t0 = time.monotonic()
        watches = {name: LinkWatch(sessions[name], [endpoint], 1.0, t0) for name in said}
        while time.monotonic() - t0 < 4.0:
            for name, watch in watches.items():
                line = watch.check(time.monotonic())
                if line is not None:
                    said[name].append(line)
            time.sleep(0.1)
    finally:
        for session in sessions.values():
            session.close()
    assert said["accepted"] == [("info", f"zenoh: linked to {endpoint}")], said
    assert len(said["refused"]) == 1 and said["refused"][0][0] == "warning", said
    assert said["refused"][0][1].startswith(f"zenoh: no link after 1 s to {endpoint}: "), said


def test_the_solver_host_says_which_camera_hosts_it_never_heard(tmp_path: Path, caplog: Any) -> None:
    """The solver host's half (issue 45: TLS failures said on both sides): a camera host whose certificate its CA
    did not sign never links and Zenoh reports nothing, so the solver host said nothing either. Now one warning,
    once, ``lost_after_s`` after its session opened, names each host never heard from, the links that are up and
    those of identities [zenoh.identities] gives no host; a host heard in time is not named. Real Zenoh sessions
    over mutual TLS on loopback; the rig's clock is held, so the line's moment does not depend on the machine's
    speed."""
    import logging
    import time

    from mocapd.io.zenoh_link import open_session
    from mocapd.pipeline.remote_cameras import RemoteRig
    from mocapd.service.config import parse_config
    from tests.test_camera_hosts import _certificates, free_port

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=tmp_path, check=True, capture_output=True)

    _certificates(tmp_path)  # ca.pem, solver and hostA signed by it; other/: someone else's CA
    # hostA's name on a certificate the rig's CA did not sign (refused), and a certificate the CA signed for a name
    # no host has (linked: Zenoh's access control drops its messages, the link itself is up)
    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "other/host.key", "-out", "other/host.pem",
        "-days", "2", "-subj", "/CN=hostA")  # fmt: skip
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "stranger.key", "-out", "stranger.csr", "-subj",
        "/CN=stranger")  # fmt: skip
    ssl("x509", "-req", "-in", "stranger.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
        "stranger.pem", "-days", "2", "-extfile", "ext")  # fmt: skip
    endpoint = f"tls/127.0.0.1:{free_port()}"
    ca = str(tmp_path / "ca.pem")
    z = parse_config({"zenoh": {
        "listen": [endpoint], "tls_root_ca": ca, "tls_cert": str(tmp_path / "solver.pem"),
        "tls_key": str(tmp_path / "solver.key"), "identities": {"hostA": "cert:hostA", "hostB": "cert:hostB"},
        "lost_after_s": 2.0,
    }}).zenoh  # fmt: skip
    now = [10**12]
    rig = RemoteRig(z, ["hostA", "hostB"], cameras={"hostA": ["cam1"], "hostB": ["cam2"]}, clock=lambda: now[0])
    rig.start()
    hosts = []
    try:
        for name in ("other/host", "stranger"):
            table = {"listen": [], "connect": [endpoint], "tls_root_ca": ca, "tls_cert": str(tmp_path / f"{name}.pem"),
                     "tls_key": str(tmp_path / f"{name}.key")}  # fmt: skip
            hosts.append(open_session(parse_config({"zenoh": table}).zenoh))
        deadline = time.monotonic() + 30.0  # the stranger's handshake, however loaded the machine
        while rig.links() != ["cert:stranger"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert rig.links() == ["cert:stranger"]  # the refused host has no link; nothing said it
        with caplog.at_level(logging.WARNING, logger="mocapd.pipeline.remote_cameras"):
            with rig.lock:
                rig.seen(rig.hosts["hostB"], 1, now[0])  # hostB's status came: it is not named
            rig.check_lost(now[0] + 1_999_999_999)  # not yet lost_after_s since the session opened
            assert not [r for r in caplog.records if "not heard" in r.getMessage()]
            now[0] += 2_000_000_000
            for _ in range(3):
                rig.check_lost(now[0])
                now[0] += 1_000_000_000
    finally:
        rig.close()
        for session in hosts:
            session.close()  # type: ignore[no-untyped-call]
    said = [r.getMessage() for r in caplog.records if "not heard" in r.getMessage()]
    assert len(said) == 1, said
    assert said[0].startswith("camera host hostA: not heard from 2 s after start: not running, or its link refused"), (
        said
    )
    assert "links up: cert:stranger" in said[0] and "does not name: cert:stranger" in said[0], said
