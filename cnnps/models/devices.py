"""Which torch device to run on: the one rule every command and stage uses."""

from __future__ import annotations

import torch

from cnnps.infra.errors import CnnpsError


def resolve_device(name: str | torch.device | None = "auto") -> torch.device:
    """'auto' (or None) -> CUDA when available, else CPU; 'cpu', 'cuda', 'cuda:1' as named.

    Asking for CUDA where torch has none raises CnnpsError with a clear message.
    """
    if isinstance(name, torch.device):
        name = str(name)
    name = "auto" if name is None else str(name).strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise CnnpsError(f"unknown device {name!r}: use auto, cpu or cuda[:N]") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise CnnpsError(f"device {name!r} requested but {why}; use --device cpu (or auto)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise CnnpsError(f"device {name!r} requested but only {torch.cuda.device_count()} CUDA GPU(s) exist")
    elif device.type != "cpu":
        raise CnnpsError(f"unsupported device {name!r}: use auto, cpu or cuda[:N]")
    return device
