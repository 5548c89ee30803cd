"""The identification experiment's pushes simulated by MuJoCo C on the object's true mesh (a CoACD
convex decomposition, MuJoCo's own soft contacts): data from another engine for `dano.sysid`."""

import dataclasses

import mujoco
import numpy as np
import trimesh

from dano.baselines.mesh import convex_decomposition, mujoco_mesh_spec
from dano.scenarios import PUSHER, push_plan
from dano.sim.compile import add_primitive
from dano.sim.scene import DanoBody, Primitive, Scene
from dano.sysid.experiments import push_recording
from dano.sysid.windows import Recording


def mesh_push_recordings(
    scene: Scene,
    mesh: trimesh.Trimesh,
    mass: float,
    friction: float,
    n_pushes: int = 10,
    fps: float = 100.0,
    n_frames: int = 41,
    force: tuple[float, float] = (2.0, 5.0),
    seed: int = 0,
    timestep: float = 0.001,
    max_hulls: int = 16,
) -> list[Recording]:
    """The pushes of `push_recordings` (same seed, same starts and forces) simulated by another
    engine: MuJoCo C with the object's true shape, `mesh` (in the frame of the field the scene's
    DANO was built from), as a CoACD convex decomposition of `mass` kg (inertia from the pieces)
    and MuJoCo's own soft contacts with `friction` on every geom.

    The object is first left to settle on the table for 0.5 s; its tracked pose is that of the
    frame at the DANO's centre of mass, as a tracker would report a fixed frame on the object.
    """
    plan = push_plan(scene, n_pushes, fps, n_frames, force, seed)
    dano, pusher = plan.scene.bodies[0], plan.scene.primitives[0]
    pieces = [p.apply_translation(-np.asarray(dano.dano.com)) for p in convex_decomposition(mesh, max_hulls=max_hulls)]
    model = _mesh_push_model(pieces, mass, friction, dano, pusher, timestep)
    data = mujoco.MjData(model)
    per_frame = max(1, round(1.0 / (fps * timestep)))
    mujoco.mj_forward(model, data)
    for _ in range(round(0.5 / timestep)):
        mujoco.mj_step(model, data)
    rest_qpos = data.qpos.copy()
    obj_body, pusher_body = model.body("object").id, model.body(PUSHER).id
    out = []
    for where, ctrl in zip(plan.starts, plan.ctrls, strict=True):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = rest_qpos
        data.qpos[7:10] = where - np.asarray(pusher.pos)
        mujoco.mj_forward(model, data)
        obj, tip = [], []
        for k in range(n_frames):
            obj.append(np.concatenate([data.xpos[obj_body], data.xquat[obj_body]]))
            tip.append(data.xpos[pusher_body].copy())
            if k < n_frames - 1:
                data.ctrl[:] = ctrl[k]
                for _ in range(per_frame):
                    mujoco.mj_step(model, data)
        out.append(push_recording(np.stack(obj), np.stack(tip), ctrl, fps, "MuJoCo C, CoACD mesh"))
    return out


def _mesh_push_model(pieces, mass: float, friction: float, dano: DanoBody, pusher: Primitive, timestep: float):
    """MuJoCo C model of a push: ground, the object as convex pieces, the actuated sphere (as dano's
    scene adds it, but colliding in MuJoCo: there is no DANO contact here)."""
    spec = mujoco_mesh_spec(pieces, mass, dano.pos, dano.quat, friction, timestep)
    add_primitive(spec, dataclasses.replace(pusher, collide=True), friction=friction)
    return spec.compile()
