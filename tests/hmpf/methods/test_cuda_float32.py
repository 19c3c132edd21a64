"""Backbones on a CUDA device run in full float32 (TF32 off), so an index built on a GPU and
queried on a CPU agree. The flags are process-wide torch settings, readable and settable
without a GPU; the parity itself is measured on a GPU by ``bench/cuda_check.py``."""

from __future__ import annotations

import pytest

from hmpf.backbones.base import full_float32_on

torch = pytest.importorskip("torch")


@pytest.fixture
def tf32_flags():
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.mark.parametrize("device", ["cuda", "cuda:1"])
def test_cuda_device_turns_tf32_off(tf32_flags: None, device: str) -> None:
    torch.backends.cudnn.allow_tf32 = True  # PyTorch's default for convolutions
    torch.backends.cuda.matmul.allow_tf32 = True
    full_float32_on(device)
    assert torch.backends.cudnn.allow_tf32 is False
    assert torch.backends.cuda.matmul.allow_tf32 is False


def test_cpu_device_changes_nothing(tf32_flags: None) -> None:
    torch.backends.cudnn.allow_tf32 = True
    torch.backends.cuda.matmul.allow_tf32 = True
    full_float32_on("cpu")
    assert torch.backends.cudnn.allow_tf32 is True
    assert torch.backends.cuda.matmul.allow_tf32 is True
