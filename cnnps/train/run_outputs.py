"""What a finished training run writes beside ``model.pt``: the params as the model file's
meta records them (:func:`recorded_params`) and the curves for ``dvc plots``
(:func:`write_plots`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cnnps.infra.atomic import write_text
from cnnps.train.params import Params


def recorded_params(params: Params) -> dict:
    """``params`` as ``model.pt``'s meta records them (:meth:`Params.from_record` reads them
    back): every field, the ``model`` section only off the paper's network, so a file of
    the paper's network holds the bytes it holds without the section."""
    record = dataclasses.asdict(params)
    if params.model == type(params.model)():
        record.pop("model")
    return record


def write_plots(out_dir: Path, history: dict) -> None:
    """``plots/loss.csv`` (step, loss) and ``plots/val.csv`` (step, mean, median) for ``dvc plots``."""
    plots = out_dir / "plots"
    write_text(plots / "loss.csv", "step,loss\n" + "".join(f"{s},{l:.6g}\n" for s, l in history["loss"]))
    write_text(
        plots / "val.csv",
        "step,val_mean_deg,val_median_deg\n" + "".join(f"{s},{a:.4f},{b:.4f}\n" for s, a, b in history["val"]),
    )
