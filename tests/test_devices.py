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
