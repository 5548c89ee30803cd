"""Shooting windows: what was observed (`Recording`, `Observed`), and each run cut into windows that
start from the observed state (pose from the data, velocity estimated or fitted, a body near the
ground settled onto it) and are stacked for `vmap` (`Windows`)."""

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from dano.sim.world import Params, World, pairs
from dano.sysid.configs import SysidError
from dano.sysid.data import Track, estimate_velocity


@dataclasses.dataclass(frozen=True)
class Recording:
    """One observed run.

    Attributes:
        tracks: observed poses by scene body name: DANOs and free or actuated primitives are
            observations; a mocap primitive's track is its prescribed path (a known input). All
            tracks share the same times.
        ctrl: (T - 1, nu) known actuator controls from each frame to the next (robot servo targets,
            then actuated primitives' forces), or None for zeros.
    """

    tracks: Mapping[str, Track]
    ctrl: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return next(iter(self.tracks.values())).n_frames

    @property
    def dt(self) -> float:
        return next(iter(self.tracks.values())).dt


class Windows(eqx.Module):
    """All shooting windows of all recordings, stacked on a leading axis n (padded to W frames)."""

    qpos: Float[Array, "n nq"]
    """Initial qpos of each window (observed bodies from the data, the others from the scene)."""
    qvel: Float[Array, "n nv"]
    mocap0: Float[Array, "n k 3"]
    """Mocap body positions at the window's first frame."""
    mocap: Float[Array, "n w k 3"]
    """Mocap positions at the end of each frame of the window."""
    ctrl: Float[Array, "n w nu"]
    external: Float[Array, "n w nbody 6"]
    target_pos: Float[Array, "n w b 3"]
    """Observed positions at the window's frames 1..W, per observed body."""
    target_quat: Float[Array, "n w b 4"]
    mask: Float[Array, "n w"]
    """1 where the frame exists, 0 in the padding of a short last window."""
    basis: Float[Array, "n S s"]
    """Maps the s fitted initial-state unknowns to the S corrections of qpos/qvel (see `start_state`)."""
    observed: PyTree | None = None
    """What an `AbstractObservation` compares each window with (a pytree, leading axis n), or None."""


@dataclasses.dataclass(frozen=True)
class Observed:
    """An observed body: where its state lives in qpos/qvel and how it moves."""

    name: str
    qpos: int
    qvel: int
    kind: str  # "free" (7 qpos, 6 qvel) or "slide" (3 + 3: an actuated primitive, no rotation)
    offset: tuple[float, ...]  # (3,) world position at qpos = 0 (slides)
    length: float  # m/rad, turns a rotation error into a length
    weight: float = 1.0  # multiplies the rotation residuals (0: positions only)

    @property
    def n_velocity(self) -> int:
        return 6 if self.kind == "free" else 3


def build_windows(scene, world, params, model, recordings, observed, qpos0, qvel0, W, settle, initial):
    """Cuts every recording into windows of W frame intervals and stacks them; also returns what
    settling changed ({"window", "body", "moved_m", "normal_speed_dropped_m_s"} per settled body)."""
    mocap_names = [p.name for p in scene.primitives if p.mode == "mocap"]
    mocap_home = np.array([p.pos for p in scene.primitives if p.mode == "mocap"], dtype=float).reshape(-1, 3)
    moving = len(world.dano_qpos) + sum(p.moving for p in world.prims)
    rows, report = [], []
    for r in recordings:
        T = r.n_frames
        starts = list(range(0, T - 1, W))
        unobserved = moving - len([o for o in observed if o.name in r.tracks])
        if len(starts) > 1 and (unobserved > 0 or world.links):
            raise SysidError(
                "multiple shooting restarts every moving body from the data: observe all of them (DANOs, free "
                "and actuated primitives), and no robot, or use one window"
            )
        mocap = np.broadcast_to(mocap_home, (T, *mocap_home.shape)).copy()
        for j, name in enumerate(mocap_names):
            if name in r.tracks:
                mocap[:, j] = r.tracks[name].pos
        ctrl = np.zeros((T - 1, model.nu)) if r.ctrl is None else np.asarray(r.ctrl, dtype=float)
        if ctrl.shape != (T - 1, model.nu):
            raise SysidError(f"ctrl must be (frames - 1, nu) = {(T - 1, model.nu)}, got {ctrl.shape}")
        external = np.zeros((T, model.nbody, 6))
        for o in observed:
            track = r.tracks.get(o.name)
            if track is not None and track.wrench is not None:
                external[:, model.body(o.name).id] = track.wrench
        for s in starts:
            row = _window(r, observed, qpos0, qvel0, mocap, ctrl, external, s, W)
            settled = {}
            if settle > 0 and world.ground_height is not None:
                settled = _settle(world, params, scene.gravity, observed, row, settle)
            report += [{"window": len(rows), "body": name, **change} for name, change in settled.items()]
            row["basis"] = _basis(observed, row, set(settled), initial, np.asarray(world.ground_normal))
            rows.append(row)
    stacked = {k: jnp.asarray(np.stack([row[k] for row in rows])) for k in rows[0] if k != "basis"}
    return Windows(**stacked, basis=jnp.asarray(_compact([row["basis"] for row in rows]))), report


