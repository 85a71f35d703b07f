"""The simulation core imports no RL library."""

import subprocess
import sys
import textwrap

RL_LIBS = ("torch", "torchrl", "tensordict", "pettingzoo", "gymnasium")


def test_core_imports_no_rl_library():
    # Importing `marlmerge` runs its __init__, which pulls in the PettingZoo view on purpose; so the
    # package is stubbed and only the core modules are loaded, to see what they need themselves.
    code = textwrap.dedent(f"""
        import importlib.util, os, sys, types
        pkg = types.ModuleType("marlmerge")
        pkg.__path__ = [os.path.dirname(importlib.util.find_spec("marlmerge").origin)]
        sys.modules["marlmerge"] = pkg
        import marlmerge.config, marlmerge.sim, marlmerge.spec.observation, marlmerge.spec.reward
        import marlmerge.metrics, marlmerge.baselines, marlmerge.policies
        bad = [m for m in sys.modules if m.split(".")[0] in {RL_LIBS!r}]
        print(bad)
        sys.exit(1 if bad else 0)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


LAYERS = (
    ("config", "files", "presets"),
    ("sim", "spec", "metrics", "baselines", "policies", "plots"),
    ("batched_env", "marl_env", "pettingzoo_env", "gym_env", "sb3_env", "render", "evaluate"),
    ("learners", "policy_file", "learned_highway", "training", "train", "cotrain", "registry"),
    ("grid", "video", "sweep", "backends", "validation"),
    ("cli", "__main__"),
)
"""The package's layers, lowest first: config <- core <- views (and greedy evaluation) <-
learners and training <- evaluation tools <- CLI. A module imports only from its own layer or
below, at the top of a file or inside a function alike."""


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "marlmerge" or len(parts) < 2:
        return None
    found = [i for i, names in enumerate(LAYERS) if parts[1] in names]
    assert found, f"{module} belongs to no layer: add it to LAYERS"
    return found[0]


def _imports(tree):
    import ast

    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module != "marlmerge":
            yield node.lineno, node.module
        elif isinstance(node, ast.ImportFrom) and node.module == "marlmerge":
            yield from ((node.lineno, f"marlmerge.{a.name}") for a in node.names)
        elif isinstance(node, ast.Import):
            yield from ((node.lineno, a.name) for a in node.names)


def test_imports_point_one_way():
    import ast
    from pathlib import Path

    import marlmerge

    root = Path(marlmerge.__file__).parent
    upward = []
    for path in sorted(root.rglob("*.py")):
        module = ".".join(("marlmerge", *path.relative_to(root).with_suffix("").parts))
        if module == "marlmerge.__init__":
            continue  # the package's front door re-exports the views
        own = _layer(module)
        for line, target in _imports(ast.parse(path.read_text())):
            layer = _layer(target)
            if layer is not None and layer > own:
                upward.append(f"{module}:{line} imports {target}")
    assert not upward, "imports against the layers:\n" + "\n".join(upward)
