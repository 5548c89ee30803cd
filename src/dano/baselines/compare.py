"""DANO against the mesh path, measured (paper Sec. VI, Fig. 8).

Every collision model of one object (a level-set mesh per density level, the DANO, and the truth
when there is one) goes through the same scenarios:

- drop: released at rest, level, its field frame 2 cm above where the truth rests, for `drop_s`;
  the rest pose is where it ends.
- slide: from that rest pose, launched along +x at `slide_speed`, for `slide_s`.
- push: from that rest pose, a sphere (driven kinematically, radius half the object's height at rest,
  on the floor, in line with its centre of mass) starts `push_gap` behind the object and moves along
  +x at `push_speed` for `push_s`.

Meshes run in MuJoCo's C engine (convex pieces, mass and inertia from the uncut mesh); the DANO in
dano's simulator (MJX + the probabilistic contact). Poses are of the field's own frame, so all
models are compared in one frame. Mass is compared at equal density: a mesh's volume against
the truth's, and the DANO's `mass / (alpha * peak)` (its volume-equivalent).
"""

import dataclasses
import time

import mujoco
import numpy as np

from dano.baselines.mesh import mujoco_mesh_spec
from dano.baselines.models import CompareError, Model, _geometry
from dano.sim.compile import add_primitive
from dano.sim.scene import Mode, Primitive


@dataclasses.dataclass(frozen=True)
class Scenarios:
    """What every model goes through (times in s, speeds in m/s, friction coefficient)."""

    friction: float = 0.5
    drop_height: float = 0.02
    drop_s: float = 1.0
    slide_speed: float = 0.5
    slide_s: float = 1.0
    push_speed: float = 0.2
    push_s: float = 0.8
    push_gap: float = 0.005
    timestep: float = 0.002


@dataclasses.dataclass(frozen=True)
class Pusher:
    """The push scenario's sphere: radius (m), centre at the start (world, m), velocity (m/s)."""

    radius: float
    start: np.ndarray
    velocity: np.ndarray

    def path(self, times: np.ndarray) -> np.ndarray:
        """Centre at `times` (n,) s: (n, 3)."""
        return self.start[None, :] + np.asarray(times)[:, None] * self.velocity[None, :]

    def primitive(self) -> Primitive:
        """The sphere as a mocap-driven primitive named "pusher" at its start."""
        return Primitive("pusher", "sphere", (self.radius,), tuple(self.start.tolist()), mode=Mode.mocap)


@dataclasses.dataclass(frozen=True)
class Outcome:
    """A model's scenarios: poses of the field frame (x, y, z, qw, qx, qy, qz) and timing."""

    rest: np.ndarray
    slide_end: np.ndarray
    push_end: np.ndarray
    sim_s: float

    @property
    def tilt_deg(self) -> float:
        """Angle of the rest orientation from the release orientation (level), degrees."""
        return _angle_deg(self.rest[3:], np.array([1.0, 0.0, 0.0, 0.0]))

    @property
    def slide_m(self) -> float:
        """Horizontal distance the field frame travelled in the slide, m."""
        return float(np.linalg.norm(self.slide_end[:2] - self.rest[:2]))

    @property
    def push_m(self) -> float:
        """Horizontal distance the field frame travelled in the push, m."""
        return float(np.linalg.norm(self.push_end[:2] - self.rest[:2]))


def release_height(reference: Model, scenarios: Scenarios) -> float:
    """Height of the field frame's origin that puts `reference`'s lowest point `drop_height` above z = 0."""
    return scenarios.drop_height - float(_geometry(reference)[:, 2].min())


def pusher(model: Model, rest: np.ndarray, scenarios: Scenarios) -> Pusher:
    """The push scenario's sphere for `model` at rest at pose `rest` (x, y, z, qw, qx, qy, qz of its
    field frame): radius half its height at rest, on the floor, starting `push_gap` behind its -x
    side in line with its centre of mass, moving along +x."""
    rot = _rotation(rest[3:])
    points = _geometry(model) @ rot.T + rest[:3]
    com = rot @ model.com + rest[:3]
    radius = 0.5 * float(points[:, 2].max() - max(points[:, 2].min(), 0.0))
    start = np.array([points[:, 0].min() - radius - scenarios.push_gap, com[1], radius + 1e-3])
    return Pusher(radius, start, np.array([scenarios.push_speed, 0.0, 0.0]))


