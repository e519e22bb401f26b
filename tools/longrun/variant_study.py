"""The variant study of a run: a second clone where ``dvc exp run`` tries variants, each
timed into the run's ledger, and the study's table."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from .paths import REPO
from .train_section import train_value


class VariantStudy:
    """The variant study's part of :class:`tools.longrun.run.Run`."""

    @property
    def study(self) -> Path:
        return self.dir / "study"

    def make_study(self) -> list[str]:
        """A second clone at the run's commit where ``dvc exp run`` tries variants.

        Its ``params.yaml`` is the run's with ``data_dir: data``, committed there as the
        experiments' baseline; ``data/meshes``, ``materials``, ``render`` and ``extract`` are
        links to the run's folders (every variant reads the same renders and shards), while
        ``data/train`` and ``data/eval`` are the study's own, so no variant touches the run's
        checkpoints. A clone of another commit is replaced (its experiments go with it)."""
        rec, notes = self.record(), []
        head = self.study_commit()
        if head != rec["commit"]:
            if self.study.exists():
                shutil.rmtree(self.study)
                notes.append(f"replaced the study clone of {str(head)[:12]}")
            subprocess.run(["git", "clone", "-q", "--no-checkout", str(REPO), str(self.study)], check=True)
            subprocess.run(["git", "-C", str(self.study), "checkout", "-q", "--detach", rec["commit"]], check=True)
            params = yaml.safe_load(self.params.read_text())
            params["data_dir"] = "data"
            (self.study / "params.yaml").write_text(
                f"# the parameters of long run {self.name!r} (tools/long_run.py), data in {self.data}\n"
                + yaml.safe_dump(params, sort_keys=False))
            git = ["git", "-C", str(self.study), "-c", "user.name=cnnps long run", "-c", "user.email=long-run@cnnps"]
            subprocess.run([*git, "commit", "-qam", f"the study's baseline: the parameters of run {self.name}"],
                           check=True)
            notes.append(f"cloned {rec['commit'][:12]} into {self.study}")
        data = self.study / "data"
        data.mkdir(exist_ok=True)
        for stage in ("meshes", "materials", "render", "extract"):
            link = data / stage
            (self.data / stage).mkdir(parents=True, exist_ok=True)  # a stage writes through the link
            if not link.is_symlink():
                if link.exists():
                    shutil.rmtree(link)
                link.symlink_to(self.data / stage, target_is_directory=True)
        return notes

    def study_commit(self) -> str | None:
        """The commit the study clone was made from (None: no study)."""
        if not (self.study / ".git").is_dir():
            return None
        return subprocess.run(["git", "-C", str(self.study), "rev-parse", "HEAD~1"], capture_output=True,
                              text=True).stdout.strip() or None

    def run_exp(self, args: list[str], poll: float) -> int:
        """``dvc exp run ARGS`` in the study clone, its CPU time in the ledger (stage ``study``).
        A study of an earlier commit of the run is kept (with its experiments): ``study``
        replaces it."""
        have = self.study_commit()
        if have is not None and have != self.record()["commit"]:
            raise SystemExit(f"{self.study} is a study of {have[:12]}, the run is now at {self.record()['commit'][:12]}: "
                             f"`long_run.py table {self.name}` keeps its rows, `long_run.py study {self.name}` starts "
                             "a new one (its experiments go)")
        self.make_study()
        # every variant is the baseline plus its own -S: DVC leaves the last experiment's
        # params in the workspace, which the next one would otherwise inherit
        subprocess.run(["git", "-C", str(self.study), "checkout", "-q", "HEAD", "--", "params.yaml"], check=True)
        cmd = [str(Path(sys.executable).parent / "dvc"), "exp", "run", *args]
        return self._timed("study", cmd, self.study, poll, command=" ".join(["dvc", "exp", "run", *args]))

    def study_rows(self) -> list[dict]:
        """One row per experiment of the study (``dvc exp show --json``): its train params,
        the measures it was scored on, and its CPU-hours from the ledger."""
        out = subprocess.run([str(Path(sys.executable).parent / "dvc"), "exp", "show", "--json"], cwd=self.study,
                             capture_output=True, text=True, check=True, env=dict(os.environ, PYTHONPATH=str(self.study)))
        ledger = json.loads(self.ledger.read_text()) if self.ledger.is_file() else {"calls": []}
        cpu: dict[str, float] = {}
        changes: dict[str, list[str]] = {}
        for c in ledger["calls"]:
            words = c.get("command", "").split()
            if c["stage"] == "study" and "-n" in words[:-1]:
                name = words[words.index("-n") + 1]
                cpu[name] = cpu.get(name, 0.0) + c["cpu_s"] / 3600
                changes[name] = [words[i + 1] for i, w in enumerate(words[:-1]) if w == "-S"]
        rows = []
        for entry in json.loads(out.stdout):
            for exp in entry.get("experiments") or []:
                if (exp.get("executor") or {}).get("state") in ("running", "queued"):
                    continue  # its rows show the workspace's files, not its own yet
                for rev in exp.get("revs") or []:
                    data = rev.get("data") or {}
                    params = ((data.get("params") or {}).get("params.yaml") or {}).get("data") or {}
                    metrics = data.get("metrics") or {}
                    tm = (metrics.get("data/train/metrics.json") or {}).get("data") or {}
                    em = (metrics.get("data/eval/metrics.json") or {}).get("data") or {}
                    if not em:
                        continue  # not scored (still running, or failed)
                    train = params.get("train") or {}
                    row = {"name": rev.get("name") or rev.get("rev"), "init": Path(train.get("init") or "scratch").stem,
                           "lr": train_value(train, "lr"), "steps": train.get("max_steps"),
                           "pixelwise": train_value(train, "pixelwise", 0.0),
                           "changes": changes.get(rev.get("name"), []),
                           "cpu_hours": round(cpu.get(rev.get("name"), 0.0), 3),
                           "val_mean_deg": tm.get("val_mean_deg")}
                    row.update(metric_columns(em, params.get("eval") or {}))
                    rows.append(row)
        return rows


