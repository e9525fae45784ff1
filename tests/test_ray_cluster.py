"""Training with Ray workers on a two-node cluster (both nodes on this host)."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray_node(args: list[str], env: dict) -> subprocess.Popen:
    """A Ray node that lives as long as its process (``ray start --block``)."""
    ray = shutil.which("ray", path=os.path.dirname(sys.executable)) or "ray"
    return subprocess.Popen(
        [ray, "start", "--block", "--disable-usage-stats", *args],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # stopped as a group, its own processes included
    )


def _stop(node: subprocess.Popen) -> None:
    if node.poll() is None:
        os.killpg(node.pid, signal.SIGTERM)
        try:
            node.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait()


def _nodes(address: str, env: dict) -> int:
    code = "import ray; ray.init(address=%r); print(len([n for n in ray.nodes() if n['Alive']]))"
    out = subprocess.run(
        [sys.executable, "-c", code % address], env=env, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    return int(out.stdout.strip() or 0)


def _failure(result: subprocess.CompletedProcess, temp_dir: Path) -> str:
    """The run's last output, then what Ray's workers printed beyond their headers (a
    crashed actor's own error is only there) and the raylets' lines on dead workers."""
    parts = [result.stderr[-3000:]]
    for log in sorted(temp_dir.glob("session_latest/logs/worker-*.err")):
        lines = [line for line in log.read_text(errors="replace").splitlines()
                 if line and not line.startswith((":job_id:", ":actor_name:"))]  # fmt: skip
        if lines:
            parts.append(f"--- {log.name}\n" + "\n".join(lines[-40:]))
    for log in sorted(temp_dir.glob("session_latest/logs/raylet*.out")):
        words = ("exit", "kill", "died", " e ")  # and errors (level E)
        lines = [line for line in log.read_text(errors="replace").splitlines()
                 if not line.startswith("[state-dump]")
                 and any(word in line.lower() for word in words)]  # fmt: skip
        if lines:
            parts.append(f"--- {log.name}\n" + "\n".join(lines[-20:]))
    return "\n".join(parts)[-12000:]


# A driver on the cluster: two evaluation actors, which spread over its nodes.
SPREAD = """
import ray
from functools import partial
from rl_pg.envs import GridWorldEnv
from rl_pg.episode_workers import EpisodeWorkers
from rl_pg.evaluation import evaluate
from torchrl.envs.utils import RandomPolicy
ray.init(address=%r, log_to_driver=False)
env = EpisodeWorkers([partial(GridWorldEnv, max_steps=20)] * 2, backend="ray")
result = evaluate(RandomPolicy(env.action_spec), env, episodes=4)
print(len(set(env.nodes)), result["mean_length"])
print([(n["NodeID"][:8], n["Resources"].get("CPU")) for n in ray.nodes() if n["Alive"]])
env.close()
"""


@pytest.mark.cluster
def test_training_and_evaluation_spread_their_workers_over_two_nodes(tmp_path):
    # Short: Ray's sockets live under the temporary directory (a path limit of ~100).
    temp_dir = Path(tempfile.mkdtemp(prefix="rl"))
    port = _free_port()
    address = f"127.0.0.1:{port}"
    # Ray 2.60 joins a second node only with token authentication and a shared token.
    env = {
        **os.environ,
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(16),
        "RAY_ADDRESS": "",
    }
    head = _ray_node(
        ["--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
         f"--temp-dir={temp_dir}"],
        env,
    )  # fmt: skip
    nodes = [head]
    try:
        deadline = time.monotonic() + 60
        while _nodes(address, env) < 1:
            assert head.poll() is None and time.monotonic() < deadline, "the head did not start"
            time.sleep(1)
        nodes.append(_ray_node([f"--address={address}", "--num-cpus=1"], env))
        while _nodes(address, env) < 2:
            assert nodes[1].poll() is None and time.monotonic() < deadline, "no second node"
            time.sleep(1)
        # Each worker takes one CPU and each node has one: one worker on each node.
        run = tmp_path / "run"
        result = subprocess.run(
            [sys.executable, "-m", "rl_pg.app", "train", "cartpole", "--ray",
             "--workers", "2", "--total-frames", "3000", "--eval-episodes", "2",
             "--run-dir", str(run), "--no-progress"],
            env={**env, "RAY_ADDRESS": address}, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert result.returncode == 0, _failure(result, temp_dir)
        assert "(2 nodes, 2 CPUs" in result.stderr, result.stderr[-3000:]
        summary = json.loads((run / "summary.json").read_text())
        assert summary["frames"] >= 3000
        # Evaluation workers (Ray actors that reserve no CPU) spread over the nodes too.
        spread = subprocess.run(
            [sys.executable, "-c", SPREAD % address], env=env, capture_output=True, text=True,
            timeout=300,
        )  # fmt: skip
        assert spread.returncode == 0, _failure(spread, temp_dir)
        spread_over, length = spread.stdout.splitlines()[0].split()
        assert spread_over == "2" and 1 <= float(length) <= 20, spread.stdout
        # MetaDrive, the slow simulator: collection and evaluation both on the cluster.
        pytest.importorskip("metadrive")
        run = tmp_path / "metadrive"
        result = subprocess.run(
            [sys.executable, "-m", "rl_pg.app", "train", "metadrive", "--ray",
             "--workers", "2", "--total-frames", "512", "--eval-interval", "512",
             "--eval-episodes", "2", "--horizon", "40", "--run-dir", str(run), "--no-progress"],
            env={**env, "RAY_ADDRESS": address}, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert result.returncode == 0, _failure(result, temp_dir)
        summary = json.loads((run / "summary.json").read_text())
        assert summary["frames"] >= 512 and summary["eval_mean_return"] is not None
        assert summary["eval_mean_route_completion"] is not None  # scored on the cluster
    finally:
        for node in reversed(nodes):
            _stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)


def test_a_cluster_address_where_nothing_answers_is_named_in_one_line(tmp_path):
    address = f"127.0.0.1:{_free_port()}"  # nothing listens there
    result = subprocess.run(
        [sys.executable, "-m", "rl_pg.app", "train", "cartpole", "--ray", "--workers", "2",
         "--total-frames", "2000", "--run-dir", str(tmp_path / "run"), "--no-progress"],
        env={**os.environ, "RAY_ADDRESS": address}, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode != 0
    assert f"RAY_ADDRESS={address}: nothing answers there" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
