"""What device the torch benches ran on, for their JSON: a CUDA GPU when one is present (the
trainers' `--device auto` picks it), else the CPU. Not a bench itself (`all.sh` skips `_*.py`)."""

from __future__ import annotations


def gpu_info() -> dict[str, object]:
    """{"present": whether torch sees a CUDA device, "name": its name or None}."""
    import torch

    present = torch.cuda.is_available()
    return {"present": present, "name": torch.cuda.get_device_name(0) if present else None}
