"""The tools beside this package that it uses (``run_weights``, ``tree_size``), imported
whether the package is ``tools.longrun`` (the tests) or ``longrun`` (``tools/long_run.py``
run as a script, its own folder on the path)."""

try:
    from tools import run_weights, tree_size
except ImportError:  # run as a script: tools/ itself is on the path
    import run_weights
    import tree_size

__all__ = ["run_weights", "tree_size"]
