"""The runnable examples in canonical_core's docstrings run and print what they say.

Every module with a ``>>>`` example is one case, so an example that rots (a renamed argument, a
changed shape or value) fails here with the module's name.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import canonical_core

# `_composite*` are the compositor's C libraries (loaded with ctypes), not Python modules.
MODULES = sorted(m.name for m in pkgutil.walk_packages(canonical_core.__path__, "canonical_core.")
                 if not m.name.rsplit(".", 1)[1].startswith(("_composite", "__main__")))


def test_modules_are_found():
    assert {"canonical_core.camera", "canonical_core.scene.scene", "canonical_core.decode.decoder"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} docstring examples failed (see the output above)"