def simulate(model: Model, height: float, scenarios: Scenarios = Scenarios()) -> Outcome:
    """Runs the drop, the slide and the push for one model (MuJoCo C for meshes, dano's simulator for
    the DANO)."""
    start = time.perf_counter()
    rest, slide, pushed = (_simulate_dano if model.dano is not None else _simulate_mesh)(model, height, scenarios)
    return Outcome(rest, slide, pushed, time.perf_counter() - start)


def _simulate_mesh(model: Model, height: float, s: Scenarios) -> tuple[np.ndarray, ...]:
    def compiled(push: Pusher | None) -> mujoco.MjModel:
        spec = mujoco_mesh_spec(
            model.pieces,  # type: ignore[arg-type]
            mass=1.0,
            pos=(0.0, 0.0, height),
            friction=s.friction,
            timestep=s.timestep,
            inertial=(model.com, model.inertia_per_mass),
        )
        if push is not None:
            add_primitive(spec, push.primitive(), friction=s.friction)
        return spec.compile()

    m = compiled(None)
    d = mujoco.MjData(m)
    mujoco.mj_step(m, d, nstep=int(round(s.drop_s / s.timestep)))
    rest = np.array(d.qpos[:7])
    d.qvel[:] = 0.0
    d.qvel[0] = s.slide_speed
    mujoco.mj_step(m, d, nstep=int(round(s.slide_s / s.timestep)))
    slide = np.array(d.qpos[:7])
    push = pusher(model, rest, s)
    m = compiled(push)
    d = mujoco.MjData(m)
    d.qpos[:7] = rest
    for centre in push.path(s.timestep * np.arange(1, int(round(s.push_s / s.timestep)) + 1)):
        d.mocap_pos[0] = centre
        mujoco.mj_step(m, d)
    pushed = np.array(d.qpos[:7])
    if not np.all(np.isfinite(np.concatenate([slide, pushed]))):
        raise CompareError(f"{model.label}: MuJoCo's state became non-finite")
    return rest, slide, pushed


def _simulate_dano(model: Model, height: float, s: Scenarios) -> tuple[np.ndarray, ...]:
    from dano.contact import ContactParams
    from dano.sim.run import Simulation, body_poses
    from dano.sim.scene import DanoBody, Scene

    dano = model.dano
    com = np.asarray(dano.com)  # type: ignore[union-attr]

    def run(pos, quat, vel, seconds, push=None):
        body = DanoBody("object", dano, pos=tuple(pos), quat=tuple(quat), vel=tuple(vel))  # type: ignore[arg-type]
        spheres = () if push is None else (push.primitive(),)
        scene = Scene(
            bodies=(body,), primitives=spheres, timestep=s.timestep, duration=seconds,
            contact=ContactParams(sliding_friction=s.friction),
        )  # fmt: skip
        sim = Simulation.from_scene(scene)
        path = None if push is None else push.path(s.timestep * np.arange(1, scene.n_steps + 1))[:, None, :]
        return body_poses(sim.run(mocap_pos=path), sim)["object"][-1]

    rest_com = run((com[0], com[1], com[2] + height), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), s.drop_s)
    rest = _com_to_frame(rest_com, com)
    slide_com = run(rest_com[:3], rest_com[3:], (s.slide_speed, 0.0, 0.0), s.slide_s)
    push_com = run(rest_com[:3], rest_com[3:], (0.0, 0.0, 0.0), s.push_s, pusher(model, rest, s))
    return rest, _com_to_frame(slide_com, com), _com_to_frame(push_com, com)


def _com_to_frame(pose: np.ndarray, com: np.ndarray) -> np.ndarray:
    """Pose of the centre of mass -> pose of the field frame (same orientation)."""
    return np.concatenate([pose[:3] - _rotation(pose[3:]) @ com, pose[3:]])


