"""``train.phases``: one training run as a sequence of phases, declared in params.yaml.

Each phase is a run of the train stage of its own ``steps``, from the weights the phase
before it ended with (the first: ``train.init``, or random weights), with some of the
train settings changed (``set``: dotted keys of ``train:``, e.g. ``optimiser.lr``,
``pixelwise.share``, ``pixelwise.effects``, ``synthesis.cone_max_deg``; whatever is not set
is the base ``train:`` section's). A phase may instead start from a weighted mean of
earlier phases' final weights (``start``: {phase: weight}, weights summing to 1, WiSE-FT
style); a phase of 0 steps is such a mean and nothing more (it is validated and becomes
the phase's weights). Within a phase, ``optimiser.average_from`` averages its checkpoints
as in any run (SWA). Adam starts afresh in every phase, as the runs of a hand-made chain
did::

    train:
      optimiser: {lr: 0.001}
      phases:
        - {name: narrow, steps: 8000, set: {synthesis.cone_max_deg: 50}}
        - {name: wide, steps: 8000, set: {optimiser.lr: 0.0003, optimiser.average_from: 4000}}
        - {name: blend, steps: 0, start: {narrow: 0.3, wide: 0.7}}

The phases, their settings and the base section are all in ``train:``, so DVC sees every
change; how they run (and resume) is :mod:`cnnps.train.phases`. This module loads no torch.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from cnnps.infra.errors import ConfigError

# what a phase cannot set: its length and its start are its own, and phases do not nest
PHASE_OWNS = ("epochs", "max_steps", "init", "phases")
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")  # a phase's name: also its folder's


@dataclass(frozen=True)
class PhaseParams:
    """One entry of ``train.phases`` (the module docstring): ``name`` (letters, digits,
    ``_ . -``; unique), ``steps`` (>= 0; 0 needs ``start``), ``set`` ({dotted key of
    ``train:``: value}), ``start`` ({earlier phase: weight}, summing to 1; empty: the
    previous phase's weights)."""

    name: str
    steps: int
    set: Mapping[str, Any] = field(default_factory=dict)
    start: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        where = f"train.phases: {self.name!r}"
        if not isinstance(self.name, str) or not NAME.match(self.name):
            raise ConfigError(f"train.phases: a phase's name must be letters, digits, '_', '.' or '-', "
                              f"got {self.name!r}")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 0:
            raise ConfigError(f"{where}: steps must be a whole number >= 0, got {self.steps!r}")
        if not isinstance(self.set, Mapping) or not isinstance(self.start, Mapping):
            raise ConfigError(f"{where}: set and start must be mappings")
        for key in self.set:
            if not isinstance(key, str) or key.split(".")[0] in PHASE_OWNS:
                raise ConfigError(f"{where}: set cannot hold {key!r} (a phase's steps and start are its own: "
                                  f"{', '.join(PHASE_OWNS)})")
        weights = list(self.start.values())
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in weights):
            raise ConfigError(f"{where}: start weights must be numbers, got {dict(self.start)}")
        if weights and abs(sum(weights) - 1.0) > 1e-9:
            raise ConfigError(f"{where}: start weights must sum to 1, got {sum(weights):g}")
        if self.steps == 0 and not weights:
            raise ConfigError(f"{where}: a phase of 0 steps needs start (a weighted mean of earlier phases)")
        object.__setattr__(self, "set", dict(self.set))
        object.__setattr__(self, "start", {k: float(v) for k, v in self.start.items()})

    def record(self) -> dict:
        """As plain data (what a run key and ``metrics.json`` hold)."""
        return {"name": self.name, "steps": self.steps, "set": dict(self.set), "start": dict(self.start)}


def check_phases(phases) -> tuple[PhaseParams, ...]:
    """``train.phases`` as PhaseParams (each a PhaseParams or a mapping of its keys):
    names unique, each ``start`` naming earlier phases only."""
    if phases is None:
        return ()
    if isinstance(phases, (str, Mapping)) or not hasattr(phases, "__iter__"):
        raise ConfigError(f"train.phases must be a list of phases, got {phases!r}")
    out: list[PhaseParams] = []
    for i, ph in enumerate(phases):
        if not isinstance(ph, PhaseParams):
            if not isinstance(ph, Mapping):
                raise ConfigError(f"train.phases[{i}] must be a mapping (name, steps, set, start), got {ph!r}")
            unknown = [k for k in ph if k not in ("name", "steps", "set", "start")]
            if unknown or "name" not in ph or "steps" not in ph:
                raise ConfigError(f"train.phases[{i}]: keys are name, steps (both needed), set, start; "
                                  f"got {sorted(ph)}")
            ph = PhaseParams(**ph)
        earlier = [p.name for p in out]
        if ph.name in earlier:
            raise ConfigError(f"train.phases: two phases are named {ph.name!r}")
        missing = [k for k in ph.start if k not in earlier]
        if missing:
            raise ConfigError(f"train.phases: {ph.name!r} starts from {missing[0]!r}, which is not an earlier phase")
        out.append(ph)
    return tuple(out)


def phase_values(base: dict, phase: PhaseParams, sections: Mapping[str, type]) -> dict:
    """The keyword arguments of the phase's ``Params``: ``base`` (the base section's
    fields, sections as their dataclasses) with ``phase.set`` applied; an unknown key is a
    ConfigError naming the phase and the known keys."""
    import dataclasses

    values = dict(base)
    changed: dict[str, dict] = {}
    for key, value in phase.set.items():
        head, _, rest = key.partition(".")
        if rest:
            if head not in sections or "." in rest:
                raise ConfigError(f"train.phases: {phase.name!r} sets {key!r}: no such key "
                                  f"(sections: {', '.join(sections)})")
            changed.setdefault(head, {})[rest] = value
        elif head in sections or head not in values:
            raise ConfigError(f"train.phases: {phase.name!r} sets {key!r}: not a key of train "
                              f"(a section's keys are set one by one, e.g. optimiser.lr)")
        else:
            values[head] = value
    for section, updates in changed.items():
        known = [f.name for f in dataclasses.fields(sections[section])]
        unknown = [k for k in updates if k not in known]
        if unknown:
            raise ConfigError(f"train.phases: {phase.name!r} sets {section}.{unknown[0]}: unknown key; "
                              f"known keys of train.{section}: {', '.join(known)}")
        values[section] = dataclasses.replace(values[section], **updates)
    return values
