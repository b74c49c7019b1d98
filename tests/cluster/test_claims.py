"""The CPUs the cluster's actors claim, fitted to the nodes (in process), and `canonical serve --cluster`
refusing claims its local Ray cluster cannot place, in one line naming the setting."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from client.cli.launch import unclaimed_port
from server.cluster.claims import CLAIM_STEP, ClaimsDoNotFit, all_claims, fitted, packs

from ..server.harness import REPO
from .conftest import settings


@pytest.mark.parametrize("nodes", [[2.0], [1.5], [2.0, 2.0], [0.0, 8.0, 4.0], [16.0]], ids=str)
def test_unset_owner_cpus_are_the_largest_that_pack_onto_the_nodes_with_a_restart_to_spare(tmp_path, nodes):
    config = settings(tmp_path, owners=4 if len(nodes) > 1 else 2)
    fit = fitted(config, nodes)
    assert fit.owner_cpus >= CLAIM_STEP and fit.ingress_cpus == config.ingress_cpus
    claims = all_claims(fit, fit.owner_cpus)
    # every owner, every ingress replica at its most, and one more of the largest claim (a restart)
    assert len(claims) == fit.owners + fit.ingress_max_replicas + 1 and claims[-1] == max(claims)
    assert packs(claims, nodes) and sum(claims) <= sum(nodes) + 1e-9
    assert not packs(all_claims(fit, fit.owner_cpus + CLAIM_STEP), nodes)  # the largest such claim


def test_the_defaults_fit_a_two_cpu_machine_where_a_whole_cpu_per_owner_did_not(tmp_path):
    fit = fitted(settings(tmp_path), [2.0])
    assert (fit.owners, fit.ingress_cpus, fit.ingress_max_replicas, fit.owner_cpus) == (2, 0.25, 4, 0.33)
    assert not packs([1.0, 1.0, 0.25], [2.0])  # the former default: the second owner could never be placed
    with pytest.raises(ClaimsDoNotFit) as refused:
        fitted(settings(tmp_path, owner_cpus=1.0), [2.0])
    assert refused.value.setting == "owner_cpus"
    assert str(refused.value).startswith("owner_cpus: 2 owners of 1 CPU and 4 ingress replicas of 0.25 CPU")
    assert "need 4 CPUs" in str(refused.value) and "the cluster has 2 CPUs (1 node)" in str(refused.value)


def test_claims_are_placed_by_node_not_by_the_clusters_total(tmp_path):
    config = settings(tmp_path, owners=4, owner_cpus=0.6)
    assert sum(all_claims(config, 0.6)) == pytest.approx(4.0)  # adds up to the two nodes' CPUs ...
    with pytest.raises(ClaimsDoNotFit, match=r"nodes of 2, 2"):  # ... but no split over them fits
        fitted(config, [2.0, 2.0])
    assert fitted(config, [4.0]) is config  # on one node of 4 it fits: the settings are taken as they are
    assert packs([1.5, 0.5], [2.0]) and not packs([1.5, 1.5], [2.0, 1.0]) and packs([], [])


def test_ingress_claims_that_leave_no_room_for_owners_are_refused_naming_ingress_cpus(tmp_path):
    with pytest.raises(ClaimsDoNotFit) as refused:
        fitted(settings(tmp_path), [1.0])
    assert refused.value.setting == "ingress_cpus" and "leave no CPU for 2 owners" in refused.value.problem
    assert fitted(settings(tmp_path, ingress_max_replicas=1), [1.0]).owner_cpus == 0.25


def test_more_owners_than_any_ingress_leaves_room_for_are_refused_naming_owners(tmp_path):
    with pytest.raises(ClaimsDoNotFit) as refused:
        fitted(settings(tmp_path, owners=300), [2.0])
    assert refused.value.setting == "owners" and refused.value.problem.startswith("300 owners of at least")
    with pytest.raises(ClaimsDoNotFit) as refused:  # they fit alone, not beside the ingress: either may give
        fitted(settings(tmp_path, owners=100), [2.0])
    assert refused.value.setting == "ingress_cpus" and refused.value.problem.endswith("ingress_max_replicas or owners")


@pytest.mark.slow
def test_serve_cluster_refuses_claims_the_local_cluster_cannot_place_in_one_line(tmp_path, ray_tmpdir):
    pytest.importorskip("ray.serve")
    env = {k: v for k, v in os.environ.items() if not k.startswith("CANONICAL_") and k != "RAY_ADDRESS"}
    env.update(CANONICAL_OWNER_CPUS="1000", RAY_TMPDIR=ray_tmpdir)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    out = subprocess.run([sys.executable, "-m", "client.cli", "serve", "--cluster", "--port", str(unclaimed_port()),
                          "--data-dir", str(tmp_path / "data")], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2, out.stderr[-3000:]
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("error: CANONICAL_OWNER_CPUS: 2 owners of 1000 CPU and 4 ingress replicas") and \
        "the cluster has" in last, out.stderr[-3000:]
    assert "Traceback" not in out.stderr and not (tmp_path / "data").exists()  # nothing started, nothing written
