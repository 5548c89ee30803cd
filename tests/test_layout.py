"""The package's layout: every module imports only from its own layer or the layers below it, and
README's module graph is the one the code has (run `python tests/test_layout.py` to print it)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "src" / "dano"
README = ROOT.parent.parent / "README.md"

LAYERS = (
    ("foundations", ("errors", "math", "validate", "results", "extras", "lanes", "_mjx", "_lazy")),
    ("data and files", ("types", "io")),
    ("the object (eqs. 1-16)", ("fields", "sampling", "mass", "surface", "reference", "build", "contact")),
    ("simulation", ("sim",)),
    ("shared bases", ("assets", "scenarios")),
    ("real-to-sim, sim-to-robot", ("sysid", "trajopt")),
    ("pixels", ("vision",)),
    ("the mesh path", ("baselines",)),
    ("front ends", ("plotting", "report", "viewer", "demo", "cli")),
)
"""Bottom up. `dano/__init__.py`, the lazy public facade, may name anything."""

ALLOWED = {("sim", "assets"): "dano.sim.panda, a deprecated alias resolved on use (goes in 0.3)"}
"""Upward imports kept on purpose, each with its reason."""

LEVEL = {unit: i for i, (_, units) in enumerate(LAYERS) for unit in units}


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """The dano modules a file imports anywhere (inside functions too), `from dano import x`
    resolved to the module `dano.x` where there is one."""
    package = _module(path) if path.name == "__init__.py" else _module(path).rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            if not base.startswith("dano"):
                continue
            subs = [f"{base}.{a.name}" for a in node.names]
            found = [s for s in subs if (ROOT.parent / s.replace(".", "/")).with_suffix(".py").is_file()
                     or (ROOT.parent / s.replace(".", "/")).is_dir()]  # fmt: skip
            out.update(found if found else [base])
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("dano"))
    return out


def _unit(module: str) -> str:
    """`dano.sim.step` -> `sim`: the layer table's name for a module."""
    return module.split(".")[1] if module.count(".") else module


def unit_graph() -> dict[str, set[str]]:
    """Who imports whom, by top-level module or subpackage (the facade left out)."""
    graph: dict[str, set[str]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        module = _module(path)
        if module == "dano":
            continue
        unit = _unit(module)
        graph.setdefault(unit, set()).update(_unit(m) for m in _imports(path) if m != "dano" and _unit(m) != unit)
    return graph


def mermaid() -> str:
    """README's graph: one subgraph per layer, bottom layer last, an arrow per import of a module
    above the two bottom layers (which everything uses); dotted: an allowed upward import."""
    graph = unit_graph()
    lines = ["```mermaid", "flowchart TD"]
    for i, (name, units) in reversed(list(enumerate(LAYERS))):
        lines.append(f'  subgraph L{i}["{name}"]')
        lines.extend(f"    {u.strip('_')}[{u}]" for u in units)
        lines.append("  end")
    for unit in sorted(graph):
        for dep in sorted(d for d in graph[unit] if LEVEL[d] >= 2):  # every layer uses the foundations
            arrow = "-.->" if (unit, dep) in ALLOWED else "-->"
            lines.append(f"  {unit.strip('_')} {arrow} {dep.strip('_')}")
    lines.append("```")
    return "\n".join(lines)


def test_every_module_is_in_a_layer():
    assert set(unit_graph()) <= set(LEVEL), f"modules in no layer: {sorted(set(unit_graph()) - set(LEVEL))}"


def test_no_module_imports_from_a_layer_above_its_own():
    upward = sorted(
        f"{unit} ({LAYERS[LEVEL[unit]][0]}) imports {dep} ({LAYERS[LEVEL[dep]][0]})"
        for unit, deps in unit_graph().items()
        for dep in deps
        if LEVEL[dep] > LEVEL[unit] and (unit, dep) not in ALLOWED
    )
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_the_readme_draws_the_graph_the_code_has():
    text = README.read_text()
    found = re.search(r"```mermaid\nflowchart TD\n.*?```", text, re.S)
    assert found is not None, "README has no module graph (python tests/test_layout.py prints it)"
    assert found.group(0) == mermaid(), "README's module graph is stale: python tests/test_layout.py prints it"


def test_every_dotted_name_in_the_readme_exists():
    """`dano.x.y` in README's code spans: a module, or an attribute of one (deprecated aliases fail)."""
    import importlib
    import warnings

    missing = []
    for name in sorted(set(re.findall(r"`(dano(?:\.[A-Za-z_]\w*)+)", README.read_text()))):
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            try:
                obj, rest = importlib.import_module(".".join(parts[:i])), parts[i:]
                break
            except ModuleNotFoundError:
                continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                for attr in rest:
                    obj = getattr(obj, attr)
        except (AttributeError, DeprecationWarning):
            missing.append(name)
    assert not missing, f"README names what does not exist: {missing}"


if __name__ == "__main__":
    print(mermaid())
