"""Run tooling kept beside the code: scripts run as ``.venv/bin/python tools/NAME.py``
(tools/README.md); a package only so the tests can import them."""
