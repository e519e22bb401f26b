"""A run's train section read and changed in either layout (sections, or the flat keys of
older code), ``--set`` applied to a preset, and the schedule that continues a run from
saved weights."""

from __future__ import annotations

import yaml


def _in_sections(train: dict) -> bool:
    """Whether a run's train section is in sections (``optimiser: {lr: ...}``, what the
    code reads since the sections came) or flat (``lr: ...``, what a run of older code
    reads): the layout the section itself has, sections when it shows neither."""
    from cnnps.stages.train import MOVED_KEYS, SECTIONS

    if any(isinstance(train.get(s), dict) for s in SECTIONS):
        return True
    return not any(k in MOVED_KEYS for k in train)


def train_value(train: dict, name: str, default=None):
    """The value of the train key ``name``, by its flat name (``lr``), in a section of
    either layout (``optimiser.lr`` or ``lr``).

    >>> train_value({"optimiser": {"lr": 0.001}}, "lr"), train_value({"lr": 0.001}, "lr")
    (0.001, 0.001)
    """
    from cnnps.stages.train import MOVED_KEYS

    if name in MOVED_KEYS and _in_sections(train):
        section, key = MOVED_KEYS[name].split(".")
        return (train.get(section) or {}).get(key, default)
    return train.get(name, default)


def with_train_values(train: dict, **values) -> dict:
    """The train section ``train`` with ``values`` (flat names) set in its own layout.

    >>> with_train_values({"optimiser": {"lr": 0.001}, "max_steps": 9}, lr=0.0001, max_steps=5)
    {'optimiser': {'lr': 0.0001}, 'max_steps': 5}
    """
    from cnnps.stages.train import MOVED_KEYS

    out, nested = dict(train), _in_sections(train)
    for name, value in values.items():
        if name in MOVED_KEYS and nested:
            section, key = MOVED_KEYS[name].split(".")
            out[section] = {**(out.get(section) or {}), key: value}
        else:
            out[name] = value
    return out


def set_value(params: dict, item: str) -> None:
    """Apply one ``KEY.PATH=VALUE`` to ``params`` in place (VALUE read as YAML: ``0``,
    ``[1200]``, ``null``; quote a word YAML reads as a boolean: ``eval.sparse_fill="off"``);
    a section on the path that is missing is created.

    >>> p = {"train": {"max_steps": 9}}; set_value(p, "train.optimiser.lr_milestones=[1200]"); p
    {'train': {'max_steps': 9, 'optimiser': {'lr_milestones': [1200]}}}
    """
    key, sep, text = item.partition("=")
    if not sep or not key or any(not part for part in key.split(".")):
        raise SystemExit(f"--set {item!r}: expected KEY.PATH=VALUE")
    *path, last = key.split(".")
    node = params
    for part in path:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise SystemExit(f"--set {item!r}: {part!r} is not a section")
    node[last] = yaml.safe_load(text)


def continue_schedule(train: dict, step: int, init: str) -> dict:
    """The train section that continues a run of ``train`` from the weights of its step
    ``step`` (``init``) as a new run: ``max_steps`` the steps left, ``lr_milestones`` those
    ahead (shifted by ``step``), ``lr`` the rate reached at ``step``; in the section's own
    layout (the run's code reads it).

    >>> continue_schedule({"max_steps": 100, "optimiser": {"lr": 1e-3, "lr_milestones": [50, 80], "lr_gamma": 0.1}},
    ...                   60, "w.pt")
    {'max_steps': 40, 'optimiser': {'lr': 0.0001, 'lr_milestones': [20], 'lr_gamma': 0.1}, 'init': 'w.pt'}
    """
    total = int(train.get("max_steps") or 0)
    if not 0 <= step < total:
        raise ValueError(f"step {step} is not inside the run's {total} steps")
    ms = [int(m) for m in train_value(train, "lr_milestones") or []]
    gamma = float(train_value(train, "lr_gamma", 0.1))
    passed = sum(step >= m for m in ms)
    return with_train_values(train, max_steps=total - step, lr=float(train_value(train, "lr")) * gamma**passed,
                             lr_milestones=[m - step for m in ms if m > step], init=init)
