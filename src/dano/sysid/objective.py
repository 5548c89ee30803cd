"""Problem (17)'s objective as the solver sees it: ½Σρ(r)² over every window, its gradient and
Gauss-Newton Hessian assembled from per-window blocks (each window differentiated in θ and its own
initial state only), and the robust losses for data with outliers."""

import enum
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano import lanes
from dano.sim.run import jitted
from dano.sysid.configs import Loss, SysidError
from dano.sysid.problem import Problem, over_windows, residuals, traced, window_residuals


class Jacobian(enum.StrEnum):
    """How a window's residuals are differentiated: `fwd` forward mode (one tangent per unknown),
    `rev` reverse mode (one cotangent per residual), `auto` reverse where a window has more unknowns
    than residuals."""

    auto = "auto"
    fwd = "fwd"
    rev = "rev"


ROBUST_SCALE = 2.795
"""σ: where the robust losses start to discount a frame's position (or rotation) error, the 95 %
quantile of the norm of a 3-vector of unit Gaussian noise (√χ²₃(0.95)): inliers keep their weight."""


def robust(r: Float[Array, "... 6"], loss: Loss | str, c: float = ROBUST_SCALE) -> Float[Array, "... 6"]:
    """Residuals whose squares sum to the robust loss: each frame's position and rotation error e
    (3-vectors, in σ) scaled by √(ρ(|e|²) / |e|²), so ½Σ|r|² = ½Σρ(|e|²) and Gauss-Newton on r is
    the "square-rooted" robust fit (Triggs et al., Bundle adjustment, §4.3).

    ρ: "l2" u; "huber" u up to c², then 2c√u − c² (linear growth: an outlier pulls with constant
    force); "cauchy" c² log(1 + u/c²) (an outlier's pull fades). Smooth, with the gradient of the
    identity at 0.
    """
    if loss not in tuple(Loss):
        *first, last = (repr(v.value) for v in Loss)
        raise SysidError(f"the loss must be {', '.join(first)} or {last}, got {loss!r}")
    if loss == Loss.l2:
        return r
    e = r.reshape(*r.shape[:-1], 2, 3)
    u = jnp.sum(e * e, axis=-1, keepdims=True)
    small = u < 1e-12 * c * c
    safe = jnp.where(small, c * c, u)  # the double `where`: no NaN gradient at e = 0
    if loss == "huber":
        ratio = jnp.where(u <= c * c, 1.0, (2.0 * c * jnp.sqrt(safe) - c * c) / safe)
    else:
        ratio = jnp.where(small, 1.0, c * c * jnp.log1p(safe / (c * c)) / safe)
    return (e * jnp.sqrt(ratio)).reshape(r.shape)


def compiled(problem: Problem, jac: Jacobian, loss_name: Loss = Loss.l2):
    """(loss, residuals and normal equations) functions of (θ, δ, windows), compiled once per problem
    structure (`dano.sim.run.jitted` of the pure functions below, with the problem as an argument:
    `dano.sysid.problem.traced`). The residuals returned are the plain ones (for the RMS errors);
    the loss and the normal equations are those of `robust(r, loss_name)`."""
    key = traced(problem)
    return (
        _in_lanes(functools.partial(jitted(_loss), key, Loss(loss_name)), _add),
        _in_lanes(functools.partial(jitted(_normal_equations), key, Jacobian(jac), Loss(loss_name)), _join),
    )


def _in_lanes(fn, join):
    """fn(θ, δ, windows) with the windows split into equal shares, one per lane (`dano.lanes`: on
    the CPU backend one per core, each from a thread of its own), the shares' results joined by
    `join`: as many lanes as divide the windows evenly (one program for every share). The 4-window
    push fit of `tests/test_sysid.py` on two lanes: 24.7 -> 17.9 s cold, 12.3 -> 6.7 s warm (a
    script, alone, the windows one after another in both)."""

    def call(theta, delta, windows):
        n = delta.shape[0]
        k = max(d for d in range(1, min(lanes.count(), n) + 1) if n % d == 0)
        if k == 1:
            return fn(theta, delta, windows)
        c = n // k

        def share(i):
            part = lambda x: x[i * c : (i + 1) * c]  # noqa: E731
            return fn(theta, part(delta), jax.tree_util.tree_map(part, windows))

        return join(lanes.in_parallel([functools.partial(share, i) for i in range(k)]))

    return call


def _add(losses):
    return sum(losses[1:], losses[0])


def _join(parts):
    """The normal equations of all windows from those of shares of them: the per-window parts (the
    residuals, g_δ, H_θδ, H_δδ) in order, the shared ones (the loss, g_θ, H_θθ) summed."""
    plain = jnp.concatenate([p[0] for p in parts])
    loss, g_t, g_d, H_tt, H_td, H_dd = zip(*(p[1] for p in parts), strict=True)
    g_d, H_td, H_dd = (jnp.concatenate(x) for x in (g_d, H_td, H_dd))
    return plain, (_add(loss), _add(g_t), g_d, _add(H_tt), H_td, H_dd)


def _loss(problem: Problem, loss_name: Loss, theta, delta, windows):
    r = residuals(problem, theta, delta, windows)
    r = r if loss_name == "l2" else robust(r, loss_name)  # robust: pose residuals only
    return 0.5 * jnp.sum(r * r)


def _normal_equations(problem: Problem, jac: Jacobian, loss_name: Loss, theta, delta, windows):
    def one(dl, w):
        def f(th, d_):
            plain = window_residuals(problem, th, d_, w).reshape(-1)
            r = plain if loss_name == "l2" else robust(plain.reshape(-1, 6), loss_name).reshape(-1)
            return r, (plain, r)

        if jac == "fwd" and theta.shape[0] + dl.shape[0] == 1:  # one tangent: a jvp, nothing batched
            (r, (plain, _)), (dr, _) = jax.jvp(f, (theta, dl), (jnp.ones_like(theta), jnp.ones_like(dl)))
            column = dr[:, None]
            return plain, r, column[:, : theta.shape[0]], column[:, theta.shape[0] :]
        differentiate = jax.jacfwd if jac == "fwd" else jax.jacrev
        (Jt, Jd), (plain, r) = differentiate(f, argnums=(0, 1), has_aux=True)(theta, dl)
        return plain, r, Jt, Jd

    plain, r, Jt, Jd = over_windows(one, delta, windows)
    return plain, (
        0.5 * jnp.sum(r * r),
        jnp.einsum("nm,nmp->p", r, Jt),
        jnp.einsum("nm,nms->ns", r, Jd),
        jnp.einsum("nmp,nmq->pq", Jt, Jt),
        jnp.einsum("nmp,nms->nps", Jt, Jd),
        jnp.einsum("nms,nmt->nst", Jd, Jd),
    )


def assemble(p: int, n: int, s: int, parts) -> tuple[float, np.ndarray, np.ndarray]:
    """Dense loss, gradient (P,) and Hessian (P, P) over y = (θ, δ₁, …, δₙ) from the blocks."""
    loss, g_t, g_d, H_tt, H_td, H_dd = (np.asarray(x) for x in parts)
    P = p + n * s
    H = np.zeros((P, P))
    H[:p, :p] = H_tt
    for i in range(n):
        sl = slice(p + i * s, p + (i + 1) * s)
        H[:p, sl] = H_td[i]
        H[sl, :p] = H_td[i].T
        H[sl, sl] = H_dd[i]
    return float(loss), np.concatenate([g_t, g_d.reshape(-1)]), H
