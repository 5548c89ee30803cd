"""The optimal control problem (`OptimalControlProblem`) and the pure functions iLQR is made of:
the objective, the constraint violation, the augmented Lagrangian, its expansion along a
trajectory, the Riccati backward pass and the closed-loop forward pass (`Pieces.call` compiles
each once per problem; `dano.trajopt.ilqr` runs the loops)."""

import atexit
import dataclasses
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dano.errors import DanoError
from dano.lanes import count as lane_count
from dano.lanes import in_parallel, shares
from dano.sim.run import jitted


class TrajoptError(DanoError):
    """A trajectory optimisation problem that cannot be set up as asked."""


@dataclasses.dataclass(frozen=True, eq=False)
class OptimalControlProblem:
    """x' = f(x, u, t) with costs and constraints (see the module docstring); all pure JAX functions.
    Hashed by identity: its pieces are compiled once per problem (`Pieces.call`).

    Attributes:
        dynamics: f(x (n,), u (m,), t) -> (n,).
        cost: ℓ(x, u, t) -> scalar, t = 0 … T-1.
        terminal_cost: ℓ_T(x) -> scalar.
        horizon: T.
        constraints: c(x, u, t) -> (p,), feasible where ≤ 0; or None.
        terminal_constraints: h(x) -> (q,), feasible where = 0; or None.
        compiler_options: XLA options for jitting the solver's pieces, e.g.
            `dano.sim.run.compiler_options(world)`: the same as the forward simulator's, so that an
            open-loop replay there repeats the optimiser's arithmetic.
    """

    dynamics: Callable
    cost: Callable
    terminal_cost: Callable
    horizon: int
    constraints: Callable | None = None
    terminal_constraints: Callable | None = None
    compiler_options: dict | None = None

    @property
    def flow(self) -> "Flow":
        """What the forward pass needs: the dynamics over the horizon (`Flow`)."""
        return Flow.of(self.dynamics, self.horizon, self.compiler_options)


def rollout(problem: OptimalControlProblem, x0: Float[Array, " n"], controls: Float[Array, "T m"]) -> Array:
    """States (T+1, n) of the open-loop controls from x0."""

    def step(x, ut):
        u, t = ut
        x_next = problem.dynamics(x, u, t)
        return x_next, x_next

    _, xs = jax.lax.scan(step, x0, (controls, jnp.arange(problem.horizon)))
    return jnp.concatenate([x0[None], xs], axis=0)


def width(fn, *args) -> int:
    """Length of the vector `fn(*args)` returns (0 for no function), without evaluating it."""
    return 0 if fn is None else int(jax.eval_shape(fn, *args).shape[0])


@dataclasses.dataclass(frozen=True)
class Pieces:
    """A problem's functions as the solver's pieces use them: constraints that are empty vectors
    where the problem has none (p, q: their lengths), the state and control sizes. Hashable, and
    equal for the same problem (by identity) and sizes: it is the static argument under which
    `call` compiles each piece once (JAX's own cache, shared by every solve of the problem)."""

    problem: OptimalControlProblem
    c: Callable  # c(x, u, t) -> (p,)
    h: Callable  # h(x) -> (q,)
    n: int
    m: int
    p: int
    q: int

    @property
    def ts(self) -> Array:
        """The time indices (T,)."""
        return jnp.arange(self.problem.horizon)

    def running(self, x, u, t, lam, rho, active):
        c = self.c(x, u, t)
        return self.problem.cost(x, u, t) + lam @ c + 0.5 * rho * jnp.sum(active * c**2)

    def terminal(self, x, nu, rho):
        h = self.h(x)
        return self.problem.terminal_cost(x) + nu @ h + 0.5 * rho * h @ h

    def constraints(self, xs, us):
        return jax.vmap(self.c)(xs[:-1], us, self.ts)

    @property
    def flow(self) -> "Flow":
        """What the forward pass needs of the problem: its dynamics over its horizon."""
        return self.problem.flow

    def call(self, fn: Callable, *args):
        """fn(self, *args), compiled once per piece and problem (`dano.sim.run.jitted`, with the
        problem's `compiler_options`). Python numbers (a step length, a penalty) are passed as
        arrays, not compiled in; ints (a batch size) stay static."""
        return _call(fn, self, _options(self.problem.compiler_options), *args)


