"""The CPUs the cluster's actors claim from Ray's scheduler, fitted to the nodes they run on. No Ray
here (`server.cluster.serve` passes the nodes' CPUs), so it is tested in process.

A claim is scheduling bookkeeping, not a limit: an owner folds on whatever cores it gets. What a claim
decides is whether Ray can place the actor at all. Claims that do not fit leave an actor waiting for
CPUs forever (an owner whose sessions never answer; an ingress replica that is never scheduled after
a restart), so every claim the service can make at once (each owner, each ingress replica at
``ingress_max_replicas``) must pack onto the nodes with one restart's worth to spare: a restarted actor
then finds room even while a replacement is being placed or a node's actors move.
"""

from __future__ import annotations

from typing import Literal

from .settings import ClusterSettings

CLAIM_STEP = 0.01  # derived claims are rounded down to this, so that the logs and errors read plainly


class ClaimsDoNotFit(ValueError):
    """The service's CPU claims cannot be placed on the cluster; ``setting`` is the one to change."""

    def __init__(self, setting: Literal["owner_cpus", "ingress_cpus"], problem: str):
        super().__init__(f"{setting}: {problem}")
        self.setting, self.problem = setting, problem


def packs(claims: list[float], nodes: list[float]) -> bool:
    """Whether ``claims`` (CPUs each) can be placed on nodes of ``nodes`` CPUs each: first fit, largest
    claim first. A fit it finds is a real placement; it may miss one that an exhaustive search would find,
    which errs on the side of smaller claims."""
    room = sorted(nodes, reverse=True)
    for claim in sorted(claims, reverse=True):
        k = next((k for k, free in enumerate(room) if claim <= free + 1e-9), None)
        if k is None:
            return False
        room[k] -= claim
    return True


def all_claims(settings: ClusterSettings, owner_cpus: float) -> list[float]:
    """Every claim at once: the owners, the ingress replicas at their most, and the largest claim again
    (the room one restarting actor needs)."""
    claims = [owner_cpus] * settings.owners + [settings.ingress_cpus] * settings.ingress_max_replicas
    return claims + [max(claims)]


def largest_owner_claim(settings: ClusterSettings, nodes: list[float]) -> float:
    """The largest owner claim, a multiple of `CLAIM_STEP`, with which `all_claims` packs onto ``nodes``;
    0 when none does. Bisection over the claim, then checked once more where rounding down met one of
    first fit's rare cases in which a smaller claim packs worse."""
    low, high = 0.0, max(nodes, default=0.0)
    while high - low > CLAIM_STEP / 4:
        middle = (low + high) / 2
        low, high = (middle, high) if packs(all_claims(settings, middle), nodes) else (low, middle)
    steps = int(low / CLAIM_STEP + 1e-6)
    while steps > 0 and not packs(all_claims(settings, steps * CLAIM_STEP), nodes):
        steps -= 1
    return round(steps * CLAIM_STEP, 6)


def describe(nodes: list[float]) -> str:
    """A cluster's CPUs in words, for errors: ``2 CPUs (1 node)`` or ``6 CPUs (nodes of 2, 4)``."""
    cpus = f"{sum(nodes):g} CPUs"
    return f"{cpus} (1 node)" if len(nodes) == 1 else f"{cpus} (nodes of {', '.join(f'{n:g}' for n in nodes)})"


def fitted(settings: ClusterSettings, nodes: list[float]) -> ClusterSettings:
    """``settings`` with claims that fit nodes of ``nodes`` CPUs each: ``owner_cpus`` as given, once
    checked, or (when unset) the largest that fits. `ClaimsDoNotFit` naming the setting otherwise."""
    ingress = f"{settings.ingress_max_replicas} ingress replicas of {settings.ingress_cpus:g} CPU"
    if settings.owner_cpus is not None:
        if not packs(all_claims(settings, settings.owner_cpus), nodes):
            need = sum(all_claims(settings, settings.owner_cpus))
            raise ClaimsDoNotFit("owner_cpus", f"{settings.owners} owners of {settings.owner_cpus:g} CPU and {ingress}, "
                                 f"with room for one restart, need {need:g} CPUs placed whole on nodes; the cluster "
                                 f"has {describe(nodes)}; lower it, or unset it to fit it to the cluster")
        return settings
    owner_cpus = largest_owner_claim(settings, nodes)
    alone = settings.model_copy(update={"ingress_cpus": 0.0})  # the owners' smallest claims without the ingress
    if owner_cpus < CLAIM_STEP and not packs(all_claims(alone, CLAIM_STEP), nodes):
        raise ClaimsDoNotFit("owners", f"{settings.owners} owners of at least {CLAIM_STEP:g} CPU each, with room for "
                             f"one restart, do not fit a cluster of {describe(nodes)} whatever the ingress takes; "
                             "lower it")
    if owner_cpus < CLAIM_STEP:
        raise ClaimsDoNotFit("ingress_cpus", f"{ingress} (ingress_max_replicas) and room for one restart leave no CPU "
                             f"for {settings.owners} owners on a cluster of {describe(nodes)}; lower it, "
                             "ingress_max_replicas or owners")
    return settings.model_copy(update={"owner_cpus": owner_cpus})


__all__ = ["CLAIM_STEP", "ClaimsDoNotFit", "all_claims", "describe", "fitted", "largest_owner_claim", "packs"]
