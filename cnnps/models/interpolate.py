"""Weight-space interpolation of two checkpoints of the same network (WiSE-FT), and the
mean of several (a model soup).

    python -m cnnps.models.interpolate A.pt B.pt --alpha 0.5 --out MIXED.pt
    python -m cnnps.models.interpolate A.pt B.pt C.pt --mean --out SOUP.pt

``MIXED = (1 - alpha) * A + alpha * B``, tensor by tensor. It makes sense when B was
fine-tuned from A (Wortsman et al., "Robust fine-tuning of zero-shot models", CVPR 2022):
both then lie in one basin of the loss, and the mid-point often keeps most of what the
fine-tune gained while giving back less of what it cost. Alpha is the caller's choice, made
by measurement (docs/models.md#v31-the-mid-point-of-v2-and-v3: a shipped mid-point and how
its alpha was chosen).

``--mean``: ``SOUP = (A + B + C + ...) / n``, tensor by tensor: the "uniform soup" of
Wortsman et al. ("Model soups", ICML 2022), for fine-tunes of one model that differ in
their seeds (docs/models.md: the shipped models that are such means).

The output's ``meta`` records alpha (or the mean's files) and each end's file, SHA-256 and meta; ``min_lights``
(what ``cnnps predict`` warns below) is the larger of the two ends' values, the fewest
lights both were trained on (each end's checkpoint meta, else the provenance record beside
it, as :func:`cnnps.models.shipped.trained_min_lights` reads it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cnnps.infra.errors import CnnpsError
from cnnps.infra.hashing import file_sha256


def _same_network(net_a, a, net_b, b) -> None:
    from cnnps.models.model_options import model_options

    if model_options(net_a) != model_options(net_b):
        raise CnnpsError(f"{b}: a different network ({model_options(net_b)}) from {a} ({model_options(net_a)}); "
                         "cannot interpolate")
    if (net_a.w, net_a.dropout_p, net_a.in_channels) != (net_b.w, net_b.dropout_p, net_b.in_channels):
        raise CnnpsError(f"{b}: a different network (w={net_b.w}, dropout={net_b.dropout_p}, "
                         f"in_channels={net_b.in_channels}) from {a} (w={net_a.w}, dropout={net_a.dropout_p}, "
                         f"in_channels={net_a.in_channels}); cannot interpolate")


def _fewest_lights(ends) -> dict:
    """``{"min_lights": n}``: the largest of the ends' trained minima (the fewest lights all saw), or {}."""
    from cnnps.models.shipped import trained_min_lights

    lights = [x for x in (trained_min_lights(p, m) for p, m in ends) if x is not None]
    return {"min_lights": max(lights)} if lights else {}


def interpolate(a: str | Path, b: str | Path, alpha: float):
    """(model, config, meta) of ``(1 - alpha) * a + alpha * b``; refuses different networks."""
    from cnnps.models.checkpoint import load_checkpoint

    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise CnnpsError(f"--alpha must be in [0, 1], got {alpha}")
    net_a, config_a, meta_a = load_checkpoint(a, "cpu")
    net_b, _config_b, meta_b = load_checkpoint(b, "cpu")
    _same_network(net_a, a, net_b, b)
    sa, sb = net_a.state_dict(), net_b.state_dict()
    net_a.load_state_dict({k: (1.0 - alpha) * sa[k] + alpha * sb[k] for k in sa})
    ends = [(a, meta_a), (b, meta_b)]
    meta = {
        "interpolated": {
            "alpha": alpha,
            "formula": "(1 - alpha) * a + alpha * b",
            **{name: {"file": str(p), "sha256": file_sha256(p), "meta": m} for name, (p, m) in zip("ab", ends)},
        }
    }
    meta.update(_fewest_lights(ends))
    return net_a, config_a, meta


def mean(paths) -> tuple:
    """(model, config, meta) of the mean of the checkpoints ``paths`` (two or more), tensor
    by tensor, in float32; refuses different networks. ``meta["mean"]`` lists each file,
    SHA-256 and meta.

    Example::

        net, config, meta = mean(["seed0/model.pt", "seed1/model.pt", "seed2/model.pt"])
    """
    from cnnps.models.checkpoint import load_checkpoint

    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise CnnpsError(f"--mean needs two or more checkpoints, got {len(paths)}")
    net, config, meta0 = load_checkpoint(paths[0], "cpu")
    ends = [(paths[0], meta0)]
    total = {k: v.float().clone() for k, v in net.state_dict().items()}
    for p in paths[1:]:
        other, _config, meta = load_checkpoint(p, "cpu")
        _same_network(net, paths[0], other, p)
        for k, v in other.state_dict().items():
            total[k] += v.float()
        ends.append((p, meta))
    like = net.state_dict()
    net.load_state_dict({k: (v / len(paths)).to(like[k].dtype) for k, v in total.items()})
    out = {"mean": [{"file": str(p), "sha256": file_sha256(p), "meta": m} for p, m in ends]}
    out.update(_fewest_lights(ends))
    return net, config, out


def main(argv: list[str] | None = None) -> None:
    from cnnps.models.checkpoint import save_checkpoint

    ap = argparse.ArgumentParser(prog="python -m cnnps.models.interpolate",
                                 description="(1 - alpha) * A + alpha * B, or with --mean the mean of "
                                             "the checkpoints, tensor by tensor")
    ap.add_argument("checkpoints", type=Path, nargs="+", help="A B (with --alpha), or two or more (with --mean)")
    how = ap.add_mutually_exclusive_group(required=True)
    how.add_argument("--alpha", type=float)
    how.add_argument("--mean", action="store_true")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    paths = args.checkpoints
    if args.alpha is not None and len(paths) != 2:
        ap.error(f"--alpha takes two checkpoints, A and B; got {len(paths)}")
    try:
        if args.mean:
            model, config, meta = mean(paths)
            said = f"the mean of {len(paths)} checkpoints"
        else:
            model, config, meta = interpolate(paths[0], paths[1], args.alpha)
            said = f"(1 - {args.alpha:g}) * {paths[0]} + {args.alpha:g} * {paths[1]}"
        save_checkpoint(args.out, model, config, meta)
    except CnnpsError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(f"wrote {args.out}: {said}")


if __name__ == "__main__":
    main()
