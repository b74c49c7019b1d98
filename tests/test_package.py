"""What importing the library does to the process: idle OpenMP threads sleep unless the user says otherwise,
numba's kernels run on that OpenMP team, and the facade's names load on first use, so that listing a capture or reading settings does not load torch."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# what OpenMP reads when torch and numba load it, seen from inside the process that imported the library
PROBE = "import canonical_core, os, numba, torch; print(os.environ['OMP_WAIT_POLICY'])"


@pytest.mark.parametrize("given, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_import_makes_idle_openmp_threads_sleep_unless_the_environment_chose(given, expected):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [expected]


def test_numba_kernels_run_on_the_openmp_team_that_the_policy_tunes():
    # numba's default order tries TBB first: with Open3D loaded (its wheel carries an old libtbb) that
    # printed a warning in every evaluation, and a machine with a newer TBB would run the kernels there
    probe = ("import importlib.util, canonical_core, numba, numpy\n"
             "if importlib.util.find_spec('open3d'): import open3d\n"
             "@numba.njit(parallel=True)\n"
             "def total(a):\n"
             "    s = 0.0\n"
             "    for i in numba.prange(a.size): s += a[i]\n"
             "    return s\n"
             "print(total(numpy.ones(1000)), numba.threading_layer())")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1000.0", "omp"]
    assert "TBB" not in out.stderr, out.stderr


def test_the_facade_loads_its_names_on_first_use():
    # listing a capture and reading settings load neither torch nor the method; the facade's names and
    # the submodules still resolve as attributes, and an unknown name is an AttributeError like any module's
    probe = ("import sys, canonical_core, canonical_core.datasets, canonical_core.config; "
             "light = 'torch' not in sys.modules and 'canonical_core.scene' not in sys.modules; "
             "scene = canonical_core.Scene(canonical_core.SceneConfig(voxel_size=0.01)); "
             "missing = not hasattr(canonical_core, 'NoSuchName'); "
             "every = all(getattr(canonical_core, name) is not None for name in canonical_core.__all__); "
             "print(light, type(scene).__name__, set(canonical_core.__all__) <= set(dir(canonical_core)), missing, every)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "Scene", "True", "True", "True"]
    # a submodule nothing imported yet, reached as an attribute of the bare package
    probe = "import canonical_core; print(canonical_core.rendering.render is canonical_core.render)"
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True"]


def test_the_names_type_checkers_see_are_the_facades():
    # the facade's lazy table and the imports it shows type checkers name the same things from the same modules
    import canonical_core

    tree = ast.parse((REPO / "canonical_core" / "__init__.py").read_text())
    shown = {alias.name: node.module for block in tree.body if isinstance(block, ast.If)
             for node in block.body if isinstance(node, ast.ImportFrom) for alias in node.names}
    assert shown == canonical_core._EXPORTS
