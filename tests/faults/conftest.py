"""Fixtures of the fault-injection tests (``-m faults``).

The upstream outputs that :func:`tests.support.faults.stage_folder` copies (meshes ->
... -> train on the tiny params) are built once per session, under pytest's own
temporary folder.
"""

from __future__ import annotations

import pytest

from tests.support import faults


@pytest.fixture(scope="session", autouse=True)
def _faults_templates(tmp_path_factory):
    faults.set_template_root(tmp_path_factory.mktemp("faults-templates"))
    yield
