"""The implicit step's contact problem and its solve (`dano.sim.implicit` builds it each step).

`ContactProblem` holds what the step has found before the solve: the unknowns' free motion V~ and
mass matrix, each pair's support and patch (all its points) and who its partner is. The functions
below are the objective of the module docstring of `dano.sim.implicit` over it, group by group, and
its solve (`solved`): over each pair's active set (`dano.contact.active`), checked exactly against
the points it dropped, or over all points once one of them turns out live.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano._mjx import mjx
from dano.contact import ContactParams, active
from dano.contact.friction import Patch, patch_terms
from dano.contact.pairs import Frame
from dano.contact.pairs import reaction as reaction_of
from dano.contact.support import Support, normal_terms, normal_velocity, overlap
from dano.math import normalize
from dano.sim.groups import each
from dano.sim.newton import minimize_convex, newton, run_if, solve_implicit
from dano.sim.step import Partner, scatter
from dano.sim.world import Params, World

PASSES = 3
"""Solves per step: the first without friction, each next one with friction at the normal forces
the previous one delivered (so that they include the support's answer to friction's own torque)."""


class _Sets(eqx.Module):
    """Per group (`ContactProblem.groups`), its pairs' supports and patches, the damper's lagged
    overlaps and the normal velocities at V~, stacked: all the points, or their active sets."""

    supports: tuple
    patches: tuple
    psi0: tuple
    u_n0: tuple


def friction_normal(N: Float[Array, " k"]) -> Float[Array, " k"]:
    """The points' normal forces that friction scales with: the positive parts of N (k,), scaled
    to add up to the pair's total. A point's spring and damper may pull (N < 0) while the pair
    pushes; clipping alone then counts more support than the pair gives (in the first version of
    this step, 10x for a box placed 0.5 mm into the floor, which lost a third of its 1 m/s in one
    step). So the positive parts give where the support is, the total how much; a pair whose net
    normal force pulls has no friction.
    """
    positive = jnp.maximum(N, 0.0)
    total, raw = jnp.maximum(jnp.sum(N), 0.0), jnp.sum(positive)
    return positive * (total / jnp.where(raw > 0, raw, 1.0))


def _centroid(patch: Patch, psi: Array) -> Patch:
    """The paper's centroid mode for friction: one point at chi carrying the whole pair."""
    total = jnp.sum(psi)
    mean = lambda x: (x @ psi / jnp.where(total > 0, total, 1.0))[:, None]  # noqa: E731
    normal = patch.normal if patch.normal.shape[1] == 1 else normalize(mean(patch.normal)[:, 0])[:, None]
    return Patch(mean(patch.r_a), mean(patch.r_b), mean(patch.u_b), patch.w_b, normal, total[None], patch.joint)


class ContactProblem(NamedTuple):
    """One step's contact problem, as the solve sees it (built by `dano.sim.implicit.implicit_step`).

    The pairs come in groups (`dano.sim.groups.pair_groups`): pairs whose DANOs have points of one
    size and budget and whose partners are primitives of one kind and size (a robot's finger boxes;
    its meshes of as many planes; the floor under two bunnies), all moving at known velocities or
    all solved for, are stacked leaf-wise along a leading axis and computed as one (`each`), so
    the step's program holds one copy of the contact per group, not per pair; a pair with a DANO
    partner is a group of its own. Each pair keeps its own velocity vector (`slots`).

    Attributes:
        world, params, h: the scene, its parameters and the step.
        n: DANOs; their 6 velocities come first in V, then each free or actuated primitive's.
        pair_list: the pairs (`dano.sim.world.pairs`) and `mates` their partners.
        groups: the pairs (indices into `pair_list`) of each group.
        other: per pair, where its partner sits in V (a DANO or a free primitive), or -1 (it moves
            at a known velocity).
        contact: per group, its pairs' `ContactParams` stacked.
        supports, patches: per group, its pairs' points at the pose the free motion reaches, stacked.
        V_free: V~ (6 n_all,); M its mass matrix; `locked` the velocities held at 0.
        frames: the unknowns' frames at the step's start; `masses` their masses.
        prim_body: the MuJoCo bodies of the free primitives in V.
        kin: the robot links' motion (`link_motion`), or None.
        xfrc: zeros shaped like `mjx.Data.xfrc_applied`.
    """

    world: World
    params: Params
    h: float
    n: int
    pair_list: tuple[tuple[int, str, int], ...]
    mates: tuple[Partner, ...]
    groups: tuple[tuple[int, ...], ...]
    other: list[int]
    contact: list[ContactParams]
    supports: list[Support]
    patches: list[Patch]
    V_free: Array
    M: Array
    locked: np.ndarray
    frames: list[Frame]
    masses: list
    prim_body: list
    kin: mjx.Data | None
    xfrc: Array

    @property
    def centroid(self) -> bool:  # friction and damper at chi (the spring per point)
        return self.world.force_mode == "centroid"


