"""Ray Serve wiring (the one module that imports Ray): owners as named detached actors, the ingress as
an autoscaled Serve deployment, and `serve_forever` behind ``canonical serve --cluster``.

Why an actor per shard of sessions rather than per session: an owner process imports torch and
numba and compiles kernels, hundreds of MB and seconds per process, so a process per session does not
scale; Serve's multiplexing routes by affinity only, so it cannot make a session single-writer. A
fixed number of shards (``owners``), each a named actor (created by `start` before the ingress takes
requests, or by the first replica that needs it under `app_builder`: ``get_if_exists``), gives every
session exactly one owner that every ingress replica finds by name; Ray restarts an owner that
dies (``max_restarts=-1``) wherever its declared CPUs fit, and the new process takes each session's
lease as it restores it from the shared data directory. Those CPUs are fitted to the cluster's nodes at
start (`server.cluster.claims`), so every owner, every ingress replica and one restarting actor always
find room.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from pathlib import Path

import ray
from ray import serve
from ray.exceptions import RayActorError

from .claims import fitted
from .ingress import OwnerUnreachable, ingress_app
from .owner import SessionOwner
from .settings import ClusterSettings

log = logging.getLogger("canonical.cluster")

APP_NAME = "canonical"
REPO = Path(__file__).resolve().parents[2]
OwnerActor = ray.remote(SessionOwner)


OWNER_PREFIX = "canonical-owner-"  # the owners' actor names: the prefix and the shard


def owner_name(shard: int) -> str:
    return f"{OWNER_PREFIX}{shard}"


def owner_actor(settings: ClusterSettings, shard: int):
    """The owner of shard ``shard``: the running actor of that name, or a new one."""
    return OwnerActor.options(name=owner_name(shard), namespace=settings.namespace, get_if_exists=True, lifetime="detached",
                              max_restarts=-1, max_task_retries=0, num_cpus=settings.owner_cpus,
                              max_concurrency=1000).remote(settings, shard)


class RayOwners:
    """`server.cluster.ingress.Owners` over the owners' actors; a dead or restarting owner -> `OwnerUnreachable`."""

    def __init__(self, settings: ClusterSettings):
        self.settings, self.count = settings, settings.owners
        self._handles: dict[int, object] = {}

    def handle(self, shard: int):
        if shard not in self._handles:
            self._handles[shard] = owner_actor(self.settings, shard)
        return self._handles[shard]

    async def call(self, shard: int, method: str, *args):
        try:
            return await getattr(self.handle(shard), method).remote(*args)
        except RayActorError as exc:
            raise OwnerUnreachable(f"owner {shard} is restarting ({type(exc).__name__})") from None


@serve.deployment
@serve.ingress()
class Ingress:
    """A stateless ingress replica: the service's app, forwarding to the owners."""

    def __init__(self, settings: ClusterSettings):
        self.settings = settings

    def __serve_build_asgi_app__(self):
        return ingress_app(self.settings, RayOwners(self.settings))


def application(settings: ClusterSettings):
    """The Serve application: the autoscaled ingress (owners are created by it on demand)."""
    return Ingress.options(
        autoscaling_config={"min_replicas": settings.ingress_min_replicas, "max_replicas": settings.ingress_max_replicas,
                            "target_ongoing_requests": settings.ingress_target_requests},
        max_ongoing_requests=max(64, int(4 * settings.ingress_target_requests)),
        health_check_period_s=settings.ingress_health_check_s,
        ray_actor_options={"num_cpus": settings.ingress_cpus},
    ).bind(settings)


def connect(address: str | None = None, num_cpus: int | None = None, namespace: str = "canonical") -> None:
    """Join the cluster at ``address`` (or ``RAY_ADDRESS``), or start a local one whose workers import
    this checkout's code."""
    if address or os.environ.get("RAY_ADDRESS"):
        ray.init(address=address, namespace=namespace)
        return
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)
    ray.init(num_cpus=num_cpus, namespace=namespace, include_dashboard=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})


def node_cpus() -> list[float]:
    """The CPUs of each live node of the connected cluster."""
    return [node["Resources"].get("CPU", 0.0) for node in ray.nodes() if node["Alive"]]


def running_owners(namespace: str) -> dict[int, object]:
    """The owners running in ``namespace`` (detached: they outlive the service that started them on a
    cluster it joined), by shard."""
    names = {a["name"] for a in ray.util.list_named_actors(all_namespaces=True) if a.get("namespace") == namespace}
    return {shard: ray.get_actor(name, namespace=namespace) for name in names
            if (shard := _shard_of_name(name)) is not None}


def _shard_of_name(name: str) -> int | None:
    shard = name.removeprefix(OWNER_PREFIX)
    return int(shard) if shard != name and shard.isdigit() else None


def _settings_of(actor) -> str | None:
    try:
        return ray.get(actor.settings_json.remote(), timeout=60)
    except Exception:  # noqa: BLE001 - an owner of an earlier version, or one that does not answer
        return None


