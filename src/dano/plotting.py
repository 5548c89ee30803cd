"""Pictures of DANOs (matplotlib, headless)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from dano.io import atomic_write  # noqa: E402
from dano.types import DANO  # noqa: E402


def plot_dano(dano: DANO, path: str | Path, title: str = "", n_normals: int = 400, seed: int = 0) -> Path:
    """Saves a PNG of the surface points (coloured by density), some normals, and the centre of mass.

    Two views: three-quarter and side. Written atomically (temporary file, then rename).
    """
    points, normals = np.asarray(dano.points), np.asarray(dano.normals)
    com = np.asarray(dano.com)
    pick = np.random.default_rng(seed).choice(len(points), size=min(n_normals, len(points)), replace=False)
    size = float(np.max(points.max(0) - points.min(0)))
    fig = plt.figure(figsize=(11, 5.2))
    for k, (elev, azim) in enumerate([(20, -60), (0, -90)]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        sc = ax.scatter(*points.T, c=np.asarray(dano.densities), s=1.5, cmap="viridis", alpha=0.6)
        ax.quiver(*points[pick].T, *normals[pick].T, length=0.08 * size, color="tab:red", linewidth=0.6)
        ax.scatter(*com, color="black", s=40, label="centre of mass")
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(np.ptp(points, axis=0))
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        if k == 0:
            ax.legend(loc="upper left")
    fig.colorbar(sc, ax=fig.axes, shrink=0.6, label="density")
    fig.suptitle(title or f"DANO: {dano.n_points} surface points, mass {float(dano.mass):.4g} kg, normals in red")
    path = Path(path)
    with atomic_write(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
