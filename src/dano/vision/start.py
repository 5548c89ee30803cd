"""The initial state of a fit to masks: the first frames tracked (or a pose track given), put on the
ground along the camera's rays when they start near it, flips of a symmetric object undone."""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Float

from dano.math import quat_conj, quat_mul, quat_to_mat
from dano.sim.scene import Scene
from dano.sysid.data import Track
from dano.vision.camera import Camera
from dano.vision.observation import MaskConfig, MaskError
from dano.vision.track import TrackConfig, track


def first_frames(field, camera, masks, visible, fps, target, scene, start_pose, config: MaskConfig, progress):
    """The centre of mass's track over the first visible frames (`config.init_seconds`), by the
    per-frame tracker, put on the ground along the camera's rays where it starts near it
    (`_along_rays`); with what that moved (None: nothing)."""
    want = max(3, int(np.ceil(config.init_seconds * fps - 1e-6)))
    k = 0
    while k < min(want, len(masks)) and visible[k]:
        k += 1
    if k < 3:
        raise MaskError(f"the first 3 masks must show the object to start from (frame {k} is empty)")
    com = np.asarray(target.dano.com)
    result = track(field, camera, masks[:k], TrackConfig(), init=start_pose, progress=progress)
    quats = unflipped(result.quats)
    rot = np.asarray(quat_to_mat(jnp.asarray(quats)))
    pos, moved = _along_rays(
        result.positions + np.einsum("tij,j->ti", rot, com), rot, target.dano, scene, camera, config
    )
    return Track(t=np.arange(k) / fps, pos=_quadratic(pos), quat=quats, source="masks (first frames tracked)"), moved


def _along_rays(pos, rot, dano, scene: Scene, camera: Camera, config: MaskConfig):
    """Tracked centres of mass (k, 3) moved along the camera's rays to the height at which the
    first frame's orientation rests on the ground, when its lowest point is within `config.settle`
    of it (a body sliding on the ground keeps its centre's height; the tracked tilts of later frames
    are no better than their depths); with a report.

    A silhouette fixes where the object is across the view far better than along it: an edge eroded
    or dilated by a pixel reads as the object farther or nearer, by centimetres at a few dozen pixels
    (bench/pixels.py, box 120 fps noisy: the first six frames tracked 1.5-3.8 cm above the table and
    as much off across it, an initial velocity off by 2 m/s). Settling straight down (`make_problem`)
    keeps the error across; along the ray it goes: there, within 5 mm.
    """
    if scene.ground_height is None:
        return pos, None
    n = np.asarray(scene.ground_normal, dtype=float)
    n = n / np.linalg.norm(n)
    offsets = np.asarray(dano.points, dtype=float) - np.asarray(dano.com, dtype=float)
    lowest = np.min(np.einsum("ij,pj,i->p", rot[0], offsets, n))  # the first frame's lowest point, from the centre
    gap = float(pos[0] @ n + lowest - float(scene.ground_height))
    if not gap <= config.settle:
        return pos, None
    eye = np.asarray(camera.position, dtype=float)
    along = (pos - eye) @ n
    if np.any(np.abs(along) < 1e-9):  # a ray parallel to the ground: nothing to intersect
        return pos, None
    scale = (float(scene.ground_height) - lowest - eye @ n) / along
    if np.any(scale <= 0):  # the ground behind the camera along a ray
        return pos, None
    moved = eye + scale[:, None] * (pos - eye)
    shift = np.linalg.norm(moved - pos, axis=1)
    return moved, {"frames": len(pos), "max_moved_m": float(shift.max()), "first_gap_m": gap}


def _quadratic(pos: Float[np.ndarray, "k 3"]) -> Float[np.ndarray, "k 3"]:
    """The least-squares quadratic in time through the positions: the initial velocity is read from
    the first three frames, and one noisy mask (an eroded or dilated edge moves the tracked depth by
    millimetres) would otherwise set it."""
    t = np.arange(len(pos), dtype=float)
    basis = np.stack([np.ones_like(t), t, t * t], axis=1)
    coef, *_ = np.linalg.lstsq(basis, pos, rcond=None)
    return basis @ coef


_HALF_TURNS = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""The identity and the half turns about the object frame's x, y and z axes (w, x, y, z)."""


def unflipped(quats: Float[np.ndarray, "n 4"]) -> Float[np.ndarray, "n 4"]:
    """Tracked orientations with half-turn flips undone: a frame more than 90° from where the frames
    before put it (at constant angular velocity) becomes whichever of q, q·Rx(π), q·Ry(π), q·Rz(π)
    is nearest that prediction. A mask cannot tell these apart for an object symmetric about its
    frame's axes (a box: the tracker may report it upside down from one frame to the next), and a
    turn of more than 90° between two frames is no slide's; the initial angular velocity read
    from a flipped frame would be absurd.
    """
    quats = np.asarray(quats, dtype=float)
    out = [quats[0]]
    for k in range(1, len(quats)):
        guess = out[-1] if k < 2 else np.asarray(quat_mul(quat_mul(out[-1], quat_conj(out[-2])), out[-1]))
        if _angle(quats[k], guess) > 0.5 * np.pi:
            candidates = np.asarray(quat_mul(jnp.asarray(quats[k])[None], jnp.asarray(_HALF_TURNS)))
            out.append(min(candidates, key=lambda c: _angle(c, guess)))
        else:
            out.append(quats[k])
    return np.stack(out)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(2.0 * np.arccos(np.clip(abs(float(np.dot(a, b))), 0.0, 1.0)))


def padded(start: Track, n: int, dt: float) -> Track:
    """The start track extended to n frames by its last pose (poses after the start are not used:
    the masks are the data), on the masks' clock."""
    if abs(start.dt - dt) > 1e-6 * dt:
        raise MaskError(f"the start track's frame rate {1 / start.dt:.6g} fps is not the masks' {1 / dt:.6g}")
    k = min(start.n_frames, n)
    index = np.minimum(np.arange(n), k - 1)
    return Track(t=np.arange(n) * dt, pos=start.pos[index], quat=start.quat[index], source=start.source)
