"""Ingest and expansion through an existing Ray cluster (a head node and a worker node started with
``ray start``, joined through ``RAY_ADDRESS`` and through ``--ray-address``) write the same bytes as the
local executor, and the cluster is joined as it is (its two nodes, not a local Ray of ``workers`` CPUs).

Each cluster run has a fresh interpreter as its driver, as a lab's command has: a process that has already
started and shut down a local Ray (other tests of the suite do) loses its connection to a cluster it joins
afterwards (its tasks report ``OwnerDiedError``, its driver "Failed to connect to GCS")."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from helpers.custom_capture import dataset_bytes, ingest, make_capture
from helpers.ray_cluster import ray_cluster
from helpers.sphere_world import build_sphere_world

from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion

pytest.importorskip("ray", reason="the ray extra is not installed")

# Starting a two-node cluster takes about a minute on a two-core machine; the module runs when asked.
if os.environ.get("RELIGHTANYONE_RAY_CLUSTER_TESTS") != "1":
    pytest.skip(
        "starts a Ray cluster with `ray start` (about a minute); run it with "
        "RELIGHTANYONE_RAY_CLUSTER_TESTS=1 pytest tests/test_ray_cluster.py",
        allow_module_level=True,
    )

pytestmark = [pytest.mark.ray, pytest.mark.usefixtures("one_torch_thread", "ray_exclusive")]

TESTS = Path(__file__).resolve().parent

# Printed by every driver after its run: what the cluster it joined holds.
REPORT_CLUSTER = """
import json, ray
print(json.dumps({"cpus": ray.cluster_resources()["CPU"],
                  "nodes": len([n for n in ray.nodes() if n["Alive"]])}))
ray.shutdown()
"""


def run_driver(code: str, *arguments: str, ray_address: str | None = None) -> dict:
    """Run ``code`` in a fresh Python (tests/ on its path, ``RAY_ADDRESS`` as given, one torch thread)
    and return the JSON object on its last output line."""
    search_path = [str(TESTS), *filter(None, [os.environ.get("PYTHONPATH")])]
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(search_path)}
    environment.pop("RAY_ADDRESS", None)
    if ray_address is not None:
        environment["RAY_ADDRESS"] = ray_address
    environment["OMP_NUM_THREADS"] = "1"
    script = textwrap.dedent(code) + REPORT_CLUSTER
    result = subprocess.run(
        [sys.executable, "-c", script, *arguments], capture_output=True, text=True, env=environment
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def assert_joined_as_it_is(cluster: dict) -> None:
    """The cluster's two one-CPU nodes, not a local Ray of ``workers`` CPUs on one node."""
    assert cluster == {"cpus": 2, "nodes": 2}


@pytest.fixture(scope="module")
def cluster(ray_exclusive):
    with ray_cluster(worker_nodes=1, cpus_per_node=1) as address:
        yield address


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("cluster") / "capture", subjects=("s1", "s2", "s3"))


def test_ingest_through_a_cluster_from_ray_address_gives_the_local_bytes(cluster, capture, tmp_path):
    reference = dataset_bytes(ingest(capture, tmp_path / "local").path)
    joined = run_driver(
        """
        import sys
        from pathlib import Path
        from helpers.custom_capture import ingest
        ingest(Path(sys.argv[1]), Path(sys.argv[2]), workers=2, executor="ray")
        """,
        str(capture),
        str(tmp_path / "cluster"),
        ray_address=cluster,
    )
    assert_joined_as_it_is(joined)
    assert dataset_bytes(tmp_path / "cluster" / "custom") == reference


def test_the_ingest_command_joins_the_cluster_named_by_ray_address(cluster, capture, tmp_path):
    reference = dataset_bytes(ingest(capture, tmp_path / "local").path)
    joined = run_driver(
        """
        import sys
        from relightanyone.cli import cli
        cli.main(sys.argv[1:], standalone_mode=False)
        """,
        *["ingest", "custom", str(capture), "--template", str(capture / "template.obj")],
        *["--out", str(tmp_path / "cluster"), "--preset", "tiny", "--workers", "2"],
        *["--executor", "ray", "--ray-address", cluster],
    )
    assert_joined_as_it_is(joined)
    assert dataset_bytes(tmp_path / "cluster" / "custom") == reference


def _hashes(folder: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()
    }


def test_expansion_through_a_cluster_gives_the_local_bytes(cluster, tmp_path):
    world = build_sphere_world(tmp_path / "world", flat=True)
    local = plan_expansion(
        world["flat"],
        world["stage1"],
        world["stage2"],
        tmp_path / "local",
        fit_iterations=(40, 10),
        device="cpu",
    )
    expand_dataset(local, progress=False)
    joined = run_driver(
        """
        import sys
        from pathlib import Path
        from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion
        flat, stage1, stage2, parent = map(Path, sys.argv[1:5])
        plan = plan_expansion(flat, stage1, stage2, parent, fit_iterations=(40, 10), device="cpu")
        expand_dataset(plan, workers=2, executor="ray", progress=False)
        """,
        *(str(world[name]) for name in ("flat", "stage1", "stage2")),
        str(tmp_path / "cluster"),
        ray_address=cluster,
    )
    assert_joined_as_it_is(joined)
    output = local.settings.output.relative_to(tmp_path / "local")
    assert _hashes(tmp_path / "cluster" / output) == _hashes(local.settings.output)
