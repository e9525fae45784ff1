"""The Ray instance or cluster that a run's Ray workers run on: a cluster that
``RAY_ADDRESS`` names, or a Ray instance started in this process."""

from __future__ import annotations

import os
import socket
import sys

from rl_pg._process import signal_handlers_kept

__all__ = ["start_ray"]


def start_ray(workers: int) -> bool:
    """Connects to the Ray cluster ``RAY_ADDRESS`` names, which brings its own resources,
    or else starts a Ray instance of ``workers`` CPUs in this process (never another
    instance found running on this machine); True if it started one."""
    import ray

    if ray.is_initialized():
        return False
    # Actors import the recipe's make_env the way this process does: they need its
    # sys.path. Their output stays in Ray's logs: Ray would prefix every line of it with
    # the collector's repr, dozens of lines each (an actor's error still reaches here).
    path = os.pathsep.join(sys.path)
    address = os.environ.get("RAY_ADDRESS", "")
    if not address:
        # A local instance's processes inherit this environment, so the path goes there
        # rather than into a runtime_env: Ray would set up a worker process of its own
        # for each actor and leave the ones it starts with (one per CPU) idle.
        previous = os.environ.get("PYTHONPATH")
        os.environ["PYTHONPATH"] = path
        try:
            with signal_handlers_kept():  # Ray's own would lose the run's stop
                ray.init(address="local", num_cpus=workers, include_dashboard=False,
                         log_to_driver=False)  # fmt: skip
        finally:
            if previous is None:
                del os.environ["PYTHONPATH"]
            else:
                os.environ["PYTHONPATH"] = previous
        return True
    _check_reachable(address)
    with signal_handlers_kept():
        ray.init(address=address, log_to_driver=False,
                 runtime_env={"env_vars": {"PYTHONPATH": path}})  # fmt: skip
    nodes = [node for node in ray.nodes() if node["Alive"]]
    cpus = sum(node["Resources"].get("CPU", 0) for node in nodes)
    print(
        f"Ray: collecting on the cluster at {address} ({len(nodes)} nodes, {cpus:g} CPUs; "
        f"each worker takes one CPU).",
        file=sys.stderr,
    )
    return False


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fails at once, naming ``RAY_ADDRESS``, when nothing answers at its ``host:port``
    (Ray itself retries in silence for minutes). Other forms (``auto``, ``ray://``) are
    left to Ray."""
    host, _, port = address.rpartition(":")
    if not host or "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as err:
        raise ConnectionError(
            f"RAY_ADDRESS={address}: nothing answers there ({err}). Start the cluster's "
            f"head with `ray start --head --port {port}` on {host}, correct RAY_ADDRESS, or "
            f"unset it to collect on a Ray instance of this process."
        ) from None