def slots(c: ContactProblem, g: int) -> np.ndarray:
    """Where each pair of group g has its velocity vector (V_a, or (V_a, V_b) with a partner in V)
    in V: (k, m) indices."""

    def row(j):
        i, o = c.pair_list[j][0], c.other[j]
        return list(range(6 * i, 6 * i + 6)) + (list(range(6 * o, 6 * o + 6)) if o >= 0 else [])

    return np.asarray([row(j) for j in c.groups[g]])


def pair_velocity(c: ContactProblem, g: int, V: Array) -> Array:
    """Each pair's velocity vector in group g at V, (k, m)."""
    return V[jnp.asarray(slots(c, g))]


def scatter_pair(c: ContactProblem, g: int, grad: Array, H: Array) -> tuple[Array, Array]:
    """A group's gradients (k, m) and Hessians (k, m, m), one per pair, added into the (6N,) and
    (6N, 6N) of all unknowns; summed first where the pairs share their unknowns (one DANO's)."""
    idx = slots(c, g)
    size = c.V_free.shape[0]
    if np.all(idx == idx[0]):
        grad, H, idx = jnp.sum(grad, axis=0, keepdims=True), jnp.sum(H, axis=0, keepdims=True), idx[:1]
    at = jnp.asarray(idx)
    return jnp.zeros(size).at[at].add(grad), jnp.zeros((size, size)).at[at[:, :, None], at[:, None, :]].add(H)


def point_sets(c: ContactProblem, sups, pts) -> _Sets:
    def u_n0(g, pt):
        return each(lambda q, v: normal_velocity(q, v)[0], pt, pair_velocity(c, g, c.V_free))

    # The damper's overlaps, lagged: at the pose the free motion reaches.
    psi0 = tuple(each(lambda s: overlap(s, s.s0), sup) for sup in sups)
    return _Sets(tuple(sups), tuple(pts), psi0, tuple(u_n0(g, pt) for g, pt in enumerate(pts)))


def with_friction(c: ContactProblem, sets: _Sets, V: Array, on: Array) -> list[Patch]:
    """Each group's friction patches at the normal forces delivered at the velocities V, times `on`
    (0: no friction, 1)."""

    def group(g):
        def one(p, sup, pt, psi0, u_n0, Vg):
            _, _, _, s, u_n = normal_terms(p, sup, pt, psi0, u_n0, c.h, Vg, c.centroid)
            N = on * friction_normal(p.impact_spring * overlap(sup, s) - p.impact_damper * psi0 * u_n)
            fr = Patch(pt.r_a, pt.r_b, pt.u_b, pt.w_b, pt.normal, N, pt.joint)
            return _centroid(fr, N) if c.centroid else fr

        Vg = pair_velocity(c, g, V)
        return each(one, c.contact[g], sets.supports[g], sets.patches[g], sets.psi0[g], sets.u_n0[g], Vg)

    return [group(g) for g in range(len(c.groups))]


def _member_terms(c: ContactProblem, sets: _Sets, g: int, friction: list[Patch], V: Array):
    """Each pair of group g: its U + h R + h D (D with the friction patches) at V, with its gradient
    and Hessian w.r.t. its velocity vector (stacked: (k,), (k, m), (k, m, m))."""

    def one(p, sup, pt, psi0, u_n0, fr, Vg):
        value, grad, H, _, _ = normal_terms(p, sup, pt, psi0, u_n0, c.h, Vg, c.centroid)
        fv, fg, fH = patch_terms(p, fr, Vg)
        return value + c.h * fv, grad + c.h * fg, H + c.h * fH

    args = (c.contact[g], sets.supports[g], sets.patches[g], sets.psi0[g], sets.u_n0[g], friction[g])
    return each(one, *args, pair_velocity(c, g, V))


def objective(c: ContactProblem, sets: _Sets, friction: list[Patch]):
    """V -> (value, gradient, Hessian) of the step's objective over `sets`, friction fixed."""

    def f(V):
        e = V - c.V_free
        value, grad, H = 0.5 * e @ c.M @ e, c.M @ e, c.M
        for g in range(len(c.groups)):
            vg, gg, Hg = _member_terms(c, sets, g, friction, V)
            gg, Hg = scatter_pair(c, g, gg, Hg)
            value, grad, H = value + jnp.sum(vg), grad + gg, H + Hg
        if c.locked.any():  # held velocities: no gradient, a unit Hessian (Newton leaves them at 0)
            grad = jnp.where(c.locked, 0.0, grad)
            H = jnp.where(c.locked[:, None] | c.locked[None, :], jnp.eye(c.V_free.shape[0]), H)
        return value, grad, H

    return f


