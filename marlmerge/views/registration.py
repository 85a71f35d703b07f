"""marlmerge's Gymnasium ids, registered by name: the env modules are imported only when
`gymnasium.make` builds an env. `import marlmerge` registers them as soon as Gymnasium is
imported, before or after marlmerge."""

from __future__ import annotations

ENV_ID = "marlmerge/RampMerge-v2"
"""The ramp vehicle as a single agent (`marlmerge.views.gym_env`)."""


def register() -> None:
    """Register `marlmerge/RampMerge-v2` (env and native vector env) with Gymnasium."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(
            id=ENV_ID,
            entry_point="marlmerge.views.gym_env:RampMergeEnv",
            vector_entry_point="marlmerge.views.gym_env:RampMergeVectorEnv",
        )
