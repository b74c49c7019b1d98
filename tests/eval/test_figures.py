from canonical_core.eval.figures import _method_colours, _pyplot
from canonical_core.eval.methods import METHODS


def test_every_method_has_its_own_colour_in_the_plots():
    # eleven methods wrapped matplotlib's default 10-colour cycle: canonical and open3d_tsdf were
    # both drawn blue
    colours = _method_colours(_pyplot(), list(METHODS))
    assert len(colours) == len(METHODS) >= 11
    assert len(set(colours.values())) == len(METHODS)


LONG_LABEL = "canonical:model=/a/very/long/path/to/some/experiment/folder/decoder.safetensors"


def _measure(text: str, font) -> float:
    from PIL import Image, ImageDraw

    return ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(text, font=font)


def test_a_long_grid_label_stays_in_its_own_column():
    import numpy as np
    from PIL import ImageFont

    from canonical_core.eval.figures import _HEADER, image_grid

    font = ImageFont.load_default()
    tile = np.zeros((30, 120, 3), np.uint8)
    grid = np.asarray(image_grid({LONG_LABEL: [tile], "x": [tile]}))
    header = grid[:_HEADER, 120:]  # column 1's label band: its own short label only, none of column 0's
    end = 4 + int(_measure("x", font)) + 2
    assert (header[:, :3] == 255).all() and (header[:, end:] == 255).all()


def test_fit_label_shows_a_model_path_by_its_file_name_and_shortens_what_does_not_fit():
    from PIL import ImageFont

    from canonical_core.eval.figures import fit_label

    font = ImageFont.load_default()
    shown = fit_label(LONG_LABEL, font, 200)
    assert shown == "canonical:model=decoder.safetensors" and _measure(shown, font) <= 200 - 8
    narrow = fit_label(LONG_LABEL, font, 120)
    assert narrow.startswith("canonical:") and narrow.endswith("...") and _measure(narrow, font) <= 120 - 8
    assert fit_label("ground truth", font, 120) == "ground truth"  # a label that fits is kept
    assert fit_label("average:support=count", font, 320) == "average:support=count"
    assert fit_label("a" * 200, font, 60).endswith("...") and _measure(fit_label("a" * 200, font, 60), font) <= 52


def test_the_legend_names_every_line_of_every_panel(monkeypatch, tmp_path):
    """The coverage ceiling is drawn in the first panel only (without extrapolation): the legend,
    beside the last panel, named only what that panel drew."""
    from canonical_core.eval import figures

    runs = [{"method": m, "views": n, "noise": 0, "psnr": 10.0 + n, "psnr_covered": 12.0, "psnr_common": 12.0,
             "psnr_ceiling": 14.0 + n} for m in ("canonical", "open3d_tsdf") for n in (2, 4)]
    results = {"runs": runs, "methods": ["canonical", "open3d_tsdf"], "extrapolation": None, "inputs": {"2": [], "4": []},
               "dataset": "x"}
    legends = []
    save = figures._save
    monkeypatch.setattr(figures, "_save", lambda fig, ax, path: (save(fig, ax, path),
                                                                 legends.append([t.get_text() for t in ax.get_legend().get_texts()])))
    figures.plot_views(results, tmp_path / "views.png")
    assert legends == [["canonical", "canonical: coverage ceiling", "open3d_tsdf"]]
    assert (tmp_path / "views.png").stat().st_size > 0
