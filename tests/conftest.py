"""Set-up shared by every test."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _fresh_compile_cache():
    """Each test compiles as a fresh process would. torch.compile keeps one cache per code
    object with room for 8 versions, and every compiled `functools.partial` (an update chunk
    with its constants bound) goes through the same wrapper: a process running many compiling
    tests in a row would otherwise fail at the ninth version (fullgraph=True)."""
    yield
    torch._dynamo.reset()
