"""Which torch device a :class:`~.enums.Device` choice means here: the one place ``"auto"`` is
resolved. torch is imported only when called."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .enums import Device
from .errors import InvalidInput

if TYPE_CHECKING:
    import torch


def resolve_device(device: Device | str | torch.device, inputs_on: torch.device | None = None) -> torch.device:
    """The torch device ``device`` means here: ``"auto"`` keeps ``inputs_on``, else CUDA when torch
    sees one, else the CPU. InvalidInput for an unknown device or CUDA that torch does not see."""
    import torch

    if isinstance(device, torch.device) or (isinstance(device, str)
                                            and str(device).lower() not in Device.values()):
        return _usable(device)
    choice = Device.parse(device, "device")

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


def _usable(device: str | torch.device) -> torch.device:
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise InvalidInput(f"device must be 'cpu', 'auto', 'cuda[:N]' or another torch device, "
                           f"got {device!r}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise InvalidInput(f"device {str(dev)!r} requested but torch sees no CUDA device")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InvalidInput(f"device {str(dev)!r} requested but torch sees "
                               f"{torch.cuda.device_count()} CUDA device(s)")
    return dev