def metric_columns(em: dict, ev: dict) -> dict:
    """The study's columns from an eval ``metrics.json`` (``em``) and its eval section
    (``ev``): the CNN's (largest K) non-convex ratios and means per light count, and each
    real capture (and subset) mean, least squares beside it. Reads only numbers and keys
    (``dvc exp show`` keeps no strings or lists of a metrics file)."""
    row = {}
    groups = em.get("by_lights_nonconvex") or {}
    k = f"cnn_k{max(ev.get('rotations') or [1, 10])}"  # the eval stage's default rotations: 1 and 10
    for n, g in groups.items():
        row[f"nonconvex_{n}_vs_ls"] = g.get(f"{k}_vs_least_squares")
        row[f"nonconvex_{n}_deg"] = (g.get(k) or {}).get("mean_deg")
    for c in ev.get("real_captures") or []:
        for name in [Path(c).name] + [f"{Path(c).name}-{n}" for n in ev.get("real_subsets") or []]:
            methods = ((em.get("captures") or {}).get(name) or {}).get("methods") or {}
            if k in methods:
                row[f"{name}_deg"] = methods[k]["mean_deg"]
                row[f"{name}_ls_deg"] = (methods.get("lambertian") or {}).get("mean_deg")
    return row


def format_study(rows: list[dict]) -> str:
    """The study as a Markdown table: K=10 mean errors in degrees, ratios to least squares."""
    def f(v, fmt="{:.2f}"):
        return "" if v is None else fmt.format(v)

    head = ("| variant | changes to the baseline (`-S`) | CPU-h | val maps | non-convex 10 / 17 / 305 lights (x LS) "
            "| BALL 96 / 20 / 10 / 6 images |")
    lines = [head, "|" + " --- |" * 6]
    for r in rows:
        ratios = " / ".join(f(r.get(f"nonconvex_{n}_vs_ls"), "{:.3f}") for n in ("10", "17", "305"))
        ball = " / ".join(f(r.get(f"ballPNG{s}_deg")) for s in ("", "-20", "-10", "-6"))
        changed = " ".join(f"`{c}`" for c in r.get("changes") or []) or "none"
        lines.append(f"| {r['name']} | {changed} | {r['cpu_hours']:.2f} | {f(r.get('val_mean_deg'))} | {ratios} "
                     f"| {ball} |")
    return "\n".join(lines)
