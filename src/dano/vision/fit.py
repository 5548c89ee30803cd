"""Fitting a density field to posed images by volume rendering (a small NeRF, in JAX, on CPU or GPU).

The model is a `NeuralField` (the density dano builds DANOs from, in optical units 1/m) beside a
small colour network; both see the same positional encoding of the point. Views without view
dependence are assumed (diffuse objects under fixed lights), which keeps the colour network small.

Loss: the mean squared colour error of a random batch of rays, plus `mask_weight` times the mean
squared error of their accumulated opacity against the object masks when the views have masks. The
masks are what pin the geometry down on few, small images; colour refines the concavities a mask
cannot see.

The box the field lives in is the visual hull's when there are masks: the points that project
inside the mask in every view, padded by `margin`. Rays are sampled only inside that box.
"""

import abc
import dataclasses
import math
import time
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float, PRNGKeyArray
from tqdm.auto import tqdm

from dano.fields import GridField, NeuralField
from dano.fields.base import AbstractField, Bounds, as_bounds
from dano.fields.grid import grid_nodes, trilinear
from dano.results import AbstractSolution, Result, finish
from dano.vision.camera import camera_rays, project
from dano.vision.configs import FitConfig, FitError, GridModel, MlpModel
from dano.vision.datasets import Views
from dano.vision.render import ray_box, render_opacity, render_rgb


def cosine_rate(rate: float, progress: Float[Array, ""]) -> Float[Array, ""]:
    """A learning rate decaying from `rate` along a half cosine to 5 % of it as `progress` goes 0 -> 1."""
    return rate * (0.05 + 0.475 * (1.0 + jnp.cos(jnp.pi * progress)))


class AbstractRadiance(eqx.Module):
    """What `fit_field` trains: optical density (1/m) and diffuse colour in [0, 1] at points (n, 3),
    world frame; the density alone as a field to build a DANO from; a regulariser for the loss."""

    @abc.abstractmethod
    def __call__(self, x: Float[Array, "n 3"]) -> tuple[Float[Array, " n"], Float[Array, "n 3"]]: ...

    @abc.abstractmethod
    def density_field(self) -> AbstractField: ...

    @abc.abstractmethod
    def regulariser(self) -> Float[Array, ""]: ...


class RadianceField(AbstractRadiance):
    """Optical density (a `NeuralField`, 1/m) and diffuse colour in [0, 1] at points (n, 3), world frame."""

    density: NeuralField
    colour: eqx.nn.MLP

    def __call__(self, x: Float[Array, "n 3"]) -> tuple[Float[Array, " n"], Float[Array, "n 3"]]:
        lo, hi = (jnp.asarray(b, dtype=x.dtype) for b in self.density.bounds)
        u = 2 * (x - lo[None, :]) / (hi - lo)[None, :] - 1
        return self.density(x), jax.nn.sigmoid(jax.vmap(self.colour)(self.density.encode(u)))

    def density_field(self) -> NeuralField:
        return self.density

    def regulariser(self) -> Float[Array, ""]:
        bias = self.density.mlp.layers[-1].bias
        assert bias is not None  # the MLP of a `NeuralField` has biases
        return jnp.zeros((), dtype=bias.dtype)


class VoxelRadiance(AbstractRadiance):
    """Density scale * softplus(raw) and sigmoid(colour) of trilinearly interpolated node values.

    The activation comes after the interpolation, so a surface can be sharper than a cell.
    """

    raw: Float[Array, "nx ny nz"]
    colour: Float[Array, "nx ny nz 3"]
    scale: float = eqx.field(static=True)
    bounds: Bounds = eqx.field(static=True, converter=as_bounds)

    def __call__(self, x: Float[Array, "n 3"]) -> tuple[Float[Array, " n"], Float[Array, "n 3"]]:
        values = trilinear(jnp.concatenate([self.raw[..., None], self.colour], axis=-1), self.bounds, x)
        return self.scale * jax.nn.softplus(values[:, 0]), jax.nn.sigmoid(values[:, 1:])

    def density_field(self) -> GridField:
        """The density at the nodes as a `GridField` (1/m)."""
        return GridField(self.scale * jax.nn.softplus(self.raw), self.bounds)

    def regulariser(self) -> Float[Array, ""]:
        """Mean squared difference of neighbouring nodes' raw density (total variation)."""
        r = self.raw
        return cast(Array, sum(jnp.mean(jnp.diff(r, axis=a) ** 2) for a in range(3)))