def _rotation(quat: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion (w, x, y, z), any norm."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat / np.linalg.norm(quat))
    return rot.reshape(3, 3)


def _angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    dot = abs(float(np.dot(q1 / np.linalg.norm(q1), q2 / np.linalg.norm(q2))))
    return float(np.degrees(2 * np.arccos(min(1.0, dot))))


def report(
    models: list[Model], outcomes: list[Outcome], truth: Model | None, truth_outcome: Outcome | None
) -> list[dict]:
    """One row per model: mass/inertia errors against the truth, rest and slide, pose differences, times."""
    rows = []
    for model, out in zip(models, outcomes, strict=True):
        row = {
            "model": model.label,
            "pieces": None if model.pieces is None else len(model.pieces),
            "rest_tilt_deg": out.tilt_deg,
            "rest_height_m": float(out.rest[2]),
            "slide_m": out.slide_m,
            "push_m": out.push_m,
            "preprocess_s": model.preprocess_s,
            "sim_s": out.sim_s,
        }
        if truth is not None and truth_outcome is not None:
            t = truth.inertia_per_mass
            row |= {
                "mass_error": model.volume / truth.volume - 1.0,
                "com_error_m": float(np.linalg.norm(model.com - truth.com)),
                "inertia_error": float(np.linalg.norm(model.inertia_per_mass - t) / np.linalg.norm(t)),
                "rest_position_diff_m": float(np.linalg.norm(out.rest[:3] - truth_outcome.rest[:3])),
                "rest_angle_diff_deg": _angle_deg(out.rest[3:], truth_outcome.rest[3:]),
                "slide_end_diff_m": float(np.linalg.norm(out.slide_end[:3] - truth_outcome.slide_end[:3])),
                "slide_angle_diff_deg": _angle_deg(out.slide_end[3:], truth_outcome.slide_end[3:]),
                "push_end_diff_m": float(np.linalg.norm(out.push_end[:3] - truth_outcome.push_end[:3])),
                "push_angle_diff_deg": _angle_deg(out.push_end[3:], truth_outcome.push_end[3:]),
            }
        rows.append({k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in row.items()})
    return rows


@dataclasses.dataclass(frozen=True)
class Comparison:
    """Everything `compare` measured: the models, their outcomes, the truth, and the table."""

    models: list[Model]
    outcomes: list[Outcome]
    truth: Model | None
    truth_outcome: Outcome | None
    rows: list[dict]


def compare(models: list[Model], truth: Model | None = None, scenarios: Scenarios = Scenarios()) -> Comparison:
    """Runs every model (and the truth) through the scenarios and tabulates the differences.

    The release height is set by the truth (else the last model), so all start at one height.
    `truth` may be one of `models` (e.g. the reference DANO when there is no better truth).
    """
    if not models:
        raise CompareError("nothing to compare")
    height = release_height(truth if truth is not None else models[-1], scenarios)
    outcomes = [simulate(m, height, scenarios) for m in models]
    if truth is None:
        truth_outcome = None
    else:  # the truth may be one of the models (the reference DANO): simulate it once
        same = [o for m, o in zip(models, outcomes, strict=True) if m is truth]
        truth_outcome = same[0] if same else simulate(truth, height, scenarios)
    return Comparison(models, outcomes, truth, truth_outcome, report(models, outcomes, truth, truth_outcome))


def format_table(rows: list[dict]) -> str:
    """The comparison as a fixed-width text table."""
    columns = [
        ("model", "model", "{}"), ("pieces", "pieces", "{}"), ("mass_error", "mass err", "{:+.1%}"),
        ("inertia_error", "inertia err", "{:.1%}"), ("com_error_m", "com err mm", "{:.1f}"),
        ("rest_tilt_deg", "tilt deg", "{:.1f}"), ("rest_height_m", "rest z mm", "{:.1f}"),
        ("slide_m", "slide mm", "{:.1f}"), ("push_m", "push mm", "{:.1f}"),
        ("rest_position_diff_m", "rest dpos mm", "{:.1f}"), ("rest_angle_diff_deg", "rest dang deg", "{:.1f}"),
        ("slide_end_diff_m", "slide dpos mm", "{:.1f}"), ("push_end_diff_m", "push dpos mm", "{:.1f}"),
        ("push_angle_diff_deg", "push dang deg", "{:.1f}"),
        ("preprocess_s", "prep s", "{:.1f}"), ("sim_s", "sim s", "{:.1f}"),
    ]  # fmt: skip
    scale = {"com_error_m", "rest_height_m", "slide_m", "push_m", "rest_position_diff_m", "slide_end_diff_m",
             "push_end_diff_m"}  # fmt: skip
    present = [c for c in columns if any(c[0] in r for r in rows)]
    cells = [[h for _, h, _ in present]]
    for r in rows:
        line = []
        for key, _, fmt in present:
            v = r.get(key)
            line.append("-" if v is None else fmt.format(v * 1e3 if key in scale else v))
        cells.append(line)
    widths = [max(len(row[i]) for row in cells) for i in range(len(present))]
    pad = [[c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))] for r in cells]
    return "\n".join("  ".join(r) for r in pad)
