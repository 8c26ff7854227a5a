"""A throw-away Ray cluster on this machine: a head node and worker nodes started with ``ray start``, as a
lab starts them on its own machines, each in its own process group so that stopping it stops every
process it started."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

READY_POLLS = 600  # state probes at most while a node joins (each probe waits on Ray itself)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _ray_command() -> str:
    return str(Path(sys.executable).with_name("ray"))


# A throw-away cluster on loopback: no token authentication (Ray enables it by default for ``ray start``;
# a lab's cluster keeps it, and its clients find the token as any Ray client does).
# A loaded machine starts a raylet slowly: Ray's default wait for it is too short there.
CLUSTER_ENVIRONMENT = {
    "RAY_AUTH_MODE": "disabled",
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_raylet_start_wait_time_s": "300",
}


def _start_node(arguments: list[str], temp_dir: Path, log: Path) -> subprocess.Popen:
    environment = {**os.environ, **CLUSTER_ENVIRONMENT}
    environment.pop("RAY_ADDRESS", None)
    return subprocess.Popen(
        [_ray_command(), "start", "--block", "--disable-usage-stats", *arguments],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        env=environment,
        cwd=temp_dir,
        start_new_session=True,
    )


def _alive_cpus(address: str) -> float:
    """CPUs of the cluster's live nodes, asked of the cluster's own state API (-1 when not reachable)."""
    probe = (
        "import ray, sys\n"
        "ray.init(address=sys.argv[1], log_to_driver=False)\n"
        "print(sum(n['Resources'].get('CPU', 0) for n in ray.nodes() if n['Alive']))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe, address],
        capture_output=True,
        text=True,
        env={**os.environ, **CLUSTER_ENVIRONMENT},
    )
    try:
        return float(result.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return -1.0


def _wait_for_cpus(address: str, wanted: float, nodes: list[subprocess.Popen], temp_dir: Path) -> None:
    """Return once the cluster's live nodes hold ``wanted`` CPUs; raise with the nodes' logs if one exits."""
    for _ in range(READY_POLLS):
        if any(node.poll() is not None for node in nodes):
            logs = "\n".join(p.read_text(errors="replace")[-2000:] for p in temp_dir.glob("*.log"))
            raise RuntimeError(f"a Ray node exited while starting:\n{logs}")
        if _alive_cpus(address) >= wanted:
            return
    raise RuntimeError(f"the Ray cluster at {address} did not reach {wanted} CPUs")


def _stop(node: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(node.pid, signal.SIGTERM)
    try:
        node.wait(timeout=60)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(node.pid, signal.SIGKILL)
        node.wait()


@contextlib.contextmanager
def ray_cluster(worker_nodes: int = 1, cpus_per_node: int = 1, head_cpus: int | None = None) -> Iterator[str]:
    """Start a head node of ``head_cpus`` CPUs (default ``cpus_per_node``) and ``worker_nodes`` worker nodes
    of ``cpus_per_node`` CPUs; yield the head's address (``host:port``) once every node has joined; stop
    them all on exit. While it runs, this process's environment lets a Ray client join it."""
    head_cpus = cpus_per_node if head_cpus is None else head_cpus
    # A short folder of its own: Ray's socket paths must fit in 107 bytes, and no other Ray shares it.
    temp_dir = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))
    port = _free_port()
    address = f"127.0.0.1:{port}"
    saved = {name: os.environ.get(name) for name in CLUSTER_ENVIRONMENT}
    os.environ.update(CLUSTER_ENVIRONMENT)
    nodes = [
        _start_node(
            [
                "--head",
                f"--port={port}",
                f"--num-cpus={head_cpus}",
                "--num-gpus=0",
                "--include-dashboard=false",
                f"--temp-dir={temp_dir}",
            ],
            temp_dir,
            temp_dir / "head.log",
        )
    ]
    try:
        # One node at a time, each joined before the next starts: nodes starting together on one small
        # machine can time out waiting for each other.
        _wait_for_cpus(address, head_cpus, nodes, temp_dir)
        for k in range(worker_nodes):
            nodes.append(
                _start_node(
                    [f"--address={address}", f"--num-cpus={cpus_per_node}", "--num-gpus=0"],
                    temp_dir,
                    temp_dir / f"worker-{k}.log",
                )
            )
            _wait_for_cpus(address, head_cpus + cpus_per_node * (k + 1), nodes, temp_dir)
        yield address
    finally:
        for node in reversed(nodes):
            _stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
