"""Shared test helpers."""

import numpy as np


def central_difference(f, x: float, rel_step: float = 1e-5) -> float:
    """Central finite difference of a scalar function, step scaled to the input."""
    h = rel_step * max(abs(x), 1.0)
    return (f(x + h) - f(x - h)) / (2 * h)


def partial_differences(f, x0: tuple, rel_step: float = 1e-5) -> list[np.ndarray]:
    """Central differences of `f(*x0)` w.r.t. each scalar argument in turn, steps scaled to the inputs."""
    out = []
    for i, xi in enumerate(x0):
        h = rel_step * max(abs(xi), 1.0)
        plus, minus = list(x0), list(x0)
        plus[i], minus[i] = xi + h, xi - h
        out.append((np.asarray(f(*plus)) - np.asarray(f(*minus))) / (2 * h))
    return out


def with_value(f):
    """f returning its value twice, for `jax.jacfwd(..., has_aux=True)`: the Jacobian and the value
    from one compiled program (central differences then need no program of their own). The value
    is computed once: `(v, v)`, not two calls of f, which would trace the rollout twice."""
    return lambda *args: (f(*args),) * 2


def analytic_fields():
    """The analytic fields the tests share (sphere, box, capsule with soft edges)."""
    from dano.fields import BoxField, CapsuleField, SphereField

    return [
        SphereField(0.05, width=0.005),
        BoxField([0.1, 0.06, 0.03], width=0.003),
        CapsuleField(0.02, 0.05, width=0.004),
    ]


def rel_err(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def browser_screenshot(page, out, size: tuple[int, int] = (1000, 1400)) -> tuple[np.ndarray, list[str]]:
    """Opens `page` (a file) in headless Chromium (Debian's `chromium`) and returns its screenshot
    (height, width, channels) and every line the page wrote to its console; skips where Chromium
    is not installed (`.ci/run` installs it). WebGL runs on the CPU (SwiftShader); the GL driver's
    own performance notes about the screenshot's read-back are not the page's and are left out."""
    import shutil
    import subprocess
    from pathlib import Path

    import imageio.v3 as iio
    import pytest

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("headless Chromium not found (Debian: apt-get install chromium; .ci/run installs it)")
    out, page = Path(out), Path(page).resolve()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-sync",
             "--disable-background-networking", "--disable-component-update", "--enable-logging=stderr", "--v=0",
             f"--user-data-dir={out.parent / 'chromium-profile'}", f"--window-size={size[0]},{size[1]}",
             f"--screenshot={out}", "--virtual-time-budget=3000", "--enable-unsafe-swiftshader"]  # fmt: skip
    run = subprocess.run([chromium, *flags, page.as_uri()], capture_output=True, text=True, timeout=120)
    assert out.is_file(), run.stderr[-2000:]
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line and "GL Driver Message" not in line]
    return iio.imread(out), console