def owners_to_replace(found: dict[int, str | None], settings: ClusterSettings) -> list[int]:
    """The shards of the running owners (``found``: shard -> the settings it runs with, as JSON; None
    where it did not say) that a service with ``settings`` must replace: those past its count of owners,
    and those with other settings.

    Example:
        >>> from server.cluster.settings import ClusterSettings
        >>> ours = ClusterSettings(data_dir="/data", owners=2)
        >>> owners_to_replace({0: ours.model_dump_json(), 1: None, 2: ours.model_dump_json()}, ours)
        [1, 2]
    """
    ours = settings.model_dump_json()
    return sorted(shard for shard, theirs in found.items() if shard >= settings.owners or theirs != ours)


def stop_owners(owners: dict[int, object], why: str) -> None:
    """Kill these owners (their sessions' files stay: a new owner restores them) and wait until their
    names are free."""
    for shard, actor in owners.items():
        log.warning("stopping owner %d: %s", shard, why)
        ray.kill(actor, no_restart=True)
    for shard, actor in owners.items():
        try:
            ray.get(actor.pid.remote(), timeout=60)
        except Exception:  # noqa: BLE001 - dead, as asked
            pass


def start_owners(settings: ClusterSettings, report_every_s: float = 30.0) -> None:
    """Start every owner and wait until each answers, before the ingress takes requests, so that no
    session's first request waits for its owner's start. Owners found running with other settings
    (a service started before on this cluster with another data directory, another count of owners...)
    or of a shard past ``settings.owners`` are replaced: each session must have the owner its settings
    say, reading the data directory they name."""
    running = running_owners(settings.namespace)
    found = {shard: _settings_of(actor) for shard, actor in running.items()}
    stale = {shard: running[shard] for shard in owners_to_replace(found, settings)}
    if stale:
        stop_owners(stale, "it runs with other settings than this service's")
    pending = {owner_actor(settings, shard).pid.remote(): shard for shard in range(settings.owners)}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=report_every_s)
        for ref in ready:
            ray.get(ref)  # an owner that failed to start raises here
            del pending[ref]
        if pending:  # a cold start compiles kernels for minutes; an owner Ray cannot place waits for CPUs
            log.warning("owners %s not started yet: each needs %g CPU, the cluster has %g free", sorted(pending.values()),
                        settings.owner_cpus, ray.available_resources().get("CPU", 0.0))


def start(settings: ClusterSettings) -> ClusterSettings:
    """Run the app on the connected cluster, answering on settings.host:settings.port; the settings it
    runs with (`server.cluster.claims.fitted`: `ClaimsDoNotFit` when they cannot be placed)."""
    settings = fitted(settings, node_cpus())
    start_owners(settings)
    serve.start(http_options={"host": settings.host, "port": settings.port})
    serve.run(application(settings), name=APP_NAME, route_prefix="/")
    return settings


def close_owners(settings: ClusterSettings) -> None:
    """Snapshot every owner's sessions (a graceful stop), skipping owners that are not running."""
    refs = []
    for shard in range(settings.owners):
        try:
            refs.append(ray.get_actor(owner_name(shard), namespace=settings.namespace).close.remote())
        except ValueError:
            continue
    for ref in refs:
        try:
            ray.get(ref, timeout=120)
        except Exception as exc:  # one owner that cannot snapshot must not stop the others
            log.error("an owner did not close: %s", exc)


def serve_forever(settings: ClusterSettings, address: str | None = None) -> int:
    """``canonical serve --cluster``: start (or join) the cluster, run the app until SIGINT/SIGTERM,
    then snapshot the owners' sessions and stop the app."""
    connect(address, namespace=settings.namespace)
    try:
        settings = start(settings)
    except BaseException:
        ray.shutdown()
        raise
    log.warning("serving on http://%s:%d with %d owners of %g CPU and %d-%d ingress replicas of %g CPU on %g CPUs "
                "(data in %s)", settings.host, settings.port, settings.owners, settings.owner_cpus,
                settings.ingress_min_replicas, settings.ingress_max_replicas, settings.ingress_cpus, sum(node_cpus()),
                settings.data_dir)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    # timed: a signal that one of Ray's threads receives runs its Python handler only once this thread
    # wakes up, which an untimed wait never does (SIGTERM, Docker's and Kubernetes' stop, went unanswered)
    while not stop.wait(0.5):
        pass
    serve.delete(APP_NAME)  # first no new requests (those in flight finish), then the owners' snapshots
    close_owners(settings)
    # detached owners outlive this process on a cluster it joined: a stopped service leaves none behind
    stop_owners(running_owners(settings.namespace), "the service stopped")
    ray.shutdown()
    return 0


def app_builder(args: dict):
    """Serve config entry point (``import_path: server.cluster.serve:app_builder``, e.g. KubeRay's
    RayService): ``args`` are `ClusterSettings` fields; the rest come from ``CANONICAL_*`` variables.
    An unset ``owner_cpus`` is fitted to the nodes there are now; a set one is taken as it is (an
    autoscaler adds the nodes that claims wait for)."""
    settings = ClusterSettings(**args)
    return application(fitted(settings, node_cpus()) if settings.owner_cpus is None else settings)