class _Active(NamedTuple):
    """The groups' active sets (None where a group is solved over all its points), the points they
    dropped, the sets over the active points, and whether a set overflowed at the start."""

    actives: list
    drops: list
    sparse: _Sets
    started_over: Array


def active_sets(c: ContactProblem) -> _Active:
    """The active set of each pair (`dano.contact.active`), where its budget is below its points."""

    def budget(g):
        i, mate = c.pair_list[c.groups[g][0]][0], c.mates[c.groups[g][0]]
        return c.world.danos[i].budget + (c.world.danos[mate.dano].budget if mate.dano >= 0 else 0)

    actives = []
    for g, sup in enumerate(c.supports):
        k = budget(g)
        actives.append(each(lambda s, k=k: active.choose(s, k), sup) if 0 < k < sup.s0.shape[-1] else None)
    triples = list(zip(c.supports, c.patches, actives, strict=True))
    taken = [each(active.take, sup, pt, a) if a is not None else (sup, pt) for sup, pt, a in triples]
    sparse = point_sets(c, [t[0] for t in taken], [t[1] for t in taken])
    drops = [each(active.dropped, sup, pt, a) if a is not None else None for sup, pt, a in triples]
    started_over = jnp.any(jnp.asarray([jnp.any(a.overflow) for a in actives if a is not None] or [False]))
    return _Active(actives, drops, sparse, started_over)


def missed(c: ContactProblem, sets: _Active, u_n0: tuple, V: Array) -> Array:
    """Whether a point that the active sets dropped is live at V (`dano.contact.active`); `u_n0`
    every point's normal velocity at V~."""
    out = sets.started_over
    for g, (a, drop) in enumerate(zip(sets.actives, sets.drops, strict=True)):
        if a is None or drop is None:  # both or neither
            continue
        Vg = pair_velocity(c, g, V)
        dV = Vg - pair_velocity(c, g, c.V_free)

        def exact(g=g, a=a, Vg=Vg):
            def one(sup, pt, act, u, v):
                return active.missed(sup, pt, act, u, v, c.h)

            return jnp.any(each(one, c.supports[g], c.patches[g], a, u_n0[g], Vg))

        # the exact check under a once-or-never loop: in a batch, only when some element needs it
        safe = jnp.all(each(lambda s, d, v: active.bound_holds(s, d, v, c.h), c.supports[g], drop, dV))
        out = out | run_if(~safe, lambda _, exact=exact: exact(), jnp.zeros((), bool))
    return out


class Solution(NamedTuple):
    """A step's solve: V', whether a dropped point turned out live (the step went dense), the
    velocities the last pass's friction was taken at, and the active sets' points (None where every
    group was solved over all its points)."""

    V_next: Array
    over: Array
    V_before: Array
    sparse: _Sets | None


def solved(c: ContactProblem) -> tuple[Array, Array, Array]:
    """The pairs' contact solved (`solve`): V', whether the step went dense, and the reactions
    (`xfrc_applied`)."""
    s = solve(c)
    return s.V_next, s.over, reactions(c, s)