@dataclasses.dataclass(frozen=True)
class Flow:
    """The dynamics over a horizon, as the forward pass (`forward`) uses them: hashed by the
    dynamics function's identity, so that problems which share their dynamics (a settling rollout
    and the push set up after it from where it came to rest) share the compiled forward pass."""

    dynamics: Callable
    horizon: int
    options: tuple

    @classmethod
    def of(cls, dynamics: Callable, horizon: int, compiler_options: dict | None = None) -> "Flow":
        """`dynamics` over `horizon` steps, compiled with XLA's `compiler_options`."""
        return cls(dynamics, horizon, _options(compiler_options))

    @property
    def ts(self) -> Array:
        return jnp.arange(self.horizon)

    def call(self, fn: Callable, *args):
        """fn(self, *args), compiled once per piece and dynamics (as `Pieces.call`)."""
        return _call(fn, self, self.options, *args)


def _options(compiler_options: dict | None) -> tuple:
    """XLA's options as sorted (name, value) pairs: hashable, the form `jitted` takes."""
    return tuple(sorted((compiler_options or {}).items()))


def _call(fn: Callable, static, options: tuple, *args):
    args = tuple(jnp.asarray(a) if isinstance(a, float) else a for a in args)
    return jitted(fn, options)(static, *args)


def _no_constraints(x, u, t):
    return jnp.zeros(0)


def _no_terminal_constraints(x):
    return jnp.zeros(0)


def pieces(problem: OptimalControlProblem, n: int, m: int) -> Pieces:
    """`problem`'s pieces for states of size n and controls of size m."""
    p = width(problem.constraints, jnp.zeros(n), jnp.zeros(m), 0)
    q = width(problem.terminal_constraints, jnp.zeros(n))
    c = problem.constraints if p and problem.constraints is not None else _no_constraints
    h = problem.terminal_constraints if q and problem.terminal_constraints is not None else _no_terminal_constraints
    return Pieces(problem, c, h, n, m, p, q)


def active_set(c, lam):
    return ((c > 0) | (lam > 0)).astype(c.dtype)


def objective(f: Pieces, xs, us):
    """∑ℓ + ℓ_T, without the Lagrangian terms."""
    return jnp.sum(jax.vmap(f.problem.cost)(xs[:-1], us, f.ts)) + f.problem.terminal_cost(xs[-1])


def violation(f: Pieces, xs, us):
    """The largest violation (inequality excess or |h|), and c (T, p), h (q,)."""
    c = f.constraints(xs, us)
    h = f.h(xs[-1])
    worst_c = jnp.max(jnp.maximum(c, 0.0), initial=0.0)
    worst_h = jnp.max(jnp.abs(h), initial=0.0)
    return jnp.maximum(worst_c, worst_h), c, h


def augmented(f: Pieces, xs, us, lam, nu, rho):
    """The augmented-Lagrangian cost."""
    active = active_set(f.constraints(xs, us), lam)
    run = jax.vmap(f.running, in_axes=(0, 0, 0, 0, None, 0))(xs[:-1], us, f.ts, lam, rho, active)
    return jnp.sum(run) + f.terminal(xs[-1], nu, rho)


def jacobians(f: Flow, xs, us, ts, jacobian_batch):
    """The dynamics Jacobians A (k, n, n) and B (k, n, m) of the frames ts (k,) from the states xs
    (k, n) under the controls us (k, m): a piece of the dynamics alone (`Flow.call`), so
    `compile_ahead` can compile it before the problem's costs exist; `jacobians_along` takes the
    horizon's frames in chunks of k."""
    jac = jax.jacfwd(f.dynamics, argnums=(0, 1))
    if jacobian_batch is None:
        return jax.vmap(jac)(xs, us, ts)
    batch = None if jacobian_batch == 1 else jacobian_batch  # 1: a plain scan, branches kept
    return jax.lax.map(lambda a: jac(*a), (xs, us, ts), batch_size=batch)


