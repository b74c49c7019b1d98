from canonical_core.eval.report import ablation_order, leads, view_steps


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


def _scored(method, views, common, ssim, psnr, covered, agree):
    return {"method": method, "views": views, "noise": 0.0, "psnr_common": common, "ssim": ssim, "psnr": psnr,
            "psnr_covered": covered, "depth_agreement": agree}


def test_the_first_method_leads_each_other_by_its_value_minus_theirs_at_every_n_both_ran():
    runs = [_scored("canonical", 2, 21.53, 0.644, 18.94, 21.43, 0.787), _scored("open3d_tsdf", 2, 21.11, 0.618, 17.01, 21.07, 0.771),
            _scored("canonical", 4, 22.02, 0.668, 19.64, 21.99, 0.776), _scored("open3d_tsdf", 4, 21.69, 0.648, 17.76, 21.68, float("nan")),
            _scored("pixel_aligned", 4, 20.27, 0.700, 17.58, 20.24, 0.762)]  # pixel_aligned without N = 2: no row for it
    assert leads(runs, ["canonical", "open3d_tsdf", "pixel_aligned"]) == [
        ["open3d_tsdf", "2", "+0.42", "+0.026", "+1.93", "+0.36", "+0.016"],
        ["open3d_tsdf", "4", "+0.33", "+0.020", "+1.88", "+0.31", "-"],  # a metric the peer lacks: no lead
        ["pixel_aligned", "4", "+1.75", "-0.032", "+2.06", "+1.75", "+0.014"],  # behind: negative
    ]
    assert leads(runs, ["canonical"]) == []


def test_the_worst_step_as_views_are_added_is_the_lowest_difference_from_one_n_to_the_next():
    psnr = {2: 13.0, 4: 14.0, 8: 13.5, 16: 15.0}
    covered = {2: 20.0, 4: 20.5, 8: 21.5, 16: 21.0}
    runs = [_scored("canonical", n, 0.0, 0.5, psnr[n], covered[n], 0.70 + n / 100) for n in (16, 2, 8, 4)]  # any order
    runs += [_scored("average", 4, 0.0, 0.5, 12.0, float("nan"), 0.6), _scored("average", 8, 0.0, 0.5, 12.5, 19.0, 0.61),
             _scored("pixel_aligned", 4, 0.0, 0.5, 11.0, 18.0, 0.5)]  # one N: nothing to step
    assert view_steps(runs, ["canonical", "average", "pixel_aligned"]) == [
        ["canonical", "-0.50", "-0.50", "0.720 -> 0.860"],  # 14.0 -> 13.5 and 21.5 -> 21.0
        ["average", "+0.50", "-", "0.600 -> 0.610"],  # a missing value makes no step
    ]