def _window(r: Recording, observed, qpos0, qvel0, mocap, ctrl, external, s: int, W: int) -> dict:
    T = r.n_frames
    n = min(W, T - 1 - s)
    frames = np.minimum(np.arange(s + 1, s + W + 1), T - 1)  # pad by repeating the last frame
    steps = np.minimum(np.arange(s, s + W), T - 2)
    qpos, qvel = qpos0.copy(), qvel0.copy()
    target_pos, target_quat = [], []
    for o in observed:
        tr = r.tracks[o.name]
        lin, ang = estimate_velocity(tr, s)
        if o.kind == "free":
            qpos[o.qpos : o.qpos + 3], qpos[o.qpos + 3 : o.qpos + 7] = tr.pos[s], tr.quat[s]
            qvel[o.qvel : o.qvel + 3], qvel[o.qvel + 3 : o.qvel + 6] = lin, ang
        else:
            qpos[o.qpos : o.qpos + 3] = tr.pos[s] - np.asarray(o.offset)
            qvel[o.qvel : o.qvel + 3] = lin
        target_pos.append(tr.pos[frames])
        target_quat.append(tr.quat[frames])
    return {
        "qpos": qpos,
        "qvel": qvel,
        "mocap0": mocap[s],
        "mocap": mocap[frames],
        "ctrl": ctrl[steps],
        "external": external[steps],
        "target_pos": np.stack(target_pos, axis=1),
        "target_quat": np.stack(target_quat, axis=1),
        "mask": (np.arange(W) < n).astype(float),
    }


def _settle(world: World, params: Params, gravity, observed, row: dict, margin: float) -> dict[str, dict]:
    """Puts DANOs that start within `margin` of the ground at their resting height (in place);
    returns what changed per body name: `moved_m` along the normal, `normal_speed_dropped_m_s`,
    `tilt_rate_dropped_rad_s`.

    The height is where the contact spring carries the weight, k ψ = m |g·n| (ψ from the smooth
    inside indicator), found by bisection along the ground normal n with the orientation kept; the
    velocity along n and the spin about axes in the ground plane (rocking, which the contact damps
    within a substep; read from noisy poses it is mostly noise) are dropped. The penalty contact
    is stiff: 0.3 mm too deep and a flat face pushes with hundreds of times its weight, so a height
    read from noisy data cannot be used as is.
    """
    from scipy.spatial.transform import Rotation

    from dano.contact.overlap import indicator

    n = np.asarray(world.ground_normal)
    g_n = abs(float(np.dot(gravity, n)))
    settled = {}
    for p, (i, kind, _) in zip(params.contact, pairs(world), strict=True):
        o = next((o for o in observed if o.name == world.names[i]), None)
        if kind != "ground" or o is None or g_n == 0:
            continue
        state = world.danos[i]
        points, shares = np.asarray(state.points), np.asarray(state.shares)
        x, q = row["qpos"][o.qpos : o.qpos + 3], row["qpos"][o.qpos + 3 : o.qpos + 7]
        height = n @ (Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix() @ points + x[:, None]) - world.ground_height
        width = float(p.indicator_width)
        target = g_n / float(p.impact_spring)  # ψ / m at rest

        def load(shift, height=height, shares=shares, width=p.indicator_width):
            return float(np.sum(shares * np.asarray(indicator(jnp.asarray(height + shift), width))))

        lowest = float(np.min(height))
        if abs(lowest) > margin:
            continue
        deep, free = -lowest - margin - width, -lowest + width + 1e-9  # shifts: load(deep) > target, load(free) = 0
        for _ in range(60):
            mid = 0.5 * (deep + free)
            deep, free = (mid, free) if load(mid) > target else (deep, mid)
        shift = 0.5 * (deep + free)
        row["qpos"][o.qpos : o.qpos + 3] = x + shift * n
        v = row["qvel"][o.qvel : o.qvel + 3]
        row["qvel"][o.qvel : o.qvel + 3] = v - (v @ n) * n
        n_body = _in_body(q, n)  # the free joint's spin is in its frame
        w = row["qvel"][o.qvel + 3 : o.qvel + 6]
        tilt = w - (w @ n_body) * n_body
        row["qvel"][o.qvel + 3 : o.qvel + 6] = w - tilt
        settled[o.name] = {
            "moved_m": float(shift), "normal_speed_dropped_m_s": float(v @ n),
            "tilt_rate_dropped_rad_s": float(np.linalg.norm(tilt)),
        }  # fmt: skip
    return settled


def _in_body(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World vector `v` in the frame of a body at orientation `quat` (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(quat[[1, 2, 3, 0]]).as_matrix().T @ v


def _basis(observed, row: dict, settled: set[str], initial: str, n: np.ndarray) -> np.ndarray:
    """Columns spanning the initial-state corrections δ of a window (S, S), zero columns for the
    directions held fixed.

    A body resting on the ground (settled) keeps contact: its corrections are planar (position
    and velocity along the ground, rotation and spin about its normal). Free rocking or lifting
    velocities are nearly unobservable there (the contact damps them within a substep) and only
    let the fit wander; everywhere else all 6 (or 12) directions are free.
    """
    blocks = []
    for o in observed:
        k = {"none": 0, "velocity": 1, "state": 2}[initial]
        if o.kind != "free" or o.name not in settled:
            blocks += [np.eye(o.n_velocity)] * k
            continue
        q = row["qpos"][o.qpos + 3 : o.qpos + 7]
        n_body = _in_body(q, n)
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        planar = np.zeros((6, 6))
        planar[:3, 0], planar[:3, 1], planar[3:, 2] = t1, t2, n_body  # along the ground; about its normal
        blocks += [planar] * k
    size = sum(b.shape[0] for b in blocks)
    out = np.zeros((size, size))
    i = 0
    for b in blocks:
        out[i : i + b.shape[0], i : i + b.shape[0]] = b
        i += b.shape[0]
    return out


def _compact(bases: list[np.ndarray]) -> np.ndarray:
    """Drops the columns that are zero in every window: (n, S, s) with s the unknowns actually fitted."""
    stacked = np.stack(bases)
    used = np.any(stacked != 0, axis=(0, 1))
    return stacked[:, :, used]
