"""Where the cells of ``fdmo bench`` run: a pool on this machine, or Ray (a local instance or a cluster).

Both run the same task (``app.bench.cell.run_cell``, one CPU each: every cell is a single-threaded process)
and yield its rows as they finish; the bench orders them as the matrix does, so the table does not depend on
which ran where or first. Ray is an optional extra, imported only here and only when asked for; vo_core never
imports it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Any

from app.bench.cell import CellJob, run_cell, stop_running_cells
from vo_core.errors import InputError

LOCAL_RAY = "auto"  # --ray auto: a Ray instance on this machine, for this bench only
LOCAL_HOST = "127.0.0.1"  # what a local Ray instance listens on: this machine only
RAY_INSTALL_HINT = 'pip install -e ".[cluster]"'
RAY_CLUSTER_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # Ray's ray_constants.ENABLE_RAY_CLUSTER


def run_in_pool(jobs: list[CellJob], workers: int) -> Iterator[dict[str, Any]]:
    """``workers`` cells at a time on this machine. Each cell is a process of its own, so a thread per cell that
    waits for it is all the pool needs; on Ctrl-C the running cells are stopped and their threads joined."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending = {pool.submit(run_cell, job) for job in jobs}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield future.result()
        finally:
            for future in pending:
                future.cancel()
            stop_running_cells()


def run_on_ray(jobs: list[CellJob], address: str, workers: int) -> Iterator[dict[str, Any]]:
    """The cells as Ray tasks of one CPU each, on a local instance (``auto``, ``workers`` CPUs, bound to
    127.0.0.1, no dashboard) or on the cluster at ``address``; on Ctrl-C the tasks still running are cancelled
    (their cells stopped) and the instance shut down."""
    ray = import_ray(local=address == LOCAL_RAY)
    if address == LOCAL_RAY:
        ray.init(num_cpus=workers, include_dashboard=False, _node_ip_address=LOCAL_HOST, log_to_driver=False,
                 configure_logging=False)
    else:
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    remote_cell = ray.remote(num_cpus=1, max_retries=0)(run_cell)
    pending = [remote_cell.remote(job) for job in jobs]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        for reference in pending:
            ray.cancel(reference)  # KeyboardInterrupt in the task: run_cell stops its cell
        if pending:
            ray.wait(pending, num_returns=len(pending), timeout=15.0)
        ray.shutdown()


def import_ray(local: bool = False):
    """Ray, or a one-line error saying how to install it. ``local``: for an instance on this machine only. Ray
    takes 127.0.0.1 as it is given only where it supports no cluster (Windows, macOS); elsewhere it replaces it by
    the machine's address and its servers listen on every interface. Its switch for that case, set before it is
    imported, makes every server of the instance listen on 127.0.0.1 (tests/test_bench.py checks it)."""
    if local:
        os.environ[RAY_CLUSTER_SWITCH] = "0"
    try:
        import ray
    except ImportError:
        raise InputError(f"--ray: Ray is not installed (it is an optional extra: {RAY_INSTALL_HINT})") from None
    return ray
