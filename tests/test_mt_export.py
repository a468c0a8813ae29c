"""MT Manager text exports (mocapd.io.mt_export): real MTw files and generated ones in every layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.core.rotations import matrix_from_quat, quat_angle, random_quat
from mocapd.errors import InputError
from mocapd.io.mt_export import parse_mt_export, read_mt_export, sensor_id_from_name

MTW = Path(__file__).parent / "data" / "opensense_mtw"


def test_real_mtw_export() -> None:
    """OpenSense's MTw file: tab-separated, // header, PacketCounter, empty UTC cells, Acc + Mat columns."""
    e = read_mt_export(MTW / "MT_012005D6_009-001_00B421E6.txt")
    assert e.sensor == "00B421E6" and e.rate_hz == 100.0
    assert e.orientation == "matrix" and e.acceleration == "measured"
    assert e.header["Update Rate"] == "100.0Hz" and e.header["Filter Profile"].startswith("human")
    assert e.ticks is None and e.counter is not None and e.counter[0] == 472
    np.testing.assert_allclose(np.diff(e.time_s), 0.01)
    assert e.dropped_rows == 0 and e.n == len(e.time_s)
    # Standing still at the start: the specific force is gravity, up in the global frame (ENU z).
    up = np.einsum("nij,nj->ni", matrix_from_quat(e.quat[:200]), e.acc[:200])
    np.testing.assert_allclose(up.mean(axis=0), [0.0, 0.0, 9.81], atol=0.15)


def _export(q: np.ndarray, *, sep: str, layout: str, header: list[str], ticks0: int = 0) -> str:
    """An export of orientations ``q`` (n, 4, ENU) of a still sensor, in one of the layouts."""
    n = len(q)
    R = matrix_from_quat(q)
    acc = np.einsum("nji,j->ni", R, [0.0, 0.0, 9.80665])
    cols = ["PacketCounter", "SampleTimeFine"]
    rows = [[str((65530 + i) % 65536), str((ticks0 + 100 * i) % (1 << 32))] for i in range(n)]
    if layout == "quat":
        cols += [f"Quat_q{i}" for i in range(4)] + ["Acc_X", "Acc_Y", "Acc_Z"]
        for i in range(n):
            rows[i] += [f"{v:.9f}" for v in (*q[i], *acc[i])]
    elif layout == "euler":
        roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
        pitch = -np.arcsin(np.clip(R[:, 2, 0], -1, 1))
        yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
        cols += ["Roll", "Pitch", "Yaw", "FreeAcc_E", "FreeAcc_N", "FreeAcc_U"]
        for i in range(n):
            rows[i] += [f"{np.degrees(v):.9f}" for v in (roll[i], pitch[i], yaw[i])] + ["0", "0", "0"]
    else:
        raise AssertionError(layout)
    lines = header + [sep.join(cols)] + [sep.join(r) for r in rows]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("sep", ["\t", ",", ";"])
@pytest.mark.parametrize("layout", ["quat", "euler"])
def test_generated_layouts(sep: str, layout: str) -> None:
    rng = np.random.default_rng(0)
    q = random_quat(rng, (50,))
    text = _export(q, sep=sep, layout=layout, header=["// General information:", "//  DeviceId: 00b4aaaa"],
                   ticks0=(1 << 32) - 1000)  # fmt: skip
    e = parse_mt_export(text, name="recording.csv")
    assert e.sensor == "00B4AAAA"
    assert e.orientation == ("quaternion" if layout == "quat" else "euler")
    assert e.acceleration == ("measured" if layout == "quat" else "from free acceleration")
    assert np.degrees(quat_angle(e.quat, q)).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(e.acc, axis=1), 9.80665, atol=1e-6)
    # SampleTimeFine wraps at 2^32 and PacketCounter at 2^16 inside the file: both are unwrapped.
    assert e.ticks is not None and np.all(np.diff(e.ticks) == 100)
    assert e.counter is not None and np.all(np.diff(e.counter) == 1)
    assert e.rate_hz == pytest.approx(100.0)  # from SampleTimeFine: no "// Update Rate" line
    np.testing.assert_allclose(e.time_s, np.arange(50) / 100.0)


def test_ned_exports_are_turned_to_enu() -> None:
    q_enu = random_quat(np.random.default_rng(1), (5,))
    # NED = rotate ENU by swapping x/y and flipping z: the same sensor reports R_ned = T R_enu.
    T = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    from mocapd.core.rotations import quat_from_matrix

    q_ned = quat_from_matrix(T @ matrix_from_quat(q_enu))
    text = _export(q_ned, sep="\t", layout="quat", header=["// Update Rate: 100Hz", "// Coordinate system: NED"])
    e = parse_mt_export(text, name="MT_00B40001.txt")
    assert e.sensor == "00B40001" and e.rate_hz == 100.0
    assert np.degrees(quat_angle(e.quat, q_enu)).max() < 1e-5


def test_missing_cells_and_errors() -> None:
    good = "// Update Rate: 100.0Hz\nPacketCounter,Quat_q0,Quat_q1,Quat_q2,Quat_q3\n"
    good += "1,1,0,0,0\n2,,,,\n3,NaN,0,0,0\n4,1,0,0,0\n"
    e = parse_mt_export(good, name="a_00B40002.txt")
    assert e.n == 2 and e.dropped_rows == 2 and e.acceleration == "gravity only"
    np.testing.assert_allclose(e.time_s, [0.0, 0.03])
    with pytest.raises(InputError, match="no orientation columns"):
        parse_mt_export("PacketCounter,Acc_X,Acc_Y,Acc_Z\n1,0,0,9.8\n", name="x_00B40003.txt", rate_hz=100)
    with pytest.raises(InputError, match="update rate"):
        parse_mt_export("PacketCounter,Quat_q0,Quat_q1,Quat_q2,Quat_q3\n1,1,0,0,0\n", name="x_00B40003.txt")
    with pytest.raises(InputError, match="not a number"):
        parse_mt_export(good.replace("4,1,0", "4,one,0"), name="a_00B40002.txt")
    with pytest.raises(InputError, match="sensor id"):
        parse_mt_export(good, name="take1.txt")
    with pytest.raises(InputError, match="no column row"):
        parse_mt_export("// only a header\n", name="a_00B40002.txt")
    assert sensor_id_from_name("MT_012005D6_009-001_00B421E6.txt") == "00B421E6"
