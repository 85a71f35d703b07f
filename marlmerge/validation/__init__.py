"""Validation of the simulator against SUMO: the same scenarios run in both, compared.

- `scenarios`: what is run (car-following cases, the mainline flow sweep) and how marlmerge runs
  it; `sumo`: the matching SUMO network and runs (needs the optional `[sumo]` extra);
- `measure`: the one set of traffic measurements both simulators' samples go through;
- `report`: tables, plots and the targets, written to `docs/validation/` by `marlmerge validate`.

Without SUMO installed, the committed reference outputs (`reference/`) stand in for SUMO's runs.
"""
