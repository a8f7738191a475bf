"""Which torch device the field trains and renders on.

CPU is the default everywhere: it is the path the project is tuned and tested on.  CUDA is optional and
runs the same code (the marcher, occupancy grid and decoders are plain torch; the K-nearest-vertex
query stays on the CPU's KD-tree and its results are moved to the GPU).  Random draws are made with CPU
generators, so a seed selects the same rays, cells and vertices on either device.
"""
from __future__ import annotations

import torch

from .errors import NeuMeshError

DEVICE_CHOICES = ("cpu", "cuda", "auto")


def draw_device(generator: torch.Generator | None, like: torch.Tensor) -> torch.device:
    """Where random draws for tensors on ``like``'s device are made: on the generator's own device when
    one is given (a CPU generator then draws the same numbers for a CPU or a CUDA field); move the
    result to ``like.device`` afterwards."""
    return like.device if generator is None else generator.device


def resolve_device(name: str | torch.device | None = "cpu") -> torch.device:
    """``"cpu"``, ``"cuda"`` / ``"cuda:N"``, or ``"auto"`` (CUDA when torch sees a GPU, else CPU).

    Raises NeuMeshError, saying what to do, when CUDA is asked for and torch cannot use it.
    """
    if isinstance(name, torch.device):
        name = str(name)
    name = (name or "cpu").strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"a CUDA {torch.version.cuda} build"
            raise NeuMeshError(
                f"device {name!r} asked for, but torch {torch.__version__} ({build}) sees no CUDA GPU. "
                "Use --device cpu (the default) or auto, or install a CUDA build of torch on a machine "
                "with an NVIDIA GPU and driver.")
        dev = torch.device(name)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise NeuMeshError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s) are "
                               "visible; use cuda:0 .. cuda:N-1")
        return dev
    raise NeuMeshError(f"unknown device {name!r}; use one of cpu, cuda, cuda:N, auto")