def init_radiance_field(bounds, config: FitConfig, *, key: PRNGKeyArray) -> AbstractRadiance:
    """`config.model`'s radiance field in the box `bounds` (2, 3), nearly transparent."""
    lo, hi = np.asarray(bounds, dtype=float)
    spacing = float(np.linalg.norm(hi - lo)) / config.n_samples
    scale = 1.0 / (config.opaque_samples * spacing)
    assert isinstance(config.model, GridModel | MlpModel)  # `FitConfig.__post_init__` normalises a name
    return config.model.init(np.stack([lo, hi]), scale, key)


def visual_hull_bounds(views: Views, resolution: int = 48, margin: float = 0.1) -> np.ndarray:
    """(2, 3) box of the visual hull (points inside every view's mask), padded by `margin` of its size.

    The search grid spans the region all cameras look at: the cube around the point nearest to all
    optical axes, as wide as the mean camera distance to that point.

    Raises:
        FitError: no masks, or no point is inside every mask.
    """
    if views.masks is None:
        raise FitError("the views have no masks: give the field's box explicitly (bounds=...)")
    centre, reach = _look_region(views)
    axis = np.linspace(-reach, reach, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + centre
    inside = np.ones(len(grid), dtype=bool)
    for camera, mask in zip(views.cameras, views.masks, strict=True):
        uv, depth = project(camera, grid)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (depth > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        hit = np.zeros(len(grid), dtype=bool)
        hit[ok] = mask[row[ok], col[ok]] > 0.5
        inside &= hit
    if not inside.any():
        raise FitError("the masks' visual hull is empty: do the cameras' poses match the images?")
    step = axis[1] - axis[0]
    lo, hi = grid[inside].min(axis=0) - step, grid[inside].max(axis=0) + step
    pad = margin * (hi - lo)
    return np.stack([lo - pad, hi + pad])


def _look_region(views: Views) -> tuple[np.ndarray, float]:
    """The point nearest (least squares) to every camera's optical axis, and the mean distance to it."""
    eyes = np.stack([c.c2w[:3, 3] for c in views.cameras])
    axes = np.stack([-c.c2w[:3, 2] for c in views.cameras])
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    centre = np.linalg.lstsq(projectors.sum(0), np.einsum("nij,nj->i", projectors, eyes), rcond=None)[0]
    return centre, float(np.mean(np.linalg.norm(eyes - centre, axis=1)))


@dataclasses.dataclass(frozen=True)
class FitResult(AbstractSolution):
    """The fitted model and its training curve (`dano.results.AbstractSolution`).

    Attributes:
        field: the optical density (1/m): a `GridField` ("grid") or `NeuralField` ("mlp"); save it
            with `save_grid` / `save_neural_field`, build a DANO from it with `build_dano`. The
            solution's `value`.
        model: density and colour together.
        bounds: (2, 3) the box it lives in.
        loss, psnr: per step taken (PSNR of the colour, dB).
        seconds: wall time of the training loop (compilation included).
        result: `completed` (all `FitConfig.steps` taken) or `nonfinite` (stopped at the first
            non-finite loss; the model is the last finite one).
        message: in words.
        iterations: optimiser steps taken.
    """

    field: GridField | NeuralField
    model: AbstractRadiance
    bounds: np.ndarray
    loss: np.ndarray
    psnr: np.ndarray
    seconds: float
    result: Result = Result.completed
    message: str = ""
    iterations: int = 0

    @property
    def value(self) -> GridField | NeuralField:
        return self.field


def fit_field(
    views: Views,
    config: FitConfig = FitConfig(),
    bounds=None,
    background=(1.0, 1.0, 1.0),
    *,
    key: PRNGKeyArray,
    progress: bool = True,
    throw: bool = True,
) -> FitResult:
    """Fits a density and colour field to posed images (volume rendering, Adam).

    Args:
        views: images, cameras and (optionally) masks, e.g. from `load_nerf_synthetic`.
        bounds: (2, 3) box of the object, world frame; default: the masks' visual hull, padded.
        background: the colour behind the object in the images (white for NeRF-synthetic data).
        throw: raise `SolverError` where the loss becomes non-finite (else the last finite model is
            returned with `result` `nonfinite`).

    Raises:
        FitError: no masks and no bounds, or an empty visual hull.
        SolverError: `throw` and the loss became non-finite.
    """
    dtype = jnp.dtype(config.dtype)
    bounds = visual_hull_bounds(views) if bounds is None else np.asarray(bounds, dtype=float)
    rays = [camera_rays(c) for c in views.cameras]
    origins = jnp.asarray(np.concatenate([o for o, _ in rays]), dtype=dtype)
    directions = jnp.asarray(np.concatenate([d for _, d in rays]), dtype=dtype)
    colours = jnp.asarray(views.images.reshape(-1, 3), dtype=dtype)
    has_masks = views.masks is not None
    masks = jnp.asarray(views.masks.reshape(-1) if views.masks is not None else np.zeros(len(colours)), dtype=dtype)
    near, far = ray_box(origins, directions, jnp.asarray(bounds, dtype=dtype))
    bg = jnp.asarray(background, dtype=dtype)
    mask_weight = config.mask_weight if has_masks else 0.0

    k_init, k_train = jax.random.split(key)
    model = init_radiance_field(bounds, config, key=k_init)
    assert isinstance(config.model, GridModel | MlpModel)
    regularisation = config.model.regularisation
    params, static = eqx.partition(model, eqx.is_inexact_array)
    params = jax.tree_util.tree_map(lambda a: a.astype(dtype), params)

    def schedule(count):  # optax's own cosine schedule mixes int and float, which strict promotion refuses
        return cosine_rate(config.learning_rate, jnp.minimum(count, config.steps).astype(dtype) / config.steps)

    optimiser = optax.adam(schedule)
    state = optimiser.init(params)

    @jax.jit
    def step(params, state, key):
        k_rays, k_samples = jax.random.split(key)
        i = jax.random.randint(k_rays, (config.batch_rays,), 0, origins.shape[0])

        def loss_fn(p):
            model = eqx.combine(p, static)
            rgb, opacity = render_rgb(model, origins[i], directions[i], near[i], far[i], config.n_samples, bg,
                                      k_samples)  # fmt: skip
            colour_mse = jnp.mean((rgb - colours[i]) ** 2)
            masked = mask_weight * jnp.mean((opacity - masks[i]) ** 2)
            return colour_mse + masked + regularisation * model.regulariser(), colour_mse

        (loss, mse), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        with jax.numpy_dtype_promotion("standard"):  # optax raises floats to int powers
            updates, state = optimiser.update(grads, state, params)
        return optax.apply_updates(params, updates), state, loss, mse

    losses, psnrs = np.zeros(config.steps), np.zeros(config.steps)
    result, message, taken = Result.completed, f"{config.steps} steps", config.steps
    start = time.perf_counter()
    bar = tqdm(range(config.steps), desc="fit field", disable=not progress)
    for n in bar:
        new_params, new_state, loss, mse = step(params, state, jax.random.fold_in(k_train, n))
        losses[n], psnrs[n] = float(loss), -10.0 * math.log10(max(float(mse), 1e-12))
        if not np.isfinite(losses[n]):
            result, message, taken = Result.nonfinite, f"stopped at step {n}; lower the learning rate", n
            break
        params, state = new_params, new_state
        if n % 50 == 0 or n == config.steps - 1:
            bar.set_postfix(loss=f"{losses[n]:.2e}", psnr=f"{psnrs[n]:.1f} dB")
    bar.close()
    message = f"{result.value}: {message}"
    finish(result, f"fit_field {message}", throw)
    seconds = time.perf_counter() - start
    params = jax.tree_util.tree_map(lambda a: a.astype(jnp.result_type(float)), params)
    model = eqx.combine(params, static)
    return FitResult(model.density_field(), model, bounds, losses[:taken], psnrs[:taken], seconds, result=result,
                     message=message, iterations=taken)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Solid:
    """A fitted field made a solid: `field` is `peak` where no camera sees into the object and 0 where
    one does (trilinear in between); `seen` (nodes) is the largest transmittance from the cameras
    that looked at the node: every camera where it is `threshold` or less (inside), the cameras up to
    the first that sees it past `threshold` where it is more (free space is settled by one camera)."""

    field: GridField
    seen: np.ndarray


def solidify(
    field: GridField, views: Views, peak: float = 1000.0, threshold: float = 0.8, n_views: int = 24,
    chunk: int = 16384,
) -> Solid:  # fmt: skip
    """The object as a solid of uniform density: the space no camera sees into (space carving).

    Images constrain a radiance field only until it is opaque, so the inside of a fitted field is a
    fog of arbitrary density, and thin haze floats around it: neither density is mass. A grid node
    is free space if some camera sees it (the transmittance from that camera to the node exceeds
    `threshold`); every other node is inside the object. Of those, the largest connected region is
    kept (isolated specks are dropped) and given density `peak` (1000: water, so alpha = 1 gives kg).

    Space no camera looks into (e.g. under an object filmed from above only) counts as inside.
    """
    from scipy import ndimage

    nodes = grid_nodes(field.bounds, cast(tuple[int, int, int], field.density.shape)).reshape(-1, 3)
    chosen = np.unique(np.linspace(0, views.n_views - 1, min(n_views, views.n_views)).astype(int))
    lo, hi = np.asarray(field.bounds)
    n_samples = int(np.ceil(np.linalg.norm(hi - lo) / np.min(field.spacing)))
    box = jnp.asarray(np.stack([lo, hi]))

    @jax.jit
    def transmittance(eye, targets):
        directions = targets - eye[None, :]
        distance = jnp.linalg.norm(directions, axis=-1)
        directions = directions / distance[:, None]
        origins = jnp.broadcast_to(eye, targets.shape)
        near, _ = ray_box(origins, directions, box)
        return 1.0 - render_opacity(field, origins, directions, near, jnp.maximum(distance, near), n_samples)

    seen = np.zeros(len(nodes))
    chunk = min(chunk, len(nodes))
    for k in chosen:
        eye = jnp.asarray(views.cameras[k].c2w[:3, 3])
        # Only the nodes no camera has seen past `threshold` yet: a node seen once is free space
        # whatever the next cameras see (most of the grid is settled by the first few cameras).
        # Each chunk is padded to `chunk` nodes so that one program serves them all.
        open_nodes = np.flatnonzero(seen <= threshold)
        for start in range(0, len(open_nodes), chunk):
            index = open_nodes[start : start + chunk]
            padded = np.pad(index, (0, chunk - len(index)), mode="edge")
            part = np.asarray(transmittance(eye, jnp.asarray(nodes[padded])))[: len(index)]
            seen[index] = np.maximum(seen[index], part)
    seen = seen.reshape(field.density.shape)
    labels, n = cast(tuple[np.ndarray, int], ndimage.label(seen <= threshold))
    if n == 0:
        raise FitError("every node of the fitted field is seen by some camera: the field is empty")
    largest = 1 + int(np.argmax(ndimage.sum(np.ones_like(seen), labels, range(1, n + 1))))
    return Solid(GridField(jnp.asarray(peak * (labels == largest)), field.bounds), seen)
