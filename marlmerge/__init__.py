"""marlmerge: multi-agent highway on-ramp merging.

A batched traffic simulator compiled with Numba (`marlmerge.sim`), a PettingZoo ParallelEnv over
it (`marlmerge.parallel_env`), Gymnasium, SB3 and torchrl views (`marlmerge.views`), and learners
built on torchrl (`marlmerge.learners`). The folders are the layers, lowest first: `config`,
`sim`, `io` and `policies`, `views`, `learners`, `evaluation`, `training`, then `cli`.

Importing the package imports nothing heavy: the names below load their module on first use, so
`import marlmerge.sim` brings in neither torch, Gymnasium nor PettingZoo. The Gymnasium id
`marlmerge/RampMerge-v2` is registered as soon as Gymnasium is imported, before or after this.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType
from typing import Any

__version__ = "0.5.0"

_LAZY = {
    "ScenarioConfig": "marlmerge.config",
    "load_scenario": "marlmerge.config",
    "Profile": "marlmerge.sim",
    "TrafficCore": "marlmerge.sim",
    "ScriptedHighwayPolicy": "marlmerge.policies",
    "ENV_ID": "marlmerge.views.registration",
    "register": "marlmerge.views.registration",
    "RampMergeEnv": "marlmerge.views.gym_env",
    "RampMergeVectorEnv": "marlmerge.views.gym_env",
    "ENV_NAME": "marlmerge.views.pettingzoo_env",
    "RampMergeParallelEnv": "marlmerge.views.pettingzoo_env",
    "env": "marlmerge.views.pettingzoo_env",
    "parallel_env": "marlmerge.views.pettingzoo_env",
    "ramp_flow_parallel_env": "marlmerge.views.ramp_flow_env",
    "ramp_flow_env": "marlmerge.views.ramp_flow_env",
    "raw_env": "marlmerge.views.pettingzoo_env",
}
"""Public name -> the module it is loaded from on first use."""

__all__ = sorted(_LAZY)

MOVED = {
    "marlmerge.files": ("marlmerge.io.files",),
    "marlmerge.policy_file": ("marlmerge.io.policy_file",),
    "marlmerge.presets": ("marlmerge.config.presets",),
    "marlmerge.spec": ("marlmerge.sim",),
    "marlmerge.spec.observation": ("marlmerge.sim.observation",),
    "marlmerge.spec.reward": ("marlmerge.sim.reward",),
    "marlmerge.spec.action": ("marlmerge.sim.action",),
    "marlmerge.baselines": ("marlmerge.policies.gap_acceptance",),
    "marlmerge.batched_env": ("marlmerge.views.torchrl_env",),
    "marlmerge.marl_env": ("marlmerge.views.torchrl_groups",),
    "marlmerge.pettingzoo_env": ("marlmerge.views.pettingzoo_env", "marlmerge.config.presets"),
    "marlmerge.gym_env": ("marlmerge.views.gym_env", "marlmerge.views.single_ego"),
    "marlmerge.sb3_env": ("marlmerge.views.sb3_env",),
    "marlmerge.render": ("marlmerge.views.render",),
    "marlmerge.learned_highway": ("marlmerge.learners.highway",),
    "marlmerge.learners.baselines_rl": (
        "marlmerge.learners.loading",
        "marlmerge.learners.dqn",
        "marlmerge.learners.td3",
        "marlmerge.learners.common",
    ),
    "marlmerge.metrics": ("marlmerge.evaluation.metrics",),
    "marlmerge.evaluate": ("marlmerge.evaluation.rollout",),
    "marlmerge.registry": ("marlmerge.evaluation.registry",),
    "marlmerge.grid": ("marlmerge.evaluation.grid",),
    "marlmerge.video": ("marlmerge.evaluation.video",),
    "marlmerge.backends": ("marlmerge.evaluation.backends",),
    "marlmerge.train": ("marlmerge.training.train", "marlmerge.config.presets"),
    "marlmerge.cotrain": (
        "marlmerge.training.cotrain",
        "marlmerge.config.cotraining",
        "marlmerge.config.presets",
    ),
    "marlmerge.sweep": ("marlmerge.training.sweep",),
    "marlmerge.plots": ("marlmerge.training.plots",),
    "marlmerge.training.config": ("marlmerge.config.training",),
    "marlmerge.training.presets": ("marlmerge.config.presets", "marlmerge.training.checkpoint"),
}
"""Import paths of version 0.3 -> the modules that hold their names now. They keep working for
one release: importing one warns (`DeprecationWarning`) and reads its names from these modules."""


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'marlmerge' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


class _MovedModule(importlib.abc.Loader):
    """Loads an old import path as a module that reads its names from the new modules."""

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        return ModuleType(spec.name)

    def exec_module(self, module: ModuleType) -> None:
        targets = MOVED[module.__name__]
        warnings.warn(
            f"{module.__name__} is now {' and '.join(targets)}; the old path goes in the next "
            "release",
            DeprecationWarning,
            stacklevel=2,
        )
        if module.__name__ == "marlmerge.spec":
            module.__path__ = []  # a package: its old submodules are moved too

        def forward(name: str) -> Any:
            for target in targets:
                new = importlib.import_module(target)
                if hasattr(new, name):
                    return getattr(new, name)
            raise AttributeError(f"module {module.__name__!r} has no attribute {name!r}")

        module.__getattr__ = forward  # type: ignore[method-assign]


class _MovedFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname in MOVED:
            return importlib.machinery.ModuleSpec(fullname, _MovedModule())
        return None


class _RegisterWithGymnasium(importlib.abc.MetaPathFinder):
    """Registers the Gymnasium ids right after Gymnasium itself is imported (a look-up alone,
    as `importlib.util.find_spec("gymnasium")`, leaves it waiting for the import)."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != "gymnasium":
            return None
        later = sys.meta_path[sys.meta_path.index(self) + 1 :]
        for finder in later:
            spec = getattr(finder, "find_spec", lambda *a: None)(fullname, path, target)
            if spec is not None:
                if spec.loader is not None:
                    spec.loader = _ThenRegister(spec.loader)
                return spec
        return None


class _ThenRegister(importlib.abc.Loader):
    def __init__(self, loader: Any) -> None:
        self.loader = loader

    def __getattr__(self, name: str) -> Any:  # resource readers and the like
        return getattr(self.loader, name)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> Any:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self.loader.exec_module(module)
        sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _RegisterWithGymnasium)]
        module.__loader__ = self.loader
        if module.__spec__ is not None:
            module.__spec__.loader = self.loader
        from marlmerge.views.registration import register

        register()


if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedFinder())
if "gymnasium" in sys.modules:
    from marlmerge.views.registration import register as _register

    _register()
elif not any(isinstance(f, _RegisterWithGymnasium) for f in sys.meta_path):
    sys.meta_path.insert(0, _RegisterWithGymnasium())
