"""The active set: the few points of a pair that can touch, so that a step costs in proportion to them.

A DANO's 5000 surface points meet a floor at a few dozen to a face's quarter of them; the implicit
step evaluates its pairs' points 10-30 times per step (Newton steps and line searches), so it
solves over a fixed-size set of K points per pair instead (static shapes: jit, vmap and grad
stay as they are). Once per step, at the predicted pose:

- the points live at the start (`live`: a depth s0 where the force law is non-zero) take the
  first slots, then those within `MARGIN` of being live; points beyond K are dropped, the slots
  left over get weight 0 (inert);
- after the solve, every dropped point is checked at the solution V: it must still exert no force
  (its depth s(V) = s0 + gain d(V) outside the law's support), first by a bound over all of them
  (|d_i| <= h (|dv| + |dw| r_max)), then, if the bound does not decide, exactly, point by point.

Where the check holds, the solve over the K points is the solve over all of them: a dropped point
contributes nothing to the value, gradient and Hessian at V and nearby (the smootherstep is flat
beyond s = -1), so the solution and its derivatives are those of the dense problem, to rounding.
Where it does not (more live points than K: an overflow), the step is solved again over all the
points (`dano.sim.implicit`), exactly, and counted (`Trajectory.fallbacks`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from dano.contact.friction import Patch
from dano.contact.support import Support, normal_velocity

MARGIN = 1e-3
"""m: points within this distance of the live band (at the predicted pose) fill the slots the
live ones leave; the post-solve check, not this margin, guarantees that none is missed."""

BAND = 2e-3
"""m: `budget` counts the points within this distance of a supporting plane."""

MIN_BUDGET = 64
"""Points: the smallest budget `budget` proposes."""


def budget(points: np.ndarray, normals: np.ndarray, directions: int = 200, seed: int = 0) -> int:
    """A DANO's points per contact pair, from its geometry: the most points within `BAND` of a
    supporting plane, over `directions` directions of a Fibonacci sphere and as many of the points'
    own normals (a flat face is found along its normal, whatever its orientation), with a quarter
    more room and at least `MIN_BUDGET`; at most all of them. A flat face on a floor needs its
    whole face (a box: ~25 %); a round body a few percent.

    Args:
        points, normals: (3, n) surface points (m) and their outward unit normals.
    """
    n = points.shape[1]
    i = np.arange(directions) + 0.5
    z = 1.0 - 2.0 * i / directions
    phi = np.pi * (1.0 + 5**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    pick = np.random.default_rng(seed).choice(n, size=min(n, directions), replace=False)
    u = np.concatenate([np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1), normals[:, pick].T])
    height = u @ points  # (directions, n)
    count = np.sum(height >= height.max(axis=1, keepdims=True) - BAND, axis=1)
    return int(min(n, max(MIN_BUDGET, np.ceil(1.25 * count.max()))))


class ActiveSet(eqx.Module):
    """K slots of a pair's points: their indices `index` (K,), whether each slot holds a point
    `valid` (K,), which points are kept `kept` (n,), and `overflow`: more points were live at the
    start than K."""

    index: Int[Array, " k"]
    valid: Bool[Array, " k"]
    kept: Bool[Array, " n"]
    overflow: Bool[Array, ""]


def threshold(support: Support) -> float:
    """The depth above which a point pushes: -1 for the smootherstep, 0 for the occupancy's clip."""
    return -1.0 if support.smooth else 0.0


def live(support: Support, s: Array) -> Array:
    """Whether each point exerts a force at depths s (n,) (or was at s0: the damper's lag)."""
    t = threshold(support)
    return (s > t) | (support.s0 > t)


def _cumsum(x: Array) -> Array:
    return jax.lax.associative_scan(jnp.add, x)  # O(n) work; XLA's CPU cumsum is a windowed reduction


def choose(support: Support, k: int) -> ActiveSet:
    """The K slots (module docstring): live points first, then those within `MARGIN`."""
    n = support.s0.shape[0]
    t = threshold(support)
    first = support.s0 > t
    if support.smooth:
        second = ~first & (support.s0 > t - MARGIN * support.gain)
    else:  # outside the partner's occupancy, but on its rising edge
        second = ~first & (support.gain > 0.0)
    rank = _cumsum(jnp.concatenate([first, second]).astype(jnp.int32)) - 1
    slot = jnp.where(first, rank[:n], jnp.where(second, rank[n:], k))
    index = jnp.zeros(k, jnp.int32).at[slot].set(jnp.arange(n, dtype=jnp.int32), mode="drop")
    count = rank[-1] + 1
    valid = jnp.arange(k, dtype=jnp.int32) < count
    kept = slot < k
    return ActiveSet(index, valid, kept, jnp.sum(first) > k)


def take(support: Support, patch: Patch, active: ActiveSet) -> tuple[Support, Patch]:
    """The support and patch restricted to the active slots (empty slots weigh nothing)."""

    n = support.s0.shape[0]

    def pick(x):  # a normal shared by all points, (3, 1), stays
        return x[..., active.index] if x.shape[-1] == n else x

    weight = jnp.where(active.valid, support.weight[active.index], 0.0)
    sup = Support(pick(support.at), pick(support.normal), weight, pick(support.s0), pick(support.gain), support.smooth)
    pt = Patch(pick(patch.r_a), pick(patch.r_b), pick(patch.u_b), patch.w_b, pick(patch.normal), weight, patch.joint)
    return sup, pt


def reach(patch: Patch) -> Float[Array, ""]:
    """The largest lever arm of a pair's points about either body's centre, m."""
    r = jnp.sum(patch.r_a * patch.r_a, axis=0)
    if patch.joint:
        r = jnp.maximum(r, jnp.sum(patch.r_b * patch.r_b, axis=0))
    return jnp.sqrt(jnp.max(r))


class Dropped(eqx.Module):
    """What the post-solve check needs of the dropped points: their largest depth and gain, and the
    pair's largest lever arm (for the bound), and the whole pair (for the exact check)."""

    s0: Float[Array, ""]
    gain: Float[Array, ""]
    reach: Float[Array, ""]


def dropped(support: Support, patch: Patch, active: ActiveSet) -> Dropped:
    out = ~active.kept
    s0 = jnp.max(jnp.where(out, support.s0, -jnp.inf))
    gain = jnp.max(jnp.where(out, support.gain, 0.0))
    return Dropped(s0, gain, reach(patch))


def bound_holds(support: Support, drop: Dropped, dV: Float[Array, " m"], h) -> Array:
    """Whether no dropped point can be live after a velocity change dV of the pair (6 or 12): each
    point's further approach is at most h (|dv| + |dw| r) per body."""
    speed = jnp.zeros((), dV.dtype)
    for b in range(dV.shape[0] // 6):
        v, w = dV[6 * b : 6 * b + 3], dV[6 * b + 3 : 6 * b + 6]
        speed = speed + jnp.sqrt(v @ v) + jnp.sqrt(w @ w) * drop.reach
    return drop.s0 + drop.gain * h * speed <= threshold(support)


def missed(support: Support, patch: Patch, active: ActiveSet, u_n0: Array, V: Float[Array, " m"], h) -> Array:
    """Whether a dropped point is live at the pair's velocities V (the exact check; `u_n0` (n,) the
    points' normal velocities at V~)."""
    u_n = normal_velocity(patch, V)[0]
    s = jnp.where(support.gain > 0.0, support.s0 - h * support.gain * (u_n - u_n0), support.s0)
    return jnp.any(live(support, s) & ~active.kept)
