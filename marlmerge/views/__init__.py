"""The views of the core: each calls the same `TrafficCore` step and only reshapes its outputs.

- `pettingzoo_env`: PettingZoo's parallel and AEC envs (ramp and mainline vehicles as agents);
- `gym_env`: Gymnasium's single-agent env and native vector env; `sb3_env`: a Stable-Baselines3
  `VecEnv`; both over `single_ego`;
- `torchrl_env`: the batched torchrl env (the ego); `torchrl_groups`: with the highway group;
- `ramp_flow_env` (PettingZoo) and `ramp_flow_torchrl` (the `"ramp"` group): ramp flow, every
  merging vehicle an agent, over `ramp_agents` (which vehicle each agent holds);
- `render`: frames and the window; `registration`: the Gymnasium ids.
"""
