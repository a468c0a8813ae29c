"""Camera hosts over Zenoh on loopback: ``mocapd detect-host`` processes publishing a synthetic rig's detections,
the solver host (``mocapd run`` with ``source = "zenoh"`` cameras) solving the people; a host killed mid-run is
shown lost, its cameras leave the solve, and it rejoins when started again; duplicates and garbage are counted
and dropped; the Zenoh configuration is the one the config asks for (no scouting, only the listed endpoints)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from mocapd.errors import ConfigError
from mocapd.io.lifecycle import guarded_command
from mocapd.io.zenoh_link import detections_key, session_settings
from mocapd.pipeline.remote_cameras import RemoteRig
from mocapd.protocols.remote import encode_detections
from mocapd.service.config import load_config, parse_config
from mocapd.sim.camera_hosts import host_config, solver_config, write_ring_calibration
from tests.test_run_rig import RunProcess

REPO = Path(__file__).resolve().parents[1]
CAMS = ["cam0", "cam1", "cam2", "cam3"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class HostProcess:
    """``mocapd detect-host`` as a subprocess, its output collected by a thread."""

    def __init__(self, config: Path) -> None:
        # guarded: it ends with the test process, however that ends (no orphan detect-host holding its ports)
        cmd = guarded_command([sys.executable, "-m", "mocapd", "detect-host", "--config", str(config)])
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        assert self.proc.stdout is not None
        stdout = self.proc.stdout
        threading.Thread(target=lambda: self.lines.extend(stdout), daemon=True).start()

    def wait_ready(self, timeout: float = 120.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(line.startswith("ready: host") for line in self.lines):
                return
            assert self.proc.poll() is None, "".join(self.lines)
            time.sleep(0.1)
        raise AssertionError("".join(self.lines))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def _synthetic_rig(tmp_path: Path, port: int) -> tuple[Path, Path]:
    endpoint = f"tcp/127.0.0.1:{port}"
    write_ring_calibration(CAMS, tmp_path / "calibration.toml")
    host = tmp_path / "hostA.toml"
    host.write_text(host_config("hostA", [{"name": c, "source": "synthetic"} for c in CAMS], [endpoint],
                                extra={"synthetic": {"people": 2, "suits": 0}}), encoding="utf-8")  # fmt: skip
    solver = tmp_path / "solver.toml"
    solver.write_text(solver_config(dict.fromkeys(CAMS, "hostA"), tmp_path / "calibration.toml", [endpoint],
                                    extra={"daemon": {"latency_s": 0.3, "keypoint_max_age_s": 0.2}}),
                      encoding="utf-8")  # fmt: skip
    return host, solver


def _people(st: dict[str, Any]) -> int:
    frame = st.get("frame") or {}
    return len(frame.get("people", []))


def test_synthetic_host_is_solved_lost_and_rejoins(tmp_path: Path) -> None:
    host_cfg, solver_cfg = _synthetic_rig(tmp_path, free_port())
    solver = RunProcess(["--config", str(solver_cfg), "--verbose"], tmp_path)
    host = HostProcess(host_cfg)
    try:
        url = solver.url(180)
        host.wait_ready()
        st = solver.wait_status(url, lambda s: _people(s) == 2 and s["frame"]["missing_cameras"] == 0, 120)
        remote = st["remote_hosts"]["hostA"]
        assert remote["lost"] is False and remote["joins"] == 1 and remote["identity"] is None
        assert st["zenoh_links"] == ["?"]  # one link, unauthenticated (loopback needs no credentials)
        # One machine, one CLOCK_MONOTONIC: the true offset is 0, and the estimate's bound must hold.
        assert abs(remote["clock_offset_ms"]) <= remote["clock_uncertainty_ms"] < 50.0
        cams = {c["name"]: c for c in st["cameras"]}
        assert all(cams[c]["kind"] == "zenoh" and cams[c]["delivered"] > 10 for c in CAMS), cams
        assert all(cams[c]["hop_ms"]["p50"] is not None for c in CAMS)
        # Both people where the simulated world has them: hips about a metre up, inside the ring.
        for p in st["frame"]["people"]:
            x, y, z = p["root_m"]
            assert 0.5 < y < 1.3 and abs(x) < 4 and abs(z) < 4, p

        host.kill()
        st = solver.wait_status(url, lambda s: s["remote_hosts"]["hostA"]["lost"], 30)
        assert st["remote_hosts"]["hostA"]["last_seen_s"] > 1.0  # shown lost once silent for lost_after_s
        st = solver.wait_status(url, lambda s: s["frame"]["missing_cameras"] == len(CAMS) and _people(s) == 0, 30)

        host = HostProcess(host_cfg)  # a new run of the same host: no restart of the solver host
        host.wait_ready()
        st = solver.wait_status(url, lambda s: _people(s) == 2 and s["frame"]["missing_cameras"] == 0, 60)
        remote = st["remote_hosts"]["hostA"]
        assert remote["lost"] is False and remote["joins"] == 2 and remote["losses"] == 1 and remote["restarts"] == 1
        code, _ = solver.interrupt()
        assert code == 0, solver.output
        assert "Traceback" not in solver.output
    finally:
        host.kill()
        solver.close()


def test_duplicates_garbage_and_strangers_are_counted_and_dropped(tmp_path: Path) -> None:
    """A publisher of our own on the camera's key: the same frame twice, an older one, garbage, another camera's
    frame, a frame at the wrong size: each counted under its reason, only the first frame delivered."""
    port = free_port()
    _, solver_cfg = _synthetic_rig(tmp_path, port)
    solver = RunProcess(["--config", str(solver_cfg)], tmp_path)
    cfg = load_config(tmp_path / "hostA.toml")
    session = zenoh.open(_config(cfg.zenoh))
    stop = threading.Event()
    try:
        url = solver.url(180)
        from mocapd.core.sorting import Detections2D

        dets = Detections2D.empty(len(solver_targets()))
        width, height = _ring_size()
        pub = session.declare_publisher(detections_key("rig", "cam0"))
        # A host's run id comes from its status, its clock offset from round trips: publish one, answer them.
        from mocapd.io.zenoh_link import clock_key, status_key
        from mocapd.protocols.remote import CameraState, encode_clock, encode_status

        def answer(q: zenoh.Query) -> None:
            q.reply(q.key_expr, encode_clock("hostA", 7, time.monotonic_ns()))

        session.declare_queryable(clock_key("rig", "hostA"), answer)
        status = session.declare_publisher(status_key("rig", "hostA"))

        def publish_status() -> None:
            while not stop.wait(0.2):
                status.put(encode_status("hostA", 7, time.monotonic_ns(), 1.0, [CameraState("cam0", 0, True)]))

        threading.Thread(target=publish_status, daemon=True).start()
        solver.wait_status(url, lambda s: s["remote_hosts"]["hostA"]["clock_offset_ms"] is not None, 30)

        def frame(n: int, camera: str = "cam0", size: tuple[int, int] = (width, height)) -> bytes:
            now = time.monotonic_ns()
            return encode_detections("hostA", camera, 7, n, now, now, size[0], size[1], dets)

        for data in [frame(5), frame(5), frame(4), b"\xc1garbage", frame(6, "cam1"), frame(7, size=(1, 1))]:
            pub.put(data)
        st = solver.wait_status(url, lambda s: s["cameras"][0]["received"] >= 6, 20)
        cam0 = st["cameras"][0]
        assert cam0["delivered"] == 1
        assert cam0["dropped"] == {"duplicate": 1, "out_of_order": 1, "wrong_camera": 1, "size": 1}
        assert cam0["decode_rejected"] == {"not_msgpack": 1}
        pub.put(frame(9, size=(width, height)))
        old = time.monotonic_ns() - 2_000_000_000
        pub.put(encode_detections("hostA", "cam0", 7, 10, old, old, width, height, dets))
        st = solver.wait_status(url, lambda s: s["cameras"][0]["received"] >= 8, 20)
        assert st["cameras"][0]["delivered"] == 2 and st["cameras"][0]["dropped"]["late"] == 1
    finally:
        stop.set()
        session.close()  # type: ignore[no-untyped-call]
        solver.close()


def solver_targets() -> tuple[str, ...]:
    from mocapd.core.keypoints import keypoint_format
    from mocapd.core.skeleton import Skeleton

    cfg = parse_config({})
    return keypoint_format(cfg.detector.model.keypoint_format).track_targets(Skeleton.from_height(1.75)).names


def _ring_size() -> tuple[int, int]:
    from mocapd.core.synthetic import named_ring_rig

    cam = named_ring_rig(["cam0"])[0]
    return cam.width, cam.height


def _config(z: Any) -> zenoh.Config:
    c = zenoh.Config()
    for k, v in session_settings(z).items():
        c.insert_json5(k, json.dumps(v))
    return c


def test_a_host_is_lost_exactly_when_silent_for_lost_after_s_and_a_new_run_resets_its_clock() -> None:
    now = [10**12]
    z = parse_config({"zenoh": {"lost_after_s": 2.0}}).zenoh
    rig = RemoteRig(z, ["hostA"], clock=lambda: now[0])
    host = rig.hosts["hostA"]
    assert rig.status()["hostA"]["lost"] is True and host.joins == 0  # never heard from
    with rig.lock:
        rig.seen(host, 1, now[0])
        host.estimator.add(now[0] - 100, now[0] + 5_000, now[0])
    now[0] += 2_000_000_000  # silent for exactly lost_after_s: not yet
    assert rig.status()["hostA"]["lost"] is False
    now[0] += 1
    st = rig.status()["hostA"]
    assert st["lost"] is True and st["losses"] == 1 and st["clock_offset_ms"] is not None
    with rig.lock:
        rig.seen(host, 2, now[0])  # heard again, from a new run: rejoined, its clock offset unknown again
        assert rig.offset_ns(host, 2, now[0]) is None and rig.offset_ns(host, 1, now[0]) is None
    st = rig.status()["hostA"]
    assert st["lost"] is False and st["joins"] == 2 and st["restarts"] == 1 and st["clock_offset_ms"] is None


def test_session_settings_never_scout_and_listen_only_where_told() -> None:
    z = parse_config({"zenoh": {"listen": [], "connect": ["tcp/127.0.0.1:7447"]}}).zenoh
    s = session_settings(z)
    assert s["scouting/multicast/enabled"] is False and s["scouting/gossip/enabled"] is False
    assert s["listen/endpoints"] == [] and s["connect/endpoints"] == ["tcp/127.0.0.1:7447"]
    assert parse_config({}).zenoh.listen == ("tcp/127.0.0.1:7447",)


def test_user_password_settings_read_the_password_file(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("s3cret\n", encoding="utf-8")
    (tmp_path / "users").write_text("alice:s3cret\n", encoding="utf-8")
    z = parse_config({"zenoh": {"listen": ["tcp/10.1.2.3:7447"], "user": "alice", "password_file": str(tmp_path / "pw"),
                                "users_file": str(tmp_path / "users")}}).zenoh  # fmt: skip
    auth = session_settings(z)["transport/auth/usrpwd"]
    assert auth == {"user": "alice", "password": "s3cret", "dictionary_file": str(tmp_path / "users")}
    z = z.model_copy(update={"password_file": str(tmp_path / "missing")})
    with pytest.raises(ConfigError, match="password_file"):
        session_settings(z)


def _certificates(folder: Path) -> None:
    """A throw-away CA and a certificate for 127.0.0.1 signed by it (openssl, setup/steps/23-openssl.sh)."""

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=mocapd-test-ca")  # fmt: skip
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "solver.key", "-out", "solver.csr", "-subj", "/CN=solver")
    (folder / "ext").write_text("subjectAltName=IP:127.0.0.1\n", encoding="utf-8")
    ssl("x509", "-req", "-in", "solver.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
        "solver.pem", "-days", "2", "-extfile", "ext")  # fmt: skip
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "hostA.key", "-out", "hostA.csr", "-subj", "/CN=hostA")
    ssl("x509", "-req", "-in", "hostA.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
        "hostA.pem", "-days", "2", "-extfile", "ext")  # fmt: skip
    (folder / "other").mkdir()
    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "other/ca.key", "-out", "other/ca.pem", "-days",
        "2", "-subj", "/CN=someone-else")  # fmt: skip


def _delivered_over(listener: zenoh.Session, talker: zenoh.Session) -> bool:
    got: list[bytes] = []
    listener.declare_subscriber("mocapd/tls-test/**", lambda s: got.append(s.payload.to_bytes()))
    for _ in range(40):
        talker.put("mocapd/tls-test/x", b"over tls")
        time.sleep(0.1)
        if got:
            return True
    return False


def test_tls_sessions_talk_with_the_ca_and_not_without_it(tmp_path: Path) -> None:
    """The TLS configuration of docs/scaling.md: mutual TLS, a tls/ listener and a camera host each with a
    certificate signed by the rig's CA get through; a client that only knows the CA certificate (public: it proves
    nothing) does not (issue 34: it did), nor does one that trusts another CA."""
    from mocapd.io.zenoh_link import open_session

    _certificates(tmp_path)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    solver = open_session(parse_config({"zenoh": {
        "listen": [endpoint], "tls_root_ca": str(tmp_path / "ca.pem"), "tls_cert": str(tmp_path / "solver.pem"),
        "tls_key": str(tmp_path / "solver.key")}}).zenoh)  # fmt: skip
    sessions = [solver]
    try:
        host = open_session(parse_config({"zenoh": {
            "listen": [], "connect": [endpoint], "tls_root_ca": str(tmp_path / "ca.pem"),
            "tls_cert": str(tmp_path / "hostA.pem"), "tls_key": str(tmp_path / "hostA.key")}}).zenoh)  # fmt: skip
        sessions.append(host)
        assert _delivered_over(solver, host)
        trusting = open_session(parse_config({"zenoh": {"listen": [], "connect": [endpoint],
                                                        "tls_root_ca": str(tmp_path / "ca.pem")}}).zenoh)  # fmt: skip
        sessions.append(trusting)
        assert not _delivered_over(solver, trusting)
        other_ca = str(tmp_path / "other" / "ca.pem")
        stranger = open_session(parse_config({"zenoh": {"listen": [], "connect": [endpoint],
                                                        "tls_root_ca": other_ca}}).zenoh)  # fmt: skip
        sessions.append(stranger)
        assert not _delivered_over(solver, stranger)
    finally:
        for s in sessions:
            s.close()  # type: ignore[no-untyped-call]


def test_detect_host_refuses_to_listen_off_loopback_without_auth(tmp_path: Path) -> None:
    cfg = tmp_path / "host.toml"
    cfg.write_text(host_config("h", [{"name": "cam0", "source": "synthetic"}], [],
                               zenoh={"listen": ["tcp/0.0.0.0:7447"]}), encoding="utf-8")  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "mocapd", "detect-host", "--config", str(cfg)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert "zenoh.listen" in proc.stderr and "not loopback" in proc.stderr and "zenoh.user" in proc.stderr