def solve(c: ContactProblem) -> Solution:
    """The pairs' contact solved: over each pair's active set, checked, or over all points; the
    passes are one traced pass run `PASSES` times (they differ only in their data)."""
    sets = active_sets(c)
    sparse_step = any(a is not None for a in sets.actives)
    # Every point's normal velocity at V~, for the exact check (once per step, not per pass).
    u_n0 = point_sets(c, c.supports, c.patches).u_n0
    tol = 1e-20 * sum(c.masses)
    # The first friction solve starts from the velocities the step starts with, not from the
    # frictionless answer: a body that friction holds is near them, while without friction it
    # may slip and turn (a resting box: 1.5 mm/s at its face, far out on the Coulomb law's flat
    # part, where Newton needs ~20 damped steps to come back instead of ~4).
    V_now = jnp.concatenate([jnp.concatenate([f.v, f.w]) for f in c.frames])

    def full():  # all the points' sets, formed only where they are used (inside the branches)
        return point_sets(c, c.supports, c.patches)

    def one_pass(carry, k):
        """Solve k: friction at the normal forces of solve k - 1 (none in the first, `PASSES`), over
        the active sets, or over all points once a dropped point turns out live (`missed`)."""
        V_before, over = carry
        x0 = jnp.where(k == 1, V_now, V_before)
        on = (k > 0).astype(V_before.dtype)
        if not sparse_step:
            every = full()
            return (
                minimize_convex(objective(c, every, with_friction(c, every, V_before, on)), x0, tol),
                over,
            ), V_before
        small = objective(c, sets.sparse, with_friction(c, sets.sparse, V_before, on))

        def dense():
            every = full()
            return objective(c, every, with_friction(c, every, V_before, on))

        def forward(x):
            """Over the active sets, then over all points once a dropped point turns out live (once
            over, the rest of the step is dense: its friction needs all the points)."""
            trial = newton(small, x, tol)
            now_over = over | missed(c, sets, u_n0, trial)
            return run_if(now_over, lambda x: newton(dense(), x, tol), trial), now_over

        def solved_over(V, now_over):  # the objective that was minimised
            return jax.lax.cond(now_over, lambda V: dense()(V), small, V)

        return solve_implicit(forward, solved_over, x0), V_before

    (V_next, over), befores = jax.lax.scan(one_pass, (c.V_free, jnp.zeros((), bool)), jnp.arange(PASSES))
    return Solution(V_next, over, befores[-1], sets.sparse if sparse_step else None)


def group_wrench(c: ContactProblem, s: Solution, g: int, point: bool = False) -> tuple[Array, Array | None]:
    """Each pair's wrench of group g on its DANO at the solution ((k, 6): force, torque about the
    DANO's centre of mass; world; -dT/dV_a / h) over the points the last pass was solved over (the
    active sets, or all points where there are none or they overflowed), and with `point` where its
    normal force acts ((k, 3): the centroid of its points' positive normal forces, world; the DANO's
    centre without any)."""
    last_on = jnp.asarray(float(PASSES > 1), c.V_free.dtype)
    centres = jnp.stack([c.frames[c.pair_list[j][0]].x for j in c.groups[g]])
    Vg = pair_velocity(c, g, s.V_next)

    def of(sets):
        grads = _member_terms(c, sets, g, with_friction(c, sets, s.V_before, last_on), s.V_next)[1]
        if not point:
            return -grads[:, :6] / c.h, None

        def at(p, sup, pt, psi0, u_n0, Vg, centre):
            _, _, _, depth, u_n = normal_terms(p, sup, pt, psi0, u_n0, c.h, Vg, c.centroid)
            N = jnp.maximum(p.impact_spring * overlap(sup, depth) - p.impact_damper * psi0 * u_n, 0.0)
            total = jnp.sum(N)
            return jnp.where(total > 0, sup.at @ N / jnp.where(total > 0, total, 1.0), centre)

        points = each(at, c.contact[g], sets.supports[g], sets.patches[g], sets.psi0[g], sets.u_n0[g], Vg, centres)
        return -grads[:, :6] / c.h, points

    def every():
        return of(point_sets(c, c.supports, c.patches))

    sparse = s.sparse
    return every() if sparse is None else jax.lax.cond(s.over, every, lambda: of(sparse))


def reactions(c: ContactProblem, s: Solution) -> Array:
    """The pairs' reactions on MuJoCo bodies, as `xfrc_applied` (`group_wrench`)."""
    xfrc = c.xfrc
    for k, body in enumerate(c.prim_body):  # a free primitive: the wrench that takes it to V'
        e = slice(6 * (c.n + k), 6 * (c.n + k) + 6)
        xfrc = scatter(xfrc, body, c.M[e, e] @ (s.V_next[e] - c.V_free[e]) / c.h)
    for g, group in enumerate(c.groups):
        if c.other[group[0]] >= 0 or all(c.mates[j].body < 0 for j in group):
            continue
        w = group_wrench(c, s, g)[0]
        for member, j in enumerate(group):
            (i, kind, _), mate = c.pair_list[j], c.mates[j]
            if mate.body < 0:
                continue
            if kind == "link":
                assert c.kin is not None  # `link_motion` ran: the world has links
                centre = c.kin.xipos[mate.body]
            else:
                centre = mate.frame.x
            xfrc = scatter(xfrc, mate.body, reaction_of(w[member], c.frames[i].x, centre))
    return xfrc


def untouched(c: ContactProblem) -> tuple[Array, Array, Array]:
    """No point of any pair is live where the free motion goes: V~ is the minimiser (every contact
    term is flat there), no check and no reaction."""
    return c.V_free, jnp.zeros((), bool), c.xfrc
