"""Benchmark rules: how a published benchmark treats some of its objects, applied only
where a caller scores against that benchmark.

A capture folder is read the same way whatever its name; a benchmark's rule is a named,
explicit drop list that the callers who reproduce the benchmark's numbers pass on (the
eval stage's real captures and ``cnnps score``; ``cnnps predict --drop 0-19`` by hand).
:data:`DILIGENT_RULES` holds DiLiGenT's: the first 20 images of BEAR are corrupted and
every published result leaves them out.

Sparse subsets of a capture (:func:`subset_drop`) are drawn by one seeded rule from the
images a benchmark rule leaves.

Example::

    drop = benchmark_drop(folder, DILIGENT_RULES)   # [0, ..., 19] for .../bearPNG, [] otherwise
    load_capture(folder, drop=drop)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.io.capture.files import read_filenames

MIN_IMAGES = 3  # photometric stereo needs three lights


@dataclass(frozen=True)
class BenchmarkRule:
    """The images (0-based, filenames.txt order) a benchmark leaves out of one of its
    objects, and why (for notes and reports)."""

    drop: tuple[int, ...]
    reason: str

    def indices(self, m: int) -> list[int]:
        """The rule's indices below ``m`` (a capture of m images), sorted."""
        return sorted(i for i in set(self.drop) if 0 <= i < m)


# DiLiGenT's rules, by capture folder name
DILIGENT_RULES: dict[str, BenchmarkRule] = {
    "bearPNG": BenchmarkRule(drop=tuple(range(20)),
                             reason="DiLiGenT: BEAR's first 20 images are corrupted; published results leave them out"),
}


def benchmark_drop(path: str | Path, rules: Mapping[str, BenchmarkRule]) -> list[int]:
    """The image indices ``rules`` leave out of the capture folder ``path``, looked up by
    the folder's name (``[]`` for a folder no rule names). Reads ``filenames.txt`` only for
    a named folder (the rule's indices below its image count).

    Example: ``benchmark_drop("data/diligent/bearPNG", DILIGENT_RULES)`` -> [0, 1, ..., 19].
    """
    root = Path(path)
    rule = rules.get(root.name)
    if rule is None:
        return []
    return rule.indices(len(read_filenames(root)))


def subset_drop(path: str | Path, n: int, seed: int = 0, exclude: Iterable[int] = ()) -> list[int]:
    """Indices (0-based, filenames.txt order) to drop so that ``n`` images of a capture
    remain, drawn by one seeded rule: the same for every capture, so held-back objects get
    their sparse subsets the same way.

    The candidates are the m images not in ``exclude`` (a benchmark's rule:
    :func:`benchmark_drop`); of those, ``n`` are drawn uniformly without replacement by
    ``numpy.random.default_rng([seed, m, n]).choice(m, n, replace=False)``. The result
    holds ``exclude`` too; pass it as ``drop`` to :func:`cnnps.io.capture.scan_capture` /
    :func:`cnnps.io.capture.load_capture`. A ConfigError unless ``MIN_IMAGES <= n <= m``.

    Example: ``load_capture(d, drop=subset_drop(d, 10))``: 10 of ballPNG's 96 images;
    ``subset_drop(bear, 10, exclude=benchmark_drop(bear, DILIGENT_RULES))``: 10 of BEAR's 76.
    """
    root = Path(path)
    names = read_filenames(root)
    excluded = set(int(i) for i in exclude)
    usable = [i for i in range(len(names)) if i not in excluded]
    m = len(usable)
    if not MIN_IMAGES <= n <= m:
        raise ConfigError(f"{root}: cannot keep {n} images of {m} (need {MIN_IMAGES} <= n <= {m})")
    keep = {usable[int(i)] for i in np.random.default_rng([seed, m, n]).choice(m, n, replace=False)}
    return [i for i in range(len(names)) if i not in keep]
