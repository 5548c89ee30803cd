"""Convex minimisation under jit, vmap and grad: damped Newton with a line search (`newton`),
differentiated through the optimality condition instead of its iterations (`solve_implicit`,
`minimize_convex`), and a once-or-never loop that `vmap` keeps cheap (`run_if`). The implicit
contact step (`dano.sim.implicit`) solves each step with these."""

import functools

import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

NEWTON_ITERATIONS = 40
"""At most this many Newton steps per solve (it stops at convergence, see `minimize_convex`)."""

SEARCH_ITERATIONS = 12
"""At most this many trial points per line search (`minimize_convex`)."""

SEARCH_TOLERANCE = 0.1
"""The line search stops where |phi'(t)| is below this fraction of |phi'(0)|."""


def newton(objective, x0: Float[Array, " n"], tol: float | Float[Array, ""]) -> Float[Array, " n"]:
    """argmin of a smooth strongly convex function by Newton's method with a line search along
    each Newton direction (not differentiable: see `minimize_convex`).

    The line search finds where the directional derivative phi'(t) = grad f(x + t dx) . dx changes
    sign (bracketed regula falsi), not a sufficient decrease by halving: Coulomb friction at a
    stiction velocity of 1e-5 m/s is a near-kink, and a rolling body's contact point sits on it.
    Newton's quadratic model then overshoots the kink, and halving zigzags across it (measured on
    the reference bunny rolling at 1 m/s: 40 Newton steps and ~200 halvings per solve; with this
    search 4-8 steps). phi' is exact where values lose their digits, near the optimum.

    Each trial point is evaluated whole (value, gradient, Hessian), and the point the search
    accepts gives the next Newton direction: a Newton step that is taken whole costs one
    evaluation. The first iteration searches along dx = 0, which evaluates x0, so `objective` is
    traced once (the step's compile time grows with the copies of it).

    Args:
        objective: x -> (value, gradient, Hessian).
        x0: the start.
        tol: stop when the Newton decrement -grad . dx (units of the value) is below this.
    """

    def step(state):
        k, x, dx, slope, _ = state

        def searching(c):
            i, found = c[0], c[-1]
            return ~found & (i < SEARCH_ITERATIONS)

        def trial(c):
            """Evaluate at t, keep it as the bracket's low end if phi still falls there, then the
            next t by regula falsi (Illinois: an end kept twice in a row counts half)."""
            i, lo, d_lo, ev_lo, hi, d_hi, t, side, _, _, _ = c
            ev_t = objective(x + t * dx)
            d = ev_t[1] @ dx
            # phi is convex: d <= 0 at t = 1 means it falls all the way (the full Newton step).
            found = (d <= 0.0) & (t >= 1.0) | (jnp.abs(d) <= SEARCH_TOLERANCE * -slope)
            below = d < 0.0
            lo, d_lo = jnp.where(below, t, lo), jnp.where(below, d, d_lo)
            ev_lo = jax.tree_util.tree_map(lambda a, b: jnp.where(below, a, b), ev_t, ev_lo)
            hi, d_hi = jnp.where(below, hi, t), jnp.where(below, d_hi, d)
            d_lo = jnp.where(below & (side == 1), d_lo, jnp.where(~below & (side == -1), 0.5 * d_lo, d_lo))
            d_hi = jnp.where(~below & (side == -1), d_hi, jnp.where(below & (side == 1), 0.5 * d_hi, d_hi))
            t_next = lo - d_lo * (hi - lo) / (d_hi - d_lo)
            t_next = jnp.clip(t_next, lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo))
            return i + 1, lo, d_lo, ev_lo, hi, d_hi, t_next, jnp.where(below, 1, -1), t, ev_t, found

        one, zero = jnp.ones((), x.dtype), jnp.zeros((), x.dtype)
        n = x.shape[0]
        blank = (zero, jnp.zeros(n, x.dtype), jnp.zeros((n, n), x.dtype))  # the low end's, until one is found
        c = (0, zero, slope, blank, one, zero, one, 0, zero, blank, False)
        _, lo, _, ev_lo, _, _, _, _, t, ev_t, found = jax.lax.while_loop(searching, trial, c)
        # Not found within the budget: the bracket's low end, where phi still falls, is a
        # guaranteed decrease (none at all if that end is still 0: stuck).
        t = jnp.where(found, t, lo)
        stuck = t <= 0.0
        f, g, H = jax.tree_util.tree_map(lambda a, b: jnp.where(found, a, b), ev_t, ev_lo)
        x = x + t * dx
        dx = -jnp.linalg.solve(jnp.where(stuck, jnp.eye(n, dtype=x.dtype), H), g)
        slope = g @ dx  # phi'(0) < 0 along the next direction
        # Converged: the decrement is below tol, or below what rounding lets the value resolve.
        small = -slope < tol + 64 * jnp.finfo(x.dtype).eps * jnp.abs(f)
        # converged: the last Newton step is taken whole (no evaluation: nothing follows it)
        return k + 1, jnp.where(small & ~stuck, x + dx, x), dx, slope, small | stuck

    def going(state):
        k, _, _, _, done = state
        return (k <= NEWTON_ITERATIONS) & ~done

    zero = jnp.zeros((), x0.dtype)
    return jax.lax.while_loop(going, step, (0, x0, jnp.zeros_like(x0), zero, False))[1]


