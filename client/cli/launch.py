"""The service as a child process, the same ``canonical serve`` a user runs: a port for it and the wait
for its /healthz. ``demo`` uses them, and so do the tests and benchmarks that need a real service."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import httpx


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def unclaimed_port() -> int:
    """A free loopback port below the kernel's ephemeral range, for a server that binds it later while
    other processes start (a Ray cluster's GCS, raylets and workers take ephemeral ports as they
    start, so a free ephemeral port picked before them may be taken by then)."""
    import random
    import socket

    low = 32768
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low = int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        pass
    for port in random.Random().sample(range(max(1024, low - 12000), low), 200):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port below {low}")


def wait_until_healthy(url: str, proc, timeout: float) -> None:
    """Poll ``url``/healthz until it answers 200; RuntimeError if ``proc`` exits or ``timeout`` s pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with code {proc.returncode} before it was ready")
        try:
            if httpx.get(f"{url}/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"the service did not become ready within {timeout:g} s")


def start_service(port: int, data_dir: Path):
    """The service as a child process (the same `canonical serve` a user runs); waits for /healthz.
    A relative ``data_dir`` is the caller's: it is resolved here, as the child runs in the project's folder."""
    import subprocess

    data_dir = Path(data_dir).resolve()
    proc = subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--port", str(port), "--data-dir", str(data_dir),
                             "--log-level", "warning"], cwd=Path(__file__).resolve().parents[2])
    try:
        wait_until_healthy(f"http://127.0.0.1:{port}", proc, timeout=120.0)
    except RuntimeError as exc:
        proc.kill()
        raise SystemExit(str(exc)) from None
    return proc
