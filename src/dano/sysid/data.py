"""Observed pose trajectories: reading and checking CSV files, and putting them in metres.

A track is what a pose tracker gives for one body: times t (T,) in s, centre-of-mass positions
(T, 3) and orientations (T, 4) as unit quaternions (w, x, y, z), object frame -> world. Files are
CSV with a header:

    t,x,y,z,qw,qx,qy,qz            one body (or without t, with a frame rate)
    t,body,x,y,z,qw,qx,qy,qz       several bodies, as `dano simulate` writes
    px,py,pz,qw,qx,qy,qz           the paper authors' files (`px` is accepted for `x`)

with optional fx,fy,fz[,tx,ty,tz]: a known external wrench on that body (world frame, N and N m
about its centre of mass) held from that frame to the next. Every way a file can be wrong gets a
`TrackFileError` naming the file and line.
"""

import csv
import dataclasses
from pathlib import Path

import numpy as np

from dano.errors import DanoError


class TrackFileError(DanoError):
    """A pose-trajectory file that cannot be used (missing columns, NaN, time not increasing, ...)."""


@dataclasses.dataclass(frozen=True)
class Track:
    """Observed poses of one body at regularly spaced times.

    Attributes:
        t: (T,) times, s, increasing.
        pos: (T, 3) centre of mass, world frame (m after `to_metric`).
        quat: (T, 4) unit quaternions (w, x, y, z), object frame -> world, sign-continuous.
        wrench: (T, 6) known external force and torque on the body from each frame to the next
            (world frame, N and N m about the centre of mass), or None.
        source: where it came from, for messages.
    """

    t: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    wrench: np.ndarray | None = None
    source: str = ""

    @property
    def n_frames(self) -> int:
        return len(self.t)

    @classmethod
    def from_poses(cls, poses: np.ndarray, dt: float, source: str = "") -> "Track":
        """A track from (T, 7) rows x, y, z, qw, qx, qy, qz sampled every `dt` s (e.g. `body_poses`)."""
        poses = np.asarray(poses, dtype=float)
        quat = poses[:, 3:7] / np.linalg.norm(poses[:, 3:7], axis=1, keepdims=True)
        return cls(t=np.arange(len(poses)) * dt, pos=poses[:, :3].copy(), quat=quat, source=source)

    def frames(self, first: int, stop: int | None = None) -> "Track":
        """Rows first … stop − 1 (0-based, as a Python slice; `stop` None: to the end)."""
        rows = slice(first, stop)
        wrench = None if self.wrench is None else self.wrench[rows]
        return dataclasses.replace(self, t=self.t[rows], pos=self.pos[rows], quat=self.quat[rows], wrench=wrench)

    @property
    def dt(self) -> float:
        """The frame interval, s (the median spacing)."""
        return float(np.median(np.diff(self.t)))


_ALIASES = {"px": "x", "py": "y", "pz": "z"}
_POSE = ("x", "y", "z", "qw", "qx", "qy", "qz")
_WRENCH = ("fx", "fy", "fz", "tx", "ty", "tz")
MIN_FRAMES = 3
TIMING_TOLERANCE = 0.1
"""Largest allowed deviation of a frame interval from the median, as a fraction of it."""


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _transposed(rows: list[list[str]]) -> list[list[str]]:
    """A file stored one row per coordinate (`x,0.1,0.2,...` / `y,...`: 7 x N, as some trackers
    write) as one row per frame; any other file unchanged."""
    names = [_ALIASES.get(r[0].strip().lower(), r[0].strip().lower()) if r else "" for r in rows if any(r)]
    if not (set(_POSE) <= set(names) and len(names) == len(set(names)) and len(names) <= 16):
        return rows
    kept = [r for r in rows if any(r)]
    if len({len(r) for r in kept}) != 1:
        return rows  # ragged: let the row checks name the line
    return [list(column) for column in zip(*kept, strict=True)]


