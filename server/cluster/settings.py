"""The cluster's settings: the service's `Settings` plus how the sessions are spread (same
``CANONICAL_*`` environment variables, e.g. ``CANONICAL_OWNERS=4``)."""

from __future__ import annotations

from pydantic import Field, ValidationInfo, field_validator

from ..settings import Settings


class ClusterSettings(Settings):
    """`Settings` for ``canonical serve --cluster``; ``data_dir`` must be a folder every node mounts."""

    owners: int = Field(2, gt=0, description="session owner processes (shards); session id -> owner by a stable hash")
    owner_cpus: float | None = Field(None, gt=0, description="CPUs each owner declares to Ray's scheduler (it folds and "
                                     "renders); unset: the most that fits the cluster's nodes at start (server.cluster.claims)")
    owner_memory_bytes: int | None = Field(None, gt=0, description="per owner: idle sessions are evicted (LRU) while "
                                           "their scenes' memory_bytes exceed this; a node's budget is this times its owners")
    ingress_min_replicas: int = Field(1, gt=0, description="Serve autoscaling: fewest ingress replicas")
    ingress_max_replicas: int = Field(4, gt=0, description="Serve autoscaling: most ingress replicas")
    ingress_target_requests: float = Field(8.0, gt=0, description="Serve autoscaling: requests in flight per ingress replica")
    ingress_cpus: float = Field(0.25, ge=0, description="CPUs each ingress replica declares (it only forwards)")
    ingress_health_check_s: float = Field(2.0, gt=0, description="Serve checks each ingress replica this often; one "
                                          "that died is replaced after the next check (Serve's default: 10 s)")
    owner_timeout_s: float = Field(300.0, gt=0, description="a request forwarded to a running owner and not answered "
                                   "in this time gets 429")
    owner_restart_wait_s: float = Field(30.0, ge=0, description="an owner not known to run (starting, restarting, waiting "
                                        "for CPUs) is waited for this long before its request gets 429; a request whose "
                                        "owner died gets its 429 once the restarted owner answers, or after this long")
    namespace: str = Field("canonical", description="Ray namespace of the owners' named actors")

    @field_validator("ingress_max_replicas")
    @classmethod
    def _at_least_the_fewest(cls, most: int, info: ValidationInfo) -> int:
        fewest = info.data.get("ingress_min_replicas")
        if fewest is not None and most < fewest:
            raise ValueError(f"at least ingress_min_replicas ({fewest}): Serve cannot autoscale between them")
        return most
