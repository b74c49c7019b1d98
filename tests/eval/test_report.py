from canonical_core.eval.methods import METHODS
from canonical_core.eval.report import _method_colours, _pyplot, ablation_order


def test_every_method_has_its_own_colour_in_the_plots():
    # eleven methods wrapped matplotlib's default 10-colour cycle: canonical and open3d_tsdf were
    # both drawn blue
    colours = _method_colours(_pyplot(), list(METHODS))
    assert len(colours) == len(METHODS) >= 11
    assert len(set(colours.values())) == len(METHODS)


def _run(method, views, psnr, agree=0.7, noise=0.0):
    return {"method": method, "views": views, "noise": noise, "psnr": psnr, "psnr_covered": psnr + 4.0,
            "ssim": 0.5, "depth_agreement": agree}


def test_the_ablation_order_ranks_the_four_aggregation_rules_per_metric_and_n():
    runs = [_run("canonical", 4, 13.0, 0.77), _run("no_reliability", 4, 12.9, 0.76), _run("no_similarity", 4, 13.1, 0.76),
            _run("average", 4, 13.2, 0.75),
            _run("canonical", 8, 14.0, float("nan")), _run("no_reliability", 8, 14.0), _run("no_similarity", 8, 13.0),
            _run("average", 8, 12.0),
            _run("canonical", 16, 15.0), _run("average", 16, 14.0)]  # an ablation missing: no rows for N = 16
    rows = {(metric, n): rest for settings, metric, n, *rest in ablation_order(runs) if settings == "defaults"}
    assert rows["PSNR", "4"] == ["average > no_similarity > canonical > no_reliability", "3 of 4", "1 of 4"]
    assert rows["depth agree", "4"] == ["canonical > no_reliability > no_similarity > average", "1 of 4", "4 of 4"]
    # ties keep the full rule first; a metric one rule lacks (nan) has no row for that N
    assert rows["SSIM", "8"] == ["canonical > no_reliability > no_similarity > average", "1 of 4", "4 of 4"]
    assert rows["PSNR", "8"][0] == "canonical > no_reliability > no_similarity > average"
    assert ("depth agree", "8") not in rows
    assert not any(n == "16" for _, n in rows)
    assert ablation_order([r for r in runs if r["method"] != "average"]) == []


def test_each_settings_group_of_the_four_rules_is_ranked_on_its_own():
    plain = [_run(m, 4, p) for m, p in (("canonical", 13.0), ("no_reliability", 12.9), ("no_similarity", 13.1), ("average", 13.2))]
    trained = [_run(f"{m}:model=ckpt", 4, p) for m, p in (("canonical", 13.4), ("no_reliability", 13.3),
                                                         ("no_similarity", 13.2), ("average", 13.1))]
    rows = {(settings, metric): rest for settings, metric, n, *rest in ablation_order(plain + trained)}
    assert rows["defaults", "PSNR"] == ["average > no_similarity > canonical > no_reliability", "3 of 4", "1 of 4"]
    assert rows["model=ckpt", "PSNR"] == ["canonical > no_reliability > no_similarity > average", "1 of 4", "4 of 4"]
    # a group with a rule missing has no rows; a method outside the four is ignored
    assert {s for s, *_ in ablation_order(plain + trained[1:] + [_run("pixel_aligned", 4, 20.0)])} == {"defaults"}
