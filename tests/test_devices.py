"""The one resolver of the ``device`` choice."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from colmap_miho.devices import resolve_device  # noqa: E402


def test_cpu_and_auto():
    assert resolve_device("cpu") == torch.device("cpu")
    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == want
    # "auto" keeps the device the inputs already live on
    assert resolve_device("auto", torch.device("cuda", 1)) == torch.device("cuda", 1)
    assert resolve_device("cpu", torch.device("cuda", 1)) == torch.device("cpu")


def test_bad_values_raise():
    with pytest.raises(ValueError, match="device"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")


def test_torch_devices_pass_through_once_usable():
    """The filter's ``device`` also takes a torch device (string or object): the same grammar."""
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("cpu:0") == torch.device("cpu", 0)
    for bad in ("cuda:x", "torch-cpu", 3):
        with pytest.raises(ValueError, match="device") as info:
            resolve_device(bad)
        assert "\n" not in str(info.value)
    if not torch.cuda.is_available():
        for cuda in ("cuda:1", torch.device("cuda", 0)):
            with pytest.raises(ValueError, match="no CUDA device"):
                resolve_device(cuda)