def read_tracks(path: str | Path, fps: float | None = None) -> dict[str, Track]:
    """Reads a pose CSV into one `Track` per body (key "" when the file has no `body` column).

    A file stored one row per coordinate, each row starting with its name (`x,0.1,0.2,...`), is
    read as its transpose.

    Args:
        path: the CSV file (format in the module docstring).
        fps: frames per second, for files without a `t` column.

    Raises:
        TrackFileError: naming the file and line of the first problem.
    """
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise TrackFileError(f"{path}: cannot read ({e.strerror})") from None
    if not rows:
        raise TrackFileError(f"{path}: empty file")
    rows = _transposed(rows)
    header = [_ALIASES.get(h.strip().lower(), h.strip().lower()) for h in rows[0]]
    missing = [c for c in _POSE if c not in header]
    if missing and all(_is_number(h) for h in header if h.strip()):
        raise TrackFileError(
            f"{path}, line 1: numbers, not column names: the first line must name the columns "
            "t,x,y,z,qw,qx,qy,qz (a file with one row per coordinate needs its name first on each row)"
        )
    if missing:
        raise TrackFileError(f"{path}, line 1: missing column(s) {missing}; need t,x,y,z,qw,qx,qy,qz (or --fps)")
    has_t = "t" in header
    if has_t and fps is not None:
        raise TrackFileError(f"{path}: has a t column and a frame rate was given too; give one")
    if not has_t and fps is None:
        raise TrackFileError(f"{path}: no t column: give the frame rate (--fps)")
    if fps is not None and not fps > 0:
        raise TrackFileError(f"{path}: frame rate must be positive, got {fps}")
    wrench_cols = [c for c in _WRENCH if c in header]
    if wrench_cols and wrench_cols != list(_WRENCH[: len(wrench_cols)]) or len(wrench_cols) not in (0, 3, 6):
        raise TrackFileError(f"{path}, line 1: a known wrench needs columns fx,fy,fz or fx,fy,fz,tx,ty,tz")
    numeric = (["t"] if has_t else []) + list(_POSE) + wrench_cols
    index = {c: header.index(c) for c in numeric}
    body_col = header.index("body") if "body" in header else None

    per_body: dict[str, list[tuple[int, list[float]]]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not v.strip() for v in row):
            continue
        if len(row) != len(header):
            raise TrackFileError(f"{path}, line {line}: {len(row)} fields, the header has {len(header)}")
        try:
            values = [float(row[index[c]]) for c in numeric]
        except ValueError:
            raise TrackFileError(f"{path}, line {line}: not a number in {row}") from None
        if not np.all(np.isfinite(values)):
            raise TrackFileError(f"{path}, line {line}: NaN or infinite value in {row}")
        name = row[body_col].strip() if body_col is not None else ""
        per_body.setdefault(name, []).append((line, values))
    if not per_body:
        raise TrackFileError(f"{path}: no data rows")
    tracks = {name: _track(path, entries, has_t, fps, len(wrench_cols)) for name, entries in per_body.items()}
    first = next(iter(tracks.values()))
    for name, tr in tracks.items():
        if tr.n_frames != first.n_frames or not np.allclose(tr.t, first.t, atol=1e-9):
            raise TrackFileError(f"{path}: body {name!r} is sampled at other times than the first body")
    return tracks


def _track(path: Path, entries: list[tuple[int, list[float]]], has_t: bool, fps, n_wrench: int) -> Track:
    lines = [line for line, _ in entries]
    data = np.array([v for _, v in entries], dtype=float)
    if len(data) < MIN_FRAMES:
        raise TrackFileError(f"{path}: {len(data)} frame(s); at least {MIN_FRAMES} are needed")
    if has_t:
        t, data = data[:, 0], data[:, 1:]
    else:
        t = np.arange(len(data)) / fps
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise TrackFileError(f"{path}, line {lines[k]}: time {t[k]:g} s does not increase (previous {t[k - 1]:g} s)")
    dt = np.median(steps)
    off = np.abs(steps - dt) > TIMING_TOLERANCE * dt
    if np.any(off):
        k = int(np.argmax(off)) + 1
        raise TrackFileError(
            f"{path}, line {lines[k]}: frame interval {steps[k - 1]:.4g} s, but the median is {dt:.4g} s: "
            "frames must be regularly spaced (fill dropped frames by interpolation)"
        )
    quat = data[:, 3:7]
    norm = np.linalg.norm(quat, axis=1)
    if np.any(norm < 1e-9):
        k = int(np.argmax(norm < 1e-9))
        raise TrackFileError(f"{path}, line {lines[k]}: zero quaternion")
    quat = quat / norm[:, None]
    flips = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=1) < 0, -1.0, 1.0))
    quat[1:] *= flips[:, None]  # continuous sign: q and -q are the same rotation
    wrench = None
    if n_wrench:
        wrench = np.zeros((len(t), 6))
        wrench[:, :n_wrench] = data[:, 7 : 7 + n_wrench]
    return Track(t=t - t[0], pos=data[:, :3], quat=quat, wrench=wrench, source=str(path))


