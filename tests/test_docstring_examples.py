"""The runnable examples in the docstrings of canonical_core, the service and the client run and print
what they say.

Every module with a ``>>>`` example is one case, so an example that rots (a renamed argument, a
changed shape or value) fails here with the module's name.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import canonical_core
import client
import server

# `_composite*` are the compositor's C libraries (loaded with ctypes), not Python modules; the cluster
# mode's modules need Ray (an extra) and are exercised by tests/cluster.
MODULES = sorted(m.name for package in (canonical_core, server, client)
                 for m in pkgutil.walk_packages(package.__path__, f"{package.__name__}.")
                 if not m.name.rsplit(".", 1)[1].startswith(("_composite", "__main__"))
                 and not m.name.startswith("server.cluster"))


def test_modules_are_found():
    assert {"canonical_core.camera", "canonical_core.scene.scene", "canonical_core.decode.decoder", "server.memory",
            "client.cli"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} docstring examples failed (see the output above)"
