"""Pose-track CSV reading and checking, frame changes, plane of motion and velocity estimates."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dano.sysid.data import (
    Track,
    TrackFileError,
    estimate_velocity,
    motion_plane_normal,
    read_tracks,
    rotate,
    to_metric,
)

HEADER = "t,x,y,z,qw,qx,qy,qz"


def _write(path, header, rows):
    """Writes a CSV: `rows` are lists of values (written with repr) or ready-made strings."""
    lines = [header] + [r if isinstance(r, str) else ",".join(repr(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _unit_quats(n, seed=0):
    q = Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]  # pyright: ignore[reportCallIssue]
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _good_rows(n=6, dt=0.1, t0=0.0):
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(n, 3))
    quat = _unit_quats(n)
    t = t0 + np.arange(n) * dt
    return t, pos, quat


def _match(path, line):
    """Regex for a message naming the file and the line."""
    return re.escape(f"{path}, line {line}:")


# --- good files ---------------------------------------------------------------------------------


def test_good_file_round_trips(tmp_path):
    t, pos, quat = _good_rows(t0=5.0)
    raw = quat * np.array([[2.0], [0.5], [1.0], [3.0], [1.0], [0.25]])  # not unit: read normalises
    path = _write(tmp_path / "a.csv", HEADER, np.concatenate([t[:, None], pos, raw], axis=1))
    tracks = read_tracks(path)
    assert list(tracks) == [""]
    tr = tracks[""]
    assert tr.n_frames == 6 and tr.source == str(path) and tr.wrench is None
    np.testing.assert_allclose(tr.t, t - 5.0, atol=1e-12)
    assert tr.t[0] == 0.0
    np.testing.assert_array_equal(tr.pos, pos)
    np.testing.assert_allclose(np.linalg.norm(tr.quat, axis=1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(np.abs(np.sum(tr.quat * quat, axis=1)), 1.0, rtol=1e-14)  # same rotations
    assert tr.dt == pytest.approx(0.1)


def test_quaternion_sign_is_made_continuous(tmp_path):
    n = 8
    t = np.arange(n) * 0.05
    angles = np.linspace(0.0, 1.0, n)
    quat = Rotation.from_rotvec(angles[:, None] * np.array([0.0, 0.6, 0.8])).as_quat()[:, [3, 0, 1, 2]]
    written = quat.copy()
    written[3] *= -1.0  # one row flipped
    written[5:] *= -1.0  # and every row from 5 on
    path = _write(tmp_path / "flip.csv", HEADER, np.concatenate([t[:, None], np.zeros((n, 3)), written], axis=1))
    tr = read_tracks(path)[""]
    np.testing.assert_allclose(tr.quat, quat * np.sign(quat[0, 0] * tr.quat[0, 0]), atol=1e-14)
    assert np.all(np.sum(tr.quat[1:] * tr.quat[:-1], axis=1) > 0)


def test_file_without_t_needs_fps(tmp_path):
    _, pos, quat = _good_rows(n=5)
    path = _write(tmp_path / "no_t.csv", "x,y,z,qw,qx,qy,qz", np.concatenate([pos, quat], axis=1))
    with pytest.raises(TrackFileError, match=re.escape(str(path)) + ".*--fps"):
        read_tracks(path)
    tr = read_tracks(path, fps=30.0)[""]
    np.testing.assert_allclose(tr.t, np.arange(5) / 30.0, rtol=1e-15)
    np.testing.assert_array_equal(tr.pos, pos)
    with pytest.raises(TrackFileError, match="positive"):
        read_tracks(path, fps=0.0)


def test_t_and_fps_together_is_an_error(tmp_path):
    t, pos, quat = _good_rows()
    path = _write(tmp_path / "both.csv", HEADER, np.concatenate([t[:, None], pos, quat], axis=1))
    with pytest.raises(TrackFileError, match=re.escape(str(path)) + ".*frame rate"):
        read_tracks(path, fps=10.0)


def test_body_column_gives_one_track_per_body(tmp_path):
    """The interleaved layout `dano simulate` writes: one row per frame per body."""
    n = 5
    t = np.arange(n) * 0.01
    pos = {"box": np.arange(3 * n, dtype=float).reshape(n, 3), "ball": -np.arange(3 * n, dtype=float).reshape(n, 3)}
    quat = {"box": _unit_quats(n, seed=2), "ball": _unit_quats(n, seed=3)}
    rows = []
    for k in range(n):
        for name in ("box", "ball"):
            rows.append(f"{t[k]:.6f},{name}," + ",".join(f"{v:.17g}" for v in (*pos[name][k], *quat[name][k])))
    path = _write(tmp_path / "sim.csv", "t,body,x,y,z,qw,qx,qy,qz", rows)
    tracks = read_tracks(path)
    assert sorted(tracks) == ["ball", "box"]
    for name, tr in tracks.items():
        np.testing.assert_allclose(tr.t, t, atol=1e-12)
        np.testing.assert_array_equal(tr.pos, pos[name])
        np.testing.assert_allclose(np.abs(np.sum(tr.quat * quat[name], axis=1)), 1.0, rtol=1e-14)


def test_bodies_sampled_at_different_times_is_an_error(tmp_path):
    rows = [f"{0.1 * k:.3f},a,0,0,0,1,0,0,0" for k in range(4)] + [f"{0.1 * k:.3f},b,0,0,0,1,0,0,0" for k in range(5)]
    path = _write(tmp_path / "bodies.csv", "t,body,x,y,z,qw,qx,qy,qz", rows)
    with pytest.raises(TrackFileError, match=re.escape(str(path)) + ".*'b'"):
        read_tracks(path)


def test_reference_format_header_with_fps(tmp_path):
    _, pos, quat = _good_rows(n=4)
    path = _write(tmp_path / "ref.csv", "px,py,pz,qw,qx,qy,qz", np.concatenate([pos, quat], axis=1))
    tr = read_tracks(path, fps=148.0)[""]
    np.testing.assert_array_equal(tr.pos, pos)
    np.testing.assert_allclose(tr.t, np.arange(4) / 148.0, rtol=1e-15)


@pytest.mark.parametrize("n_wrench", [3, 6])
def test_wrench_columns(tmp_path, n_wrench):
    t, pos, quat = _good_rows()
    w = np.random.default_rng(4).normal(size=(6, n_wrench))
    header = HEADER + "," + ",".join(["fx", "fy", "fz", "tx", "ty", "tz"][:n_wrench])
    path = _write(tmp_path / "w.csv", header, np.concatenate([t[:, None], pos, quat, w], axis=1))
    tr = read_tracks(path)[""]
    assert tr.wrench is not None and tr.wrench.shape == (6, 6)
    np.testing.assert_array_equal(tr.wrench[:, :n_wrench], w)
    np.testing.assert_array_equal(tr.wrench[:, n_wrench:], 0.0)


def test_incomplete_wrench_columns_are_an_error(tmp_path):
    t, pos, quat = _good_rows()
    path = _write(tmp_path / "w.csv", HEADER + ",fx,fy", np.concatenate([t[:, None], pos, quat, pos[:, :2]], axis=1))
    with pytest.raises(TrackFileError, match=_match(path, 1) + ".*fx,fy,fz"):
        read_tracks(path)


# --- bad files: each error names the file and the line (header = line 1) ------------------------


def _rows_text(n=6, dt=0.1):
    t, pos, quat = _good_rows(n=n, dt=dt)
    return [",".join(repr(float(v)) for v in (t[k], *pos[k], *quat[k])) for k in range(n)]


def test_missing_column(tmp_path):
    rows = [r.rsplit(",", 1)[0] for r in _rows_text()]
    path = _write(tmp_path / "miss.csv", "t,x,y,z,qw,qx,qy", rows)
    with pytest.raises(TrackFileError, match=_match(path, 1) + ".*'qz'"):
        read_tracks(path)


@pytest.mark.parametrize(
    ("row", "field", "value", "line", "message"),
    [
        (2, 2, "nan", 4, "NaN"),  # a NaN position
        (4, 0, "inf", 6, "infinite"),  # an infinite time
        (0, 5, "abc", 2, "not a number"),  # text in a quaternion
    ],
    ids=["nan", "infinite-time", "non-numeric"],
)
def test_a_bad_value_names_its_line(tmp_path, row, field, value, line, message):
    rows = _rows_text()
    fields = rows[row].split(",")
    fields[field] = value
    rows[row] = ",".join(fields)
    path = _write(tmp_path / "bad.csv", HEADER, rows)
    with pytest.raises(TrackFileError, match=_match(path, line) + ".*" + message):
        read_tracks(path)


def test_blank_lines_are_skipped_but_counted(tmp_path):
    rows = _rows_text()
    rows.insert(2, "")
    fields = rows[4].split(",")
    fields[1] = "nan"
    rows[4] = ",".join(fields)  # data row 4, after a blank line: line 6
    path = _write(tmp_path / "blank.csv", HEADER, rows)
    with pytest.raises(TrackFileError, match=_match(path, 6)):
        read_tracks(path)
    rows[4] = _rows_text()[3]
    path = _write(tmp_path / "blank_ok.csv", HEADER, rows)
    assert read_tracks(path)[""].n_frames == 6


@pytest.mark.parametrize(
    ("times", "line"),
    [
        ([0.0, 0.1, 0.1, 0.3, 0.4], 4),  # equal
        ([0.0, 0.1, 0.2, 0.15, 0.4], 5),  # decreasing
        ([0.0, 0.0, 0.1, 0.2, 0.3], 3),  # equal at the start
    ],
)
def test_time_not_increasing(tmp_path, times, line):
    rows = [f"{tk!r},0,0,0,1,0,0,0" for tk in times]
    path = _write(tmp_path / "time.csv", HEADER, rows)
    with pytest.raises(TrackFileError, match=_match(path, line) + ".*does not increase"):
        read_tracks(path)


def test_irregular_frame_interval(tmp_path):
    times = [0.0, 0.1, 0.2, 0.35, 0.45, 0.55]  # one interval of 0.15 s, the median 0.1 s
    path = _write(tmp_path / "gap.csv", HEADER, [f"{tk!r},0,0,0,1,0,0,0" for tk in times])
    with pytest.raises(TrackFileError, match=_match(path, 5) + ".*regularly spaced"):
        read_tracks(path)
    slight = [0.0, 0.1, 0.2, 0.305, 0.405, 0.505]  # 5 % off: accepted
    path = _write(tmp_path / "jitter.csv", HEADER, [f"{tk!r},0,0,0,1,0,0,0" for tk in slight])
    assert read_tracks(path)[""].n_frames == 6


def test_irregular_interval_in_a_body_names_its_line(tmp_path):
    rows = []
    for k, tk in enumerate([0.0, 0.1, 0.2, 0.4, 0.5]):
        rows += [f"{tk!r},a,{k},0,0,1,0,0,0", f"{tk!r},b,{k},0,0,1,0,0,0"]
    path = _write(tmp_path / "gap2.csv", "t,body,x,y,z,qw,qx,qy,qz", rows)
    with pytest.raises(TrackFileError, match=_match(path, 8)):  # body a's 4th row: data row 7
        read_tracks(path)


def test_fewer_than_three_frames(tmp_path):
    path = _write(tmp_path / "short.csv", HEADER, _rows_text(n=2))
    with pytest.raises(TrackFileError, match=re.escape(str(path)) + ".*2 frame"):
        read_tracks(path)


def test_header_only_and_empty_file(tmp_path):
    path = _write(tmp_path / "head.csv", HEADER, [])
    with pytest.raises(TrackFileError, match=re.escape(str(path)) + ".*no data rows"):
        read_tracks(path)
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(TrackFileError, match=re.escape(str(tmp_path / "empty.csv")) + ".*empty"):
        read_tracks(tmp_path / "empty.csv")
    with pytest.raises(TrackFileError, match="cannot read"):
        read_tracks(tmp_path / "absent.csv")


def test_zero_quaternion(tmp_path):
    rows = _rows_text()
    fields = rows[2].split(",")
    fields[4:8] = ["0", "0", "0", "0"]
    rows[2] = ",".join(fields)
    path = _write(tmp_path / "zero.csv", HEADER, rows)
    with pytest.raises(TrackFileError, match=_match(path, 4) + ".*zero quaternion"):
        read_tracks(path)


@pytest.mark.parametrize(("extra", "count"), [(",1.0", 9), (None, 7)])
def test_wrong_number_of_fields(tmp_path, extra, count):
    rows = _rows_text()
    rows[3] = rows[3] + extra if extra else rows[3].rsplit(",", 1)[0]
    path = _write(tmp_path / "fields.csv", HEADER, rows)
    with pytest.raises(TrackFileError, match=_match(path, 5) + f" {count} fields"):
        read_tracks(path)


# --- velocity estimates ------------------------------------------------------------------------


def test_estimate_velocity_recovers_constant_acceleration_and_body_rate():
    """Positions p0 + v0 t + a t²/2 are a quadratic, so the fit is exact. Orientations
    q(t) = q0 ⊗ exp(ω t) give q_k⁻¹ ⊗ q_j = exp(ω (t_j - t_k)), whose rotation vector is exactly
    ω (t_j - t_k): linear in time, so that fit is exact too. The tolerance only covers round-off in
    scipy's quaternion -> rotation vector (~1e-16 rad) divided by the window's time span (~0.04 s),
    amplified by the least-squares solve: about 5e-14 seen, 1e-10 allowed."""
    n, dt = 25, 0.01
    t = np.arange(n) * dt
    p0, v0, acc = np.array([0.1, -0.2, 0.3]), np.array([0.5, 1.0, -0.7]), np.array([0.0, 0.0, -9.81])
    omega = np.array([2.0, -5.0, 9.0])  # |ω| ≈ 10.5 rad/s: 2.6 rad over the track
    q0 = Rotation.from_rotvec([0.3, -0.4, 1.2])
    rot = q0 * Rotation.from_rotvec(t[:, None] * omega)
    quat = rot.as_quat()[:, [3, 0, 1, 2]]
    tr = Track(t=t, pos=p0 + t[:, None] * v0 + 0.5 * t[:, None] ** 2 * acc, quat=quat)
    for k in (0, 1, n // 2, n - 2, n - 1):
        for half_width in (1, 2, 4):
            v, w = estimate_velocity(tr, k, half_width=half_width)
            np.testing.assert_allclose(v, v0 + acc * t[k], rtol=0, atol=1e-10)
            np.testing.assert_allclose(w, omega, rtol=0, atol=1e-10)
    # it is the body-frame rate, not the world-frame one (which differs for a rotated q0)
    world = rot[n // 2].apply(omega)
    assert np.linalg.norm(world - omega) > 1.0
    assert np.linalg.norm(estimate_velocity(tr, n // 2)[1] - world) > 1.0


def test_estimate_velocity_on_a_three_frame_track():
    t = np.array([0.0, 0.5, 1.0])
    tr = Track(t=t, pos=np.stack([t, t * t, np.zeros(3)], axis=1), quat=np.tile([1.0, 0.0, 0.0, 0.0], (3, 1)))
    for k in range(3):
        v, w = estimate_velocity(tr, k)
        np.testing.assert_allclose(v, [1.0, 2 * t[k], 0.0], atol=1e-12)
        np.testing.assert_allclose(w, 0.0, atol=1e-12)


# --- plane of motion ---------------------------------------------------------------------------


def _tilted_arc(n=40):
    normal = np.array([0.2, -0.3, 1.0])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    phi = np.linspace(0.0, 2.0, n)  # a 115° arc
    pos = np.array([0.5, 0.2, 0.03]) + 0.3 * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return normal, Track(t=np.arange(n) * 0.01, pos=pos, quat=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))


def test_motion_plane_normal_of_a_tilted_arc():
    normal, tr = _tilted_arc()
    found = motion_plane_normal([tr])
    assert found.shape == (3,)
    assert np.linalg.norm(found) == pytest.approx(1.0, rel=1e-14)
    assert abs(found @ normal) == pytest.approx(1.0, abs=1e-12)
    # two tracks in parallel planes a few mm apart (different heights of the centre of mass)
    in_plane = tr.pos[0] + 0.5 * (tr.pos[::-1] - tr.pos[0])  # a smaller arc in the same plane
    shifted = Track(t=tr.t, pos=in_plane + 0.004 * normal, quat=tr.quat)
    assert abs(motion_plane_normal([tr, shifted]) @ normal) > 1 - 1e-3


def test_motion_plane_normal_refuses_a_noisy_straight_line_and_a_3d_path():
    n = 60
    rng = np.random.default_rng(5)
    s = np.linspace(0.0, 1.0, n)
    line = np.array([0.1, 0.2, 0.0]) + s[:, None] * np.array([0.3, -0.5, 0.05]) + 1e-4 * rng.normal(size=(n, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    with pytest.raises(TrackFileError, match="straight"):
        motion_plane_normal([Track(t=s, pos=line, quat=q)])
    axis = np.zeros((n, 3))
    axis[:, 0] = s
    with pytest.raises(TrackFileError, match="straight"):
        motion_plane_normal([Track(t=s, pos=axis, quat=q)])
    helix = np.stack([np.cos(6 * s), np.sin(6 * s), s], axis=1)
    with pytest.raises(TrackFileError):
        motion_plane_normal([Track(t=s, pos=helix, quat=q)])


def test_motion_plane_normal_refuses_an_exact_straight_line():
    n = 50
    s = np.linspace(0.0, 1.0, n)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    rng = np.random.default_rng(0)
    for _ in range(20):
        line = rng.normal(size=3) + s[:, None] * rng.normal(size=3)
        with pytest.raises(TrackFileError, match="straight"):
            motion_plane_normal([Track(t=s, pos=line, quat=q)])


# --- units and frames --------------------------------------------------------------------------


def _track_with_wrench():
    t, pos, quat = _good_rows()
    wrench = np.random.default_rng(6).normal(size=(6, 6))
    return Track(t=t, pos=pos, quat=quat, wrench=wrench, source="x.csv")


def test_to_metric_scales_positions_only():
    tr = _track_with_wrench()
    m = to_metric(tr, 0.001)
    np.testing.assert_allclose(m.pos, tr.pos * 0.001, rtol=1e-15)
    np.testing.assert_array_equal(m.t, tr.t)
    np.testing.assert_array_equal(m.quat, tr.quat)
    np.testing.assert_array_equal(m.wrench, tr.wrench)
    assert m.source == tr.source
    np.testing.assert_array_equal(tr.pos, _track_with_wrench().pos)  # the original is untouched


def test_rotate_moves_positions_and_orientations_consistently():
    tr = _track_with_wrench()
    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    offset = np.array([1.0, -2.0, 0.5])
    out = rotate(tr, R, offset)
    np.testing.assert_allclose(out.pos, tr.pos @ R.T + offset, atol=1e-14)
    np.testing.assert_array_equal(out.t, tr.t)
    np.testing.assert_allclose(np.linalg.norm(out.quat, axis=1), 1.0, rtol=1e-14)
    mats = Rotation.from_quat(tr.quat[:, [1, 2, 3, 0]]).as_matrix()
    new = Rotation.from_quat(out.quat[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(new, R @ mats, atol=1e-14)
    # a point fixed in the body lands where the moved pose puts it
    body_point = np.array([0.02, -0.01, 0.03])
    world = tr.pos + mats @ body_point
    np.testing.assert_allclose(out.pos + new @ body_point, world @ R.T + offset, atol=1e-14)
    assert out.wrench is not None and tr.wrench is not None
    np.testing.assert_allclose(out.wrench[:, :3], tr.wrench[:, :3] @ R.T, atol=1e-14)
    np.testing.assert_allclose(out.wrench[:, 3:], tr.wrench[:, 3:] @ R.T, atol=1e-14)
    assert np.all(np.sum(out.quat[1:] * out.quat[:-1], axis=1) * np.sum(tr.quat[1:] * tr.quat[:-1], axis=1) > 0)
    no_offset = rotate(tr, R)
    np.testing.assert_allclose(no_offset.pos, tr.pos @ R.T, atol=1e-14)


def test_from_poses():
    _, pos, quat = _good_rows(n=5)
    tr = Track.from_poses(np.concatenate([pos, 2.0 * quat], axis=1), dt=0.02, source="sim")
    np.testing.assert_allclose(tr.t, np.arange(5) * 0.02)
    np.testing.assert_array_equal(tr.pos, pos)
    np.testing.assert_allclose(tr.quat, quat, rtol=1e-15)
    assert tr.wrench is None and tr.source == "sim" and tr.dt == pytest.approx(0.02)
