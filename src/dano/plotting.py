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
        sc = ax.scatter(*points.T, c=np.asarray(dano.densities), s=1.5, cmap="viridis", alpha=0.6)  # pyright: ignore[reportArgumentType]
        ax.quiver(*points[pick].T, *normals[pick].T, length=0.08 * size, color="tab:red", linewidth=0.6)  # pyright: ignore[reportArgumentType]
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
    return _save(fig, path)


def plot_identification(problem, result, path: str | Path, max_windows: int = 6) -> Path:
    """Saves a PNG: observed (dots) and fitted (lines) positions of every observed body in the first
    windows, x, y, z against time, and the loss per iteration (log scale).

    Args:
        problem: a `dano.sysid.Problem`; result: its `dano.sysid.Identification`.
    """
    from dano.sysid import simulate_windows

    qpos = np.asarray(simulate_windows(problem, result.theta, result.delta))  # (n, W + 1, nq)
    w = problem.windows
    target, mask = np.asarray(w.target_pos), np.asarray(w.mask) > 0
    dt = problem.scene.timestep
    n = min(problem.n_windows, max_windows)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [2.2, 1]})
    ax = axes[0]
    colours = {"x": "tab:blue", "y": "tab:orange", "z": "tab:green"}
    for i in range(n):
        t0 = i * problem.n_frames * dt if problem.recordings == 1 else 0.0
        t = t0 + dt * np.arange(problem.n_frames + 1)
        for b, o in enumerate(problem.observed):
            start = np.asarray(w.qpos[i, o.qpos : o.qpos + 3]) + np.asarray(o.offset)
            sim = qpos[i, :, o.qpos : o.qpos + 3] + np.asarray(o.offset)
            obs = np.concatenate([start[None], target[i, :, b]])
            keep = np.concatenate([[True], mask[i]])
            for k, axis in enumerate("xyz"):
                label = f"{axis}" if i == 0 and b == 0 else None
                ax.plot(t[keep], sim[keep, k], color=colours[axis], lw=1.4, label=label)
                ax.plot(t[keep], obs[keep, k], ".", color=colours[axis], ms=3.5)
    ax.set_xlabel("time in window [s]" if problem.recordings > 1 else "time [s]")
    ax.set_ylabel("position [m]")
    names = ", ".join(o.name for o in problem.observed)
    ax.set_title(f"{names}: observed (dots) and fitted (lines), {n} of {problem.n_windows} window(s)")
    ax.legend(loc="best")
    ax = axes[1]
    ax.semilogy(np.arange(len(result.loss)), np.maximum(result.loss, 1e-300), "o-", color="black")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss ½Σr² (r in units of σ)")
    fitted = ", ".join(f"{k} = {v:.4g} ± {result.stderr[k]:.2g}" for k, v in result.params.items())
    ax.set_title(fitted, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def plot_masks(problem, result, path: str | Path, n_frames: int = 8) -> Path:
    """Saves a PNG for an identification from masks (`dano.vision.pixels`): for `n_frames` frames
    spread over the video, the mask, the DANO's silhouette simulated at the estimate, and their
    difference (red: mask only, blue: silhouette only), each over the frame's window; and the loss
    per iteration.
    """
    from dano.vision.observation import PixelObservation, simulated_silhouettes

    observation = problem.observation
    if not isinstance(observation, PixelObservation):
        raise TypeError("plot_masks needs a problem fitted to masks (dano.vision.pixels.mask_problem)")
    opacity, mask = simulated_silhouettes(problem, result.theta, result.delta)
    shape = observation.shape
    n = len(opacity)
    picks = np.unique(np.linspace(0, n - 1, min(n_frames, n)).round().astype(int))
    rows, cols = shape
    fig = plt.figure(figsize=(1.5 * len(picks) * cols / rows + 3.6, 5.2))
    grid = fig.add_gridspec(3, len(picks) + 1, width_ratios=[1.0] * len(picks) + [1.6 * len(picks) * rows / cols / 4])
    axes = np.array([[fig.add_subplot(grid[r, c]) for c in range(len(picks))] for r in range(3)])
    fps = 1.0 / problem.scene.timestep
    for c, k in enumerate(picks):
        seen, sim = mask[k].reshape(shape), opacity[k].reshape(shape)
        difference = seen - sim
        axes[0, c].imshow(seen, cmap="gray", vmin=0, vmax=1)
        axes[1, c].imshow(sim, cmap="gray", vmin=0, vmax=1)
        axes[2, c].imshow(difference, cmap="bwr_r", vmin=-1, vmax=1)
        axes[0, c].set_title(f"frame {k + 1}\n{(k + 1) / fps:.3f} s", fontsize=8)
        for r in range(3):
            axes[r, c].set_xticks([])
            axes[r, c].set_yticks([])
    for r, label in enumerate(["mask", "simulated", "mask − sim."]):
        axes[r, 0].set_ylabel(label)
    ax = fig.add_subplot(grid[:, -1])
    ax.semilogy(np.arange(len(result.loss)), np.maximum(result.loss, 1e-300), "o-", color="black", ms=3)
    ax.set_xlabel("iteration (last horizon)")
    ax.set_ylabel("loss ½Σr²")
    fitted = "\n".join(f"{k} = {v:.4g} ± {result.stderr[k]:.2g}" for k, v in result.params.items())
    ax.set_title(fitted, fontsize=8)
    names = ", ".join(o.name for o in problem.observed)
    fig.suptitle(f"{names}: masks and the silhouette simulated at the estimate (each frame's window)")
    fig.tight_layout()
    return _save(fig, path)


def plot_rests(comparison, path: str | Path, title: str = "") -> Path:
    """Fig. 8 of the paper, measured: each model at its rest pose on the floor, seen from the side
    (x-z) and from the front (y-z): level-set meshes as their faces, the DANO as its points."""
    import jax.numpy as jnp

    from dano.math import quat_to_mat

    entries = list(zip(comparison.models, comparison.outcomes, strict=True))
    if comparison.truth is not None and all(m is not comparison.truth for m in comparison.models):
        entries.append((comparison.truth, comparison.truth_outcome))
    fig, axes = plt.subplots(2, len(entries), figsize=(3.2 * len(entries), 5.6), squeeze=False)
    for k, (model, outcome) in enumerate(entries):
        rot = np.asarray(quat_to_mat(jnp.asarray(outcome.rest[3:])))
        for row, (a, b) in enumerate([(0, 2), (1, 2)]):
            ax = axes[row, k]
            if model.mesh is not None:
                v = np.asarray(model.mesh.vertices) @ rot.T + outcome.rest[:3]
                tris = v[np.asarray(model.mesh.faces)][:, :, [a, b]]
                from matplotlib.collections import PolyCollection

                ax.add_collection(PolyCollection(tris, facecolor="tab:blue", edgecolor="none", alpha=0.05))
            else:
                p = np.asarray(model.dano.points) @ rot.T + outcome.rest[:3]
                ax.scatter(p[:, a], p[:, b], s=0.5, color="tab:orange")
            ax.axhline(0.0, color="black", linewidth=1.0)
            ax.autoscale_view()
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel("xyz"[a] + " [m]")
            if k == 0:
                ax.set_ylabel("z [m]")
        label = f"{model.label}\ntilt {outcome.tilt_deg:.1f} deg, z {outcome.rest[2] * 1e3:.0f} mm"
        axes[0, k].set_title(label, fontsize=9)
    fig.suptitle(title or "At rest on the floor: level-set meshes (MuJoCo) and the DANO")
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    """Writes the figure as a PNG atomically (temporary file, then rename) and closes it."""
    path = Path(path)
    with atomic_write(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
