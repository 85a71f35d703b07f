"""How a learner is trained: the run config schema (`config`), presets (`presets`), the one loop
and its factories (`loop`) and what a run writes while it runs (`logs`). The two kinds of run
built on them are `marlmerge.train` (the ego against scripted traffic) and `marlmerge.cotrain`
(learned highway agents and the ego, in phases)."""
