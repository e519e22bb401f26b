"""Weight-space interpolation of two checkpoints of the same network (WiSE-FT).

    python -m cnnps.models.interpolate A.pt B.pt --alpha 0.5 --out MIXED.pt

``MIXED = (1 - alpha) * A + alpha * B``, tensor by tensor. It makes sense when B was
fine-tuned from A (Wortsman et al., "Robust fine-tuning of zero-shot models", CVPR 2022):
both then lie in one basin of the loss, and the mid-point often keeps most of what the
fine-tune gained while giving back less of what it cost. Model v3.1 is such a mid-point of
v2 and v3 (docs/models.md#v31-the-mid-point-of-v2-and-v3); the measurements chose alpha,
not this module.

The output's ``meta`` records alpha and each end's file, SHA-256 and meta; ``min_lights``
(what ``cnnps predict`` warns below) is the larger of the two ends' values, the fewest
lights both were trained on (each end's checkpoint meta, else the provenance record beside
it, as :func:`cnnps.models.shipped.trained_min_lights` reads it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cnnps.infra.errors import CnnpsError
from cnnps.infra.hashing import file_sha256


def interpolate(a: str | Path, b: str | Path, alpha: float):
    """(model, config, meta) of ``(1 - alpha) * a + alpha * b``; refuses different networks."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.shipped import trained_min_lights

    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise CnnpsError(f"--alpha must be in [0, 1], got {alpha}")
    net_a, config_a, meta_a = load_checkpoint(a, "cpu")
    net_b, _config_b, meta_b = load_checkpoint(b, "cpu")
    if (net_a.w, net_a.dropout_p, net_a.in_channels) != (net_b.w, net_b.dropout_p, net_b.in_channels):
        raise CnnpsError(f"{b}: a different network (w={net_b.w}, dropout={net_b.dropout_p}, "
                         f"in_channels={net_b.in_channels}) from {a} (w={net_a.w}, dropout={net_a.dropout_p}, "
                         f"in_channels={net_a.in_channels}); cannot interpolate")
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
    lights = [x for x in (trained_min_lights(p, m) for p, m in ends) if x is not None]
    if lights:
        meta["min_lights"] = max(lights)
    return net_a, config_a, meta


def main(argv: list[str] | None = None) -> None:
    from cnnps.models.checkpoint import save_checkpoint

    ap = argparse.ArgumentParser(prog="python -m cnnps.models.interpolate",
                                 description="(1 - alpha) * A + alpha * B, tensor by tensor")
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--alpha", type=float, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    try:
        model, config, meta = interpolate(args.a, args.b, args.alpha)
        save_checkpoint(args.out, model, config, meta)
    except CnnpsError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(f"wrote {args.out}: (1 - {args.alpha:g}) * {args.a} + {args.alpha:g} * {args.b}")


if __name__ == "__main__":
    main()
