"""The AEC form of the PettingZoo ParallelEnvs (`parallel_to_aec`), with each agent's action
checked when the agent gives it.

PettingZoo's conversion buffers the actions of a cycle and hands them to the parallel `step`
once every agent has acted, so a bad action used to be reported only then, at another agent's
turn. Here it is refused at its own `step`, naming the agent and the value, before the buffer
takes it; the parallel `step` checks the whole cycle again as before.
"""

from __future__ import annotations

from typing import Any

from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec_wrapper
from pettingzoo.utils.wrappers import OrderEnforcingWrapper

from marlmerge.sim.action import as_actions


class CheckedAEC(parallel_to_aec_wrapper):
    """`parallel_to_aec_wrapper` whose `step` checks the selected live agent's action, sized by
    the parallel env's `action_sizes` (1 for an agent it does not list)."""

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if not (self.terminations.get(agent) or self.truncations.get(agent)):
            size = self.env.action_sizes.get(agent, 1)
            as_actions(action, (size,), f"action of {agent!r}", exact=True)
        super().step(action)


def checked_aec(par_env: ParallelEnv) -> AECEnv:
    """`par_env` as an AEC env with PettingZoo's order checks, each action checked when given."""
    return OrderEnforcingWrapper(CheckedAEC(par_env))
