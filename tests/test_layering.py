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
