"""Sparse-light subsets of a capture: which n of its m images, by one seeded rule.

    .venv/bin/python tools/image_subsets.py CAPTURE_DIR [--n 20 10 6] [--seed 0]

The rule (the same for every capture, so held-back objects get subsets drawn the same
way; :func:`cnnps.io.capture.subset_drop`, which the eval stage's ``real_subsets`` uses):
the images are those of ``filenames.txt`` after DiLiGenT's benchmark rule
(:data:`cnnps.io.capture.DILIGENT_RULES`: ``bearPNG`` loses its first 20); n of those m are drawn uniformly without replacement by
``numpy.random.default_rng([seed, m, n]).choice(m, n, replace=False)`` and kept in
filenames.txt order. Writes ``benchmarks/image_lists/<capture>-<n>.txt``, one image name
a line. ``python -m benchmarks.predict.model_accuracy --subsets`` predicts with each list
(the other images dropped; :mod:`benchmarks.subsets` reads them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LISTS = REPO / "benchmarks" / "image_lists"


def usable_images(capture: Path) -> list[str]:
    """Image names in light order, after DiLiGenT's benchmark rule."""
    from cnnps.io.capture import DILIGENT_RULES, benchmark_drop, read_filenames

    drop = set(benchmark_drop(capture, DILIGENT_RULES))
    return [n for i, n in enumerate(read_filenames(capture)) if i not in drop]


def subset_names(capture: Path, n: int, seed: int = 0) -> list[str]:
    """The n image names kept by the seeded rule (:func:`cnnps.io.capture.subset_drop`)."""
    from cnnps.io.capture import (
        DILIGENT_RULES,
        benchmark_drop,
        read_filenames,
        subset_drop,
    )

    drop = set(subset_drop(capture, n, seed, exclude=benchmark_drop(capture, DILIGENT_RULES)))
    return [name for i, name in enumerate(read_filenames(capture)) if i not in drop]


def list_path(capture_name: str, n: int) -> Path:
    return LISTS / f"{capture_name}-{n}.txt"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--n", type=int, nargs="+", default=[20, 10, 6])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    LISTS.mkdir(parents=True, exist_ok=True)
    for n in args.n:
        names = subset_names(args.capture, n, args.seed)
        path = list_path(args.capture.name, n)
        path.write_text(f"# {n} of {len(usable_images(args.capture))} images of {args.capture.name}, "
                        f"tools/image_subsets.py rule, seed {args.seed}\n" + "\n".join(names) + "\n")
        print(path.relative_to(REPO), " ".join(names))


if __name__ == "__main__":
    main()
