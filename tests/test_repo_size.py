"""The tracked tree stays under 25 MB (:mod:`tools.tree_size`: a clone is what CI and a
newcomer download, and a lent GPU machine carries the checkout). Large outputs stay out of
git: a finished run keeps its JSON, ledger and the SHA-256 of its weights, not the weights
(``tools/run_weights.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tools.tree_size import too_big, tracked_sizes

REPO = Path(__file__).resolve().parents[1]


def test_the_tracked_tree_is_under_25_mb():
    sizes = tracked_sizes(REPO)
    if sizes is None:
        pytest.skip("not a git checkout")
    why = too_big(sizes)
    assert why is None, why


def test_the_message_names_the_biggest_files():
    sizes = [(9_000_000, "a.pt"), (20_000_000, "b.pt"), (10, "c.txt")]
    why = too_big(sizes, show=2)
    assert why.startswith("the tracked files come to 29.0 MB, over the 25 MB limit")
    assert why.splitlines()[1:] == ["   20.00 MB  b.pt", "    9.00 MB  a.pt"]
    assert too_big(sizes[:1]) is None
