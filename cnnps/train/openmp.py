"""OpenMP's wait policy, chosen before torch loads (this module does not import torch)."""

from __future__ import annotations

import os
import sys


def prefer_passive_openmp() -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless the user chose a policy; True if it took effect.

    OpenMP reads the policy once, when torch loads its runtime, so this only works before
    the first ``import torch`` of the process (``cnnps run-stage train`` imports torch
    only inside :func:`cnnps.stages.train.run`, after calling this). Idle OpenMP threads
    then sleep instead of spinning: on a machine shared with another busy process, the
    default (spinning) policy makes each training step wait for a descheduled thread; on
    an idle machine sleeping costs a wake-up per parallel region
    (docs/performance.md#training-settings).
    """
    if "OMP_WAIT_POLICY" in os.environ or "torch" in sys.modules:
        return False
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True
