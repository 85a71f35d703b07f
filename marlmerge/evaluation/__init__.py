"""Judging policies: trajectory metrics (`metrics`), greedy rollouts (`rollout`), policy specs
by name (`registry`), the robustness grid (`grid`) and its scale-out `backends`, videos
(`video`) and the scripted drive of `marlmerge simulate` (`simulate`)."""