def forward_trials(
    f: Flow, xs, us, k, K, alphas: Sequence[float], lanes: int | None = None
) -> Iterator[tuple[float, tuple]]:
    """(α, `forward` rollout at α) for each step size in order, `dano.lanes.count(lanes)` rollouts
    at a time: a line search that stops at the first it accepts wastes at most that many less one
    rollouts, each on a core that would have waited."""
    step = lane_count(lanes)
    for i in range(0, len(alphas), step):
        group = alphas[i : i + step]
        yield from zip(group, in_parallel([lambda a=a: f.call(forward, xs, us, k, K, a) for a in group]), strict=True)


_AHEAD: "weakref.WeakKeyDictionary[Callable, dict[tuple, threading.Event]]" = weakref.WeakKeyDictionary()
_AHEAD_LOCK = threading.Lock()


def _ahead_key(f: Flow, n: int, m: int, jacobian_batch: int | None, lanes: int) -> tuple:
    return shares(f.horizon, lanes).shape[1], f.options, n, m, jacobian_batch


def compile_ahead(f: Flow, n: int, m: int, jacobian_batch: int | None, lanes: int | None = None) -> None:
    """Starts compiling `jacobians` for states of size n and controls of size m, over the chunks of
    frames `jacobians_along` takes on `lanes` lanes (`dano.lanes.count`: None, one per core), in a
    thread of its own, so the largest program a solve needs compiles while the caller goes on (XLA
    lets go of the GIL while it compiles): a push compiles it during its settling and warm start,
    which compile and run the forward pass.
    Once per dynamics and shapes; `jacobians_along` waits for it. An error there is left for the
    call that needs the program, which compiles it again and raises.
    """
    key = _ahead_key(f, n, m, jacobian_batch, lane_count(lanes))
    with _AHEAD_LOCK:
        table = _AHEAD.setdefault(f.dynamics, {})
        if key in table:
            return
        done = table[key] = threading.Event()
    size = key[0]
    xs, us, ts = jnp.zeros((size, n)), jnp.zeros((size, m)), jnp.zeros(size, int)

    def work():
        try:
            jitted(jacobians, f.options).lower(f, xs, us, ts, jacobian_batch).compile()  # pyright: ignore[reportFunctionMemberAccess]
        except Exception:  # noqa: BLE001, S110 (the call that needs it raises it)
            pass
        finally:
            done.set()

    with _AHEAD_LOCK:
        if not _REGISTERED:  # on first use, not at import
            atexit.register(_finish_compiling)
            _REGISTERED.append(True)
        _PENDING[:] = [e for e in _PENDING if not e.is_set()] + [done]
    threading.Thread(target=work, name="dano-compile-ahead", daemon=True).start()


_PENDING: list[threading.Event] = []  # the compilations `compile_ahead` started that may still run
_REGISTERED: list[bool] = []


def _finish_compiling() -> None:
    """At exit, the compilations `compile_ahead` started are let finish: a thread stopped inside
    XLA while Python shuts down would abort the process."""
    for done in _PENDING:
        done.wait()


def jacobians_along(f: Flow, xs, us, jacobian_batch, lanes: int | None = None):
    """A (T, n, n) and B (T, n, m) along the states xs (T+1, n) and controls us (T, m): `jacobians`
    over the horizon in chunks of equal length, one per lane (`dano.lanes.count(lanes)`, run by
    `in_parallel`; the last chunk padded with its last frame), once compiled (`compile_ahead`,
    started here if not before)."""
    T, n, m, lanes = f.horizon, xs.shape[1], us.shape[1], lane_count(lanes)
    compile_ahead(f, n, m, jacobian_batch, lanes)
    _AHEAD[f.dynamics][_ahead_key(f, n, m, jacobian_batch, lanes)].wait()
    frames = shares(T, lanes)
    ts = jnp.arange(T)
    parts = in_parallel([lambda i=i: f.call(jacobians, xs[i], us[i], ts[i], jacobian_batch) for i in frames])
    if len(parts) == 1:
        return parts[0]
    A, B = (jnp.concatenate(p, axis=0)[:T] for p in zip(*parts, strict=True))
    return A, B


