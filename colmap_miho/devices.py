"""Which torch device a :class:`~.enums.Device` choice means on this machine.

The one place where ``"auto"`` is resolved, for the filter's torch kernels, the NCC
refinement and the pipeline. torch is imported only when the function runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .enums import Device
from .errors import InvalidInput

if TYPE_CHECKING:
    import torch


def resolve_device(device: Device | str, inputs_on: torch.device | None = None) -> torch.device:
    """The torch device ``device`` means here.

    Args:
        device: ``"cpu"``; ``"cuda"``; or ``"auto"``: ``inputs_on`` when given, else CUDA
            when torch sees a CUDA device, else the CPU.
        inputs_on: the device the caller's inputs already live on (e.g. CUDA tensors it was
            handed), which ``"auto"`` keeps; None when the inputs do not pin one.

    Raises:
        ValueError: ``device`` is not a :class:`~.enums.Device` value, or is ``"cuda"`` and
            torch sees no CUDA device (:class:`~.errors.InvalidInput`: bad input, exit 2).
    """
    choice = Device.parse(device, "device")
    import torch

    if choice is Device.CUDA:
        if not torch.cuda.is_available():
            raise InvalidInput("device='cuda' but torch sees no CUDA device")
        return torch.device("cuda")
    if choice is Device.AUTO:
        if inputs_on is not None:
            return inputs_on
        if torch.cuda.is_available():
            return torch.device("cuda")
    return torch.device("cpu")
