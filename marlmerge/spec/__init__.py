"""What an agent observes and is rewarded for: the one definition of each observation layout and
reward term. The simulator's kernels compute them (`marlmerge.sim`); every view reads them."""
