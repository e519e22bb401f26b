"""A training run longer than a session: a fixed checkout, data outside the work tree, a
CPU-time ledger, and a fallback to committed weights (:mod:`tools.longrun`, whose
docstring is the manual).

    .venv/bin/python tools/long_run.py start v4 --preset cpu-train-v4 [--commit HEAD] [--root /work/runs]
    .venv/bin/python tools/long_run.py resume v4 [--stages render extract train]
    .venv/bin/python tools/long_run.py save v4      # then commit tools/runs/v4/
"""

if __name__ == "__main__":
    from longrun.cli import main  # this folder is on the path when the script runs

    raise SystemExit(main())