def solve_implicit(forward, objective, x0: Float[Array, " n"]):
    """(x*, aux) = forward(x0), found without derivatives (any loops: `newton`, `run_if`), x* the
    minimiser of x -> objective(x, aux); returned with the derivatives of the exact minimiser (the
    implicit function theorem at grad f(x*) = 0): dx* = -H^-1 (d grad f), H the objective's own
    analytic Hessian at x* and d grad f the gradient's change with everything `objective` closes
    over. That is one forward pass of the gradient per tangent; `lax.custom_root` also linearised
    the gradient in x and transposed it to rebuild H (jacrev), which dominated the step's
    derivatives and their compile time. `aux` (booleans) has no derivative."""
    closed_f, consts_f = _hoisted(forward, x0)
    aux = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(forward, x0)[1])
    closed_o, consts_o = _hoisted(objective, x0, aux)
    return _solved(closed_f, closed_o, len(consts_f), x0, *consts_f, *consts_o)


def _hoisted(fun, *example):
    """fun as a function of its arguments followed by every traced value it closes over, and those
    values (`jax.closure_convert` hoists only the differentiable ones; a custom derivative rule
    must not close over any tracer, integer ones included)."""
    closed, shape = jax.make_jaxpr(fun, return_shape=True)(*example)
    out_tree = jax.tree_util.tree_structure(shape)
    traced = [isinstance(c, jax.core.Tracer) for c in closed.consts]
    hoisted = [c for c, t in zip(closed.consts, traced, strict=True) if t]
    fixed = [c for c, t in zip(closed.consts, traced, strict=True) if not t]

    def converted(*args):
        given, extra = args[: len(example)], iter(args[len(example) :])
        plain = iter(fixed)
        consts = [next(extra) if t else next(plain) for t in traced]
        out = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree_util.tree_leaves(given))
        return jax.tree_util.tree_unflatten(out_tree, out)

    return converted, hoisted


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _solved(forward, objective, n_forward: int, x0, *consts):
    del objective
    return forward(x0, *consts[:n_forward])


@_solved.defjvp
def _solved_jvp(forward, objective, n_forward: int, primals, tangents):
    x0, *consts = primals
    x, aux = forward(x0, *consts[:n_forward])
    mine = tuple(consts[n_forward:])
    (_, _, H), (_, dg, _) = jax.jvp(lambda *c: objective(x, aux, *c), mine, tuple(tangents[1 + n_forward :]))
    no_tangent = jax.tree_util.tree_map(lambda a: np.zeros(np.shape(a), jax.dtypes.float0), aux)
    return (x, aux), (-jnp.linalg.solve(H, dg), no_tangent)


def minimize_convex(objective, x0: Float[Array, " n"], tol: float | Float[Array, ""]) -> Float[Array, " n"]:
    """`newton`, differentiable through the optimality condition grad f(x*) = 0 (`solve_implicit`),
    not through the iterations."""
    return solve_implicit(lambda x: (newton(objective, x, tol), None), lambda x, _: objective(x), x0)[0]


def run_if(pred: Bool[Array, ""], fn, x):
    """fn(x) where pred, else x: a loop that runs once or not at all, so under `vmap` fn runs only
    when some element needs it (a `lax.cond` there would run it always). Not reverse-differentiable;
    use it in a `solve_implicit` forward solve, or for a decision that is not differentiated."""
    return jax.lax.while_loop(lambda c: c[0], lambda c: (jnp.zeros_like(c[0]), fn(c[1])), (pred, x))[1]