def to_metric(track: Track, scale: float) -> Track:
    """The track with positions multiplied by `scale` (metres per tracker unit); wrenches are left as
    given (they are in N and N m already)."""
    return dataclasses.replace(track, pos=track.pos * scale)


def rotate(track: Track, R: np.ndarray, offset: np.ndarray | None = None) -> Track:
    """The track seen in another frame: x' = R x + offset, q' = quat(R) ⊗ q; wrenches rotated too."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(R)
    q = Rotation.from_quat(track.quat[:, [1, 2, 3, 0]])
    quat = (rot * q).as_quat()[:, [3, 0, 1, 2]]
    quat *= np.where(quat[:1, :1] < 0, -1.0, 1.0)
    pos = track.pos @ R.T + (0.0 if offset is None else offset)
    wrench = None if track.wrench is None else np.concatenate([track.wrench[:, :3] @ R.T, track.wrench[:, 3:] @ R.T], 1)
    return dataclasses.replace(track, pos=pos, quat=quat, wrench=wrench)


def motion_plane_normal(tracks: list[Track], min_ratio: float = 5.0) -> np.ndarray:
    """Unit normal of the plane the centre of mass moves in (both signs are candidates for "up").

    A sliding object's centre of mass stays at a constant height over the table, so its positions
    lie on a plane whose normal is the gravity axis. The smallest principal axis of all positions is
    taken; the motion must span the plane: the middle singular value must be `min_ratio` times the
    smallest (and not round-off next to the largest: a straight path fixes no plane).

    Raises:
        TrackFileError: the motion is too straight or too three-dimensional to fix a plane.
    """
    pos = np.concatenate([tr.pos for tr in tracks])
    centred = pos - pos.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    if not (s[1] > min_ratio * s[2] and s[1] > 1e-6 * s[0]):
        raise TrackFileError(
            f"cannot fit gravity from the plane of motion: the positions spread {s[0]:.3g}, {s[1]:.3g}, "
            f"{s[2]:.3g} along their principal axes (a straight or a 3-D path does not fix a plane); "
            "give the gravity direction instead"
        )
    return vt[2] / np.linalg.norm(vt[2])


def estimate_velocity(track: Track, k: int, half_width: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Velocity at frame k from the poses around it: (linear (3,) world, m/s; angular (3,) body frame, rad/s).

    A quadratic is fitted by least squares to the frames k - half_width ... k + half_width (cut to the
    track, at least 3 frames) and differentiated at t_k; for the orientation, to the rotation vectors
    of q_k⁻¹ ⊗ q_j (the body-frame rotation from frame k), whose derivative at t_k is the body-frame
    angular velocity (what a MuJoCo free joint's qvel holds).
    """
    from scipy.spatial.transform import Rotation

    lo, hi = max(0, k - half_width), min(track.n_frames, k + half_width + 1)
    if hi - lo < 3:
        lo, hi = max(0, hi - 3), max(hi, min(track.n_frames, lo + 3))
    tau = track.t[lo:hi] - track.t[k]
    q = Rotation.from_quat(track.quat[lo:hi][:, [1, 2, 3, 0]])
    q_k = Rotation.from_quat(track.quat[k][[1, 2, 3, 0]])
    rotvec = (q_k.inv() * q).as_rotvec()
    basis = np.stack([np.ones_like(tau), tau, tau * tau], axis=1)
    coef, *_ = np.linalg.lstsq(basis, np.concatenate([track.pos[lo:hi], rotvec], axis=1), rcond=None)
    return coef[1, :3], coef[1, 3:]


def write_track(path: str | Path, track: Track) -> None:
    """Writes `t,x,y,z,qw,qx,qy,qz` (and the wrench columns if any), atomically."""
    from dano.io import atomic_write

    header = ["t", *_POSE] + (list(_WRENCH) if track.wrench is not None else [])
    columns = [track.t[:, None], track.pos, track.quat] + ([track.wrench] if track.wrench is not None else [])
    rows = np.concatenate(columns, axis=1)
    with atomic_write(path, suffix=".csv") as tmp, open(tmp, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(header)
        out.writerows([[f"{v:.12g}" for v in row] for row in rows])
