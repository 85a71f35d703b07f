"""`own_code`: a process may compile any number of updaters with distinct settings."""

import functools
from dataclasses import dataclass

import pytest
import torch
from test_quadq import _filled_replay, _gen, _net
from torch._dynamo.exc import FailOnRecompileLimitHit

import marlmerge.learners.quadq_fast as qf
from marlmerge.learners import quadq as qq
from marlmerge.learners.compiling import own_code


@dataclass(frozen=True)
class _Spec:
    c: float


def _scaled(spec: _Spec, x: torch.Tensor) -> torch.Tensor:
    return x * spec.c + 1.0


def _compile(fn):  # as the updaters compile: constants of the spec baked into the graph
    return torch.compile(fn, fullgraph=True, dynamic=False)


def test_own_code_calls_the_function_and_keeps_its_name():
    f = own_code(functools.partial(_scaled, _Spec(3.0)))
    assert f(torch.tensor(2.0)).item() == 7.0
    assert f.__name__ == "_scaled"
    assert f.__code__ is not own_code(_scaled).__code__


def test_each_copy_has_its_own_recompile_budget():
    """With the limit at 2, three partials of distinct specs through one shared code (torch's
    wrapper of a partial) fail with fullgraph; through `own_code` each compiles."""
    x = torch.ones(3)
    try:
        with torch._dynamo.config.patch(recompile_limit=2):
            for c in (1.0, 2.0, 3.0):
                f = _compile(own_code(functools.partial(_scaled, _Spec(c))))
                assert torch.equal(f(x), x * c + 1.0)
            with pytest.raises(FailOnRecompileLimitHit):
                for c in (1.0, 2.0, 3.0):
                    _compile(functools.partial(_scaled, _Spec(c)))(x)
    finally:
        torch._dynamo.reset()  # the shared wrapper's versions stay with this test


def test_compiled_updaters_with_distinct_settings_in_one_process():
    """Updaters are compiled with fullgraph: past the limit, a shared code would raise."""
    with torch._dynamo.config.patch(recompile_limit=1):
        for gamma in (0.9, 0.95):
            loss = qq.QuadraticQLoss(_net(), gamma=gamma)
            fast = qf.FastQuadQUpdater(
                loss,
                _filled_replay(200, _gen(13)),
                generator=_gen(14),
                updates_per_call=2,
                target_update_period=10,
                compile=True,
            )
            assert torch.isfinite(fast.step()).all()
