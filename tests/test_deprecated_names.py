"""Public names spelt ``color`` are ``colour`` now; the old spelling still works for one release and
warns (DeprecationWarning) naming the new one."""

from __future__ import annotations

import warnings

import pytest
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.decode.decoder import GaussianDecoder
from canonical_core.deprecation import RenamedKeys, get_renamed


@pytest.fixture(scope="module")
def scene() -> Scene:
    scene = Scene(SceneConfig(voxel_size=0.2, features={"dim": 4}))
    for frame in synthetic_rgbd(num_frames=1, width=32, height=24):
        scene.fold(frame)
    return scene


def test_gaussians_colors_warns_and_equals_colours(scene):
    g = scene.decode()
    with pytest.warns(DeprecationWarning, match="Gaussians.colors: renamed to Gaussians.colours"):
        old = g.colors
    assert torch.equal(old, g.colours) and g.colours.shape == (len(g), 3)


def test_field_keys_answer_to_the_old_spelling_with_a_warning(scene):
    fields = scene.fields()
    assert "colour" in fields and "representative_colour" in fields and "color" not in fields
    for old, new in (("color", "colour"), ("representative_color", "representative_colour")):
        with pytest.warns(DeprecationWarning, match=f"\\['{old}'\\]: renamed to \\['{new}'\\]"):
            assert fields[old] is fields[new]
    with pytest.raises(KeyError):
        fields["colours"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fields["colour"]  # the new name never warns


def test_decoder_reads_old_field_dicts_with_a_warning(scene):
    fields = dict(scene.fields())
    decoder = GaussianDecoder(4)
    fields.pop("sh")  # the decoder then makes SH from the colour
    new = decoder(fields, 0.2)
    fields["color"] = fields.pop("colour")
    with pytest.warns(DeprecationWarning, match="renamed to \\['colour'\\]"):
        old = decoder(fields, 0.2)
    assert torch.equal(new.sh, old.sh)


def test_renamed_keys_only_map_what_they_are_told():
    d = RenamedKeys({"a": 1}, {"b": "a", "c": "missing"})
    with pytest.warns(DeprecationWarning):
        assert d["b"] == 1
    for key in ("c", "z"):
        with pytest.raises(KeyError):
            d[key]
    assert get_renamed({"new": 1, "old": 2}, "new", "old") == 1