def expand(f: Pieces, xs, us, lam, nu, rho):
    """The augmented cost's gradients and Hessians along (xs, us) (the dynamics': `jacobians`)."""
    problem, n, ts = f.problem, f.n, f.ts
    c = f.constraints(xs, us)
    active = active_set(c, lam)
    z = jnp.concatenate([xs[:-1], us], axis=1)

    def cost_z(zt, t):
        return problem.cost(zt[:n], zt[n:], t)

    def c_z(zt, t):
        return f.c(zt[:n], zt[n:], t)

    # The Lagrangian terms to first order in c (Gauss-Newton, as ALTRO): their Hessian is
    # rho C^T C over the active rows. Their exact Hessian adds (lam + rho c) * c'', which is
    # indefinite for a nonlinear constraint (a link's height, a torque through the state)
    # and would be met only by regularisation so large that the step vanishes.
    C = jax.vmap(jax.jacfwd(c_z))(z, ts)  # (T, p, n + m)
    g = jax.vmap(jax.grad(cost_z))(z, ts) + jnp.einsum("tpz,tp->tz", C, lam + rho * active * c)
    H = jax.vmap(jax.hessian(cost_z))(z, ts) + rho * jnp.einsum("tpz,tp,tpy->tzy", C, active, C)
    h = f.h(xs[-1])
    Ch = jax.jacfwd(f.h)(xs[-1])  # (q, n)
    gT = jax.grad(problem.terminal_cost)(xs[-1]) + Ch.T @ (nu + rho * h)
    HT = jax.hessian(problem.terminal_cost)(xs[-1]) + rho * Ch.T @ Ch
    return g, H, gT, HT


def backward(f: Pieces, A, B, g, H, gT, HT, reg):
    """Riccati recursion; returns gains, the predicted decrease terms and a failure flag."""
    n, m = f.n, f.m

    def step(carry, inputs):
        Vx, Vxx, failed = carry
        A_t, B_t, g_t, H_t = inputs
        Qx = g_t[:n] + A_t.T @ Vx
        Qu = g_t[n:] + B_t.T @ Vx
        Qxx = H_t[:n, :n] + A_t.T @ Vxx @ A_t
        Quu = H_t[n:, n:] + B_t.T @ Vxx @ B_t
        Qux = H_t[n:, :n] + B_t.T @ Vxx @ A_t
        Quu_reg = Quu + reg * jnp.eye(m)
        L = jnp.linalg.cholesky(0.5 * (Quu_reg + Quu_reg.T))
        bad = ~jnp.all(jnp.isfinite(L))
        solve = lambda r: jax.scipy.linalg.cho_solve((L, True), r)  # noqa: E731
        k = -solve(Qu)
        K = -solve(Qux)
        Vx = Qx + K.T @ Quu @ k + K.T @ Qu + Qux.T @ k
        Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
        Vxx = 0.5 * (Vxx + Vxx.T)
        dV = jnp.stack([k @ Qu, 0.5 * k @ Quu @ k])
        return (Vx, Vxx, failed | bad), (k, K, dV)

    (_, _, failed), (k, K, dV) = jax.lax.scan(step, (gT, HT, jnp.zeros((), bool)), (A, B, g, H), reverse=True)
    failed = failed | ~jnp.all(jnp.isfinite(k)) | ~jnp.all(jnp.isfinite(K))
    return k, K, jnp.sum(dV, axis=0), failed


def forward(f: Flow, xs, us, k, K, alpha):
    """The closed-loop rollout u = ū + α k + K (x − x̄) (`Flow.call`)."""

    def step(x, inputs):
        x_ref, u_ref, k_t, K_t, t = inputs
        u = u_ref + alpha * k_t + K_t @ (x - x_ref)
        x_next = f.dynamics(x, u, t)
        return x_next, (x_next, u)

    _, (x_new, u_new) = jax.lax.scan(step, xs[0], (xs[:-1], us, k, K, f.ts))
    return jnp.concatenate([xs[:1], x_new], axis=0), u_new


def open_loop_states(f: Flow, x0: Float[Array, " n"], controls: Float[Array, "T m"]) -> Array:
    """The states (T+1, n) of the open-loop `controls` from x0: the closed-loop forward pass with
    no feedback and no step, so that it and the solver's forward passes are one compiled program."""
    us = jnp.asarray(controls)
    T, m = us.shape
    n = x0.shape[0]
    xs = jnp.zeros((T + 1, n)).at[0].set(x0)
    return f.call(forward, xs, us, jnp.zeros((T, m)), jnp.zeros((T, m, n)), 0.0)[0]
