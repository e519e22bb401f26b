"""Where the long-run tool keeps things: this repository, the runs' folder in git, the
stages' names; and the one way it writes a JSON record (whole, or not at all)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from cnnps.stages import STAGES as stage_names

REPO = Path(__file__).resolve().parents[2]

STAGES = list(stage_names)  # cnnps.stages.STAGES


CARRIED = REPO / "tools" / "runs"  # what git carries of every run


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)



def git_head() -> str:
    return subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
