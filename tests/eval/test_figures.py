from canonical_core.eval.figures import _method_colours, _pyplot
from canonical_core.eval.methods import METHODS


def test_every_method_has_its_own_colour_in_the_plots():
    # eleven methods wrapped matplotlib's default 10-colour cycle: canonical and open3d_tsdf were
    # both drawn blue
    colours = _method_colours(_pyplot(), list(METHODS))
    assert len(colours) == len(METHODS) >= 11
    assert len(set(colours.values())) == len(METHODS)
