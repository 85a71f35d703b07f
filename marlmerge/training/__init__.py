"""How a learner is trained: the one loop and its factories (`loop`), what a run writes while it
runs (`logs`), resuming from a checkpoint (`checkpoint`), the two kinds of run built on them,
`train` (the ego against scripted traffic) and `cotrain` (learned highway agents and the ego, in
phases), many seeds at once (`sweep`) and a run's figures (`plots`). The run schemas are in
`marlmerge.config.training` and `marlmerge.config.cotraining`."""
