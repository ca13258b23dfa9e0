"""Where the torch paths run (body skinning, the collision energy and its optimiser,
pytorch-kinematics FK): `cpu`, `cuda`, or `auto` (CUDA when a GPU is present).

Why a setting and not "always the GPU when there is one": CUDA's float rounding differs from
the CPU's, so a GPU run of the same input gives other contents (and content hashes), and its
atomic adds (`index_add`, the backward of gathers) are not bit-reproducible run to run, while
a seeded CPU run is (the project's determinism promise). The
setting is part of the step's configuration, hence of its content key: CUDA results are stored
under their own keys, never mixed with CPU ones, and `cpu` (the default) gives the results the
tests and the published tables were measured with. `auto` is keyed as written, so a store
shared by CPU-only and GPU machines should name `cpu` or `cuda` explicitly.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

import torch

from embody.errors import ConfigError

DeviceSpec = Literal["cpu", "cuda", "auto"]


def torch_device(spec: str, key: str = "device") -> torch.device:
    """The torch device for a setting; `cuda` without a usable GPU is a config error (`key`
    names the setting), `auto` falls back to the CPU."""
    if spec == "cpu":
        return torch.device("cpu")
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if spec == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(key, "'cuda' asked for, but torch sees no CUDA device "
                                   f"(torch {torch.__version__}); use 'auto' or 'cpu'")
        return torch.device("cuda")
    raise ConfigError(key, f"unknown device {spec!r}; expected cpu, cuda or auto")


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Torch intra-op threads at `n` inside the block, then as before (also when it raises).
    The setting is torch's process-wide one: the collision optimiser, the metrics step and a
    run with several workers (`flows.threads`) each hold it for their duration."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
