"""The package's folders are its layers: imports point one way, no folder imports a folder above
it, no private name crosses a module, and importing the core pulls in no RL library."""

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import marlmerge

ROOT = Path(marlmerge.__file__).parent
RL_LIBS = ("torch", "torchrl", "tensordict", "pettingzoo", "gymnasium")

LAYERS = (
    ("config",),
    ("sim",),
    ("io", "policies"),
    ("views",),
    ("learners",),
    ("evaluation", "validation"),
    ("training",),
    ("cli", "__main__"),
)
"""The package's layers, lowest first: config <- core <- saved files and rule policies <- views
<- learners <- evaluation (and validation against SUMO) <- training <- CLI. A module imports
only from its own layer or below, at the top of a file or inside a function alike."""

ROOT_MODULES = {"__init__", "__main__", "cli"}


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(ROOT.rglob("*.py")):
        module = ".".join(("marlmerge", *path.relative_to(ROOT).with_suffix("").parts))
        out.append((module.removesuffix(".__init__"), path))
    return out


def _folder(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "marlmerge" and len(parts) > 1 else None


def _layer(module: str) -> int | None:
    folder = _folder(module)
    if folder is None:
        return None
    found = [i for i, names in enumerate(LAYERS) if folder in names]
    assert found, f"{module} belongs to no layer: add its folder to LAYERS"
    return found[0]


def _imports(tree: ast.AST):
    """(line, module, imported names) of every import of a marlmerge module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("marlmerge"):
            if node.module == "marlmerge":  # `from marlmerge import x`: x may be a module
                for a in node.names:
                    yield node.lineno, f"marlmerge.{a.name}", []
            else:
                yield node.lineno, node.module, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("marlmerge"):
                    yield node.lineno, a.name, []


def _edges():
    for module, path in _modules():
        if module == "marlmerge":
            continue  # the front door loads its public names lazily
        for line, target, names in _imports(ast.parse(path.read_text())):
            yield module, line, target, names


def test_only_the_front_door_and_the_cli_sit_at_the_package_root():
    root = {p.stem for p in ROOT.glob("*.py")}
    assert root == ROOT_MODULES, f"modules at the package root: {sorted(root - ROOT_MODULES)}"


def test_imports_point_one_way():
    upward = [
        f"{module}:{line} imports {target}"
        for module, line, target, _ in _edges()
        if _layer(target) is not None and _layer(target) > _layer(module)
    ]
    assert not upward, "imports against the layers:\n" + "\n".join(upward)


def test_no_import_cycle_between_folders():
    graph: dict[str, set[str]] = {}
    for module, _, target, _ in _edges():
        a, b = _folder(module), _folder(target)
        if a and b and a != b:
            graph.setdefault(a, set()).add(b)

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for nxt in graph.get(start, ()):
            if nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})):
                return True
        return False

    cycles = sorted(f for f in graph if reaches(f, f, {f}))
    assert not cycles, f"folders on an import cycle: {cycles}"


def test_no_private_name_is_imported_across_modules():
    private = [
        f"{module}:{line} imports {target} {name}"
        for module, line, target, names in _edges()
        for name in [*names, *target.split(".")]
        if name.startswith("_") and not name.startswith("__")
    ]
    assert not private, "private names imported from another module:\n" + "\n".join(private)


@pytest.mark.parametrize(
    "code",
    [
        "import marlmerge",
        "import marlmerge.sim",
        "from marlmerge import ScenarioConfig, TrafficCore, ScriptedHighwayPolicy",
        "import marlmerge.config, marlmerge.sim, marlmerge.policies, marlmerge.evaluation.metrics",
    ],
)
def test_the_core_imports_no_rl_library(code):
    check = textwrap.dedent(f"""
        import sys
        {code}
        bad = sorted({{m.split(".")[0] for m in sys.modules}} & set({RL_LIBS!r}))
        print(bad)
        sys.exit(1 if bad else 0)
    """)
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("order", ["marlmerge first", "gymnasium first", "looked up first"])
def test_the_gymnasium_id_is_registered_whichever_is_imported_first(order):
    imports = ["import marlmerge", "import gymnasium"]
    if order == "gymnasium first":
        imports.reverse()
    if order == "looked up first":  # as torchrl asks whether Gymnasium is installed
        imports.insert(1, "import importlib.util; importlib.util.find_spec('gymnasium')")
    code = "; ".join([*imports, "print('marlmerge/RampMerge-v2' in gymnasium.registry)"])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "True", out.stdout + out.stderr


@pytest.mark.parametrize("old", sorted(marlmerge.MOVED))
def test_old_import_paths_warn_and_give_the_same_objects(old):
    import importlib
    import warnings

    sys.modules.pop(old, None)  # imported before: import it afresh
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mod = importlib.import_module(old)
    assert any(issubclass(w.category, DeprecationWarning) for w in caught), caught
    new = [importlib.import_module(t) for t in marlmerge.MOVED[old]]
    own = [
        (m, n)
        for m in new
        for n, v in vars(m).items()
        if not n.startswith("_")
        and (getattr(v, "__module__", None) == m.__name__ or n in getattr(m, "__all__", ()))
    ]
    assert own, "nothing to forward"
    for _, n in own:
        owner = next(x for x in new if hasattr(x, n))
        assert getattr(mod, n) is getattr(owner, n), n
    with pytest.raises(AttributeError):
        mod.no_such_name  # noqa: B018


def test_every_folder_of_the_package_ships_in_a_wheel():
    from marlmerge.config import read_toml

    listed = set(read_toml(ROOT.parent / "pyproject.toml")["tool"]["setuptools"]["packages"])
    folders = {m for m, p in _modules() if p.name == "__init__.py"}
    assert folders <= listed, f"packages missing from pyproject.toml: {sorted(folders - listed)}"


def test_every_kernel_file_is_hashed_for_the_compile_cache():
    # a kernel file left out of KERNEL_SOURCES would keep stale machine code of its inlined
    # functions in its callers' cache after an edit (the list also holds layout.py, whose
    # constants the kernels compile in)
    from marlmerge.sim.jit import KERNEL_SOURCES

    sim = Path(marlmerge.__file__).parent / "sim"
    with_kernels = {
        f"sim/{p.name}" for p in sim.glob("*.py") if "@kernel" in p.read_text(encoding="utf-8")
    }
    assert with_kernels <= set(KERNEL_SOURCES)
    assert "sim/layout.py" in KERNEL_SOURCES
