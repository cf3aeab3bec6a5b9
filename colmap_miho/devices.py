"""Which torch device a :class:`~.enums.Device` choice (or a torch device) means on this machine.

The one grammar of a device, and the one place where ``"auto"`` is resolved, for the filter's
torch kernels, the NCC refinement and the pipeline. torch is imported only when the function
runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .enums import Device
from .errors import InvalidInput

if TYPE_CHECKING:
    import torch


def resolve_device(device: Device | str | torch.device, inputs_on: torch.device | None = None) -> torch.device:
    """The torch device ``device`` means here.

    Args:
        device: ``"cpu"``; ``"cuda"``; or ``"auto"``: ``inputs_on`` when given, else CUDA
            when torch sees a CUDA device, else the CPU. Any other torch device string
            (``"cuda:1"``) or a ``torch.device`` object is that device, once torch can use it
            here (the filter's ``device`` takes them; the recipes' and the CLI's ``device``
            are :class:`~.enums.Device` values).
        inputs_on: the device the caller's inputs already live on (e.g. CUDA tensors it was
            handed), which ``"auto"`` keeps; None when the inputs do not pin one.

    Raises:
        ValueError: ``device`` is neither a :class:`~.enums.Device` value nor a torch device,
            or is a CUDA device that torch does not see (:class:`~.errors.InvalidInput`: bad
            input, exit 2).
    """
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
    """``device`` (a torch device string or object) as a ``torch.device``, checked to be one
    that torch can use here."""
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
