"""The assets every tool shares, from installed packages (nothing downloads): the Stanford bunny
that pymeshfix ships and the Franka Panda of example-robot-data."""

from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import trimesh

from dano.extras import MissingExtraError
from dano.fields import load_mesh
from dano.sim.scene import Number, Robot, Vec3

BUNNY_SCALE = 0.003
"""m per mesh unit: pymeshfix's bunny is ~50 units wide, a real Stanford bunny ~0.15 m."""

WATER = 1000.0
"""kg/m^3: the mesh field's peak density, so alpha = 1 gives the mass of a bunny of water."""


def bunny_path() -> Path:
    """The Stanford bunny's PLY file that pymeshfix ships."""
    import pymeshfix

    return Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"


def bunny_mesh() -> trimesh.Trimesh:
    """The pymeshfix Stanford bunny, repaired to be watertight and scaled to metres."""
    return load_mesh(bunny_path(), repair=True, scale=BUNNY_SCALE)


def panda(base_pos: Vec3 = (0.0, 0.0, 0.0), qpos: tuple[Number, ...] = (), **kwargs) -> Robot:
    """The Franka Panda of `example-robot-data` (URDF, STL collision meshes), with the 0.1 kg m²
    armature per joint of MuJoCo Menagerie's Panda (the URDF has none; without it the hand's joint,
    M_jj = 0.0067 kg m², is unstable under the default servo at 0.5 ms steps).

    Raises:
        MissingExtraError: example-robot-data is not installed (`pip install "dano[robots]"`).
    """
    kwargs.setdefault("armature", 0.1)
    try:
        root = Path(str(distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data")))
    except PackageNotFoundError:
        raise MissingExtraError('the Panda comes from example-robot-data: pip install "dano[robots]"') from None
    path = root / "robots" / "panda_description" / "urdf" / "panda.urdf"
    if not path.is_file():
        raise MissingExtraError(f'the Panda URDF is not at {path}: pip install "dano[robots]"')
    return Robot(str(path), base_pos=base_pos, qpos=qpos, package_dirs=(("example-robot-data", str(root)),), **kwargs)
