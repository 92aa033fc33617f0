"""Test helpers, one copy each (no tests here). Import them as ``from tests.support import ...``;
the shared fixtures (``procs``, ``pca_file``, ``closer``) live in ``tests/conftest.py``.

* :mod:`tests.support.processes`: ``python -m apps.cli`` children (:func:`cli_cmd`,
  :func:`start_cli`, :class:`Proc`), their environment (:func:`proc_env`), teardown
  (:func:`stop_process`, :func:`stop_all`) and waits (:func:`wait_for`, :func:`wait_log`).
* :mod:`tests.support.roles`: the rayfronts roles' arguments and clients (:func:`edge_args`,
  :func:`mapper_args`, :func:`client`, :func:`mapped`, :func:`fit_pca`, :func:`zenoh_client_config`).
* :mod:`tests.support.ports`: :func:`free_port`, :func:`port_is_free`, :func:`dead_endpoint`.
* :mod:`tests.support.netns`: :func:`ip`, :func:`network_namespaces` (root and iproute2).
* :mod:`tests.support.zenoh_agent`: a Zenoh session in a child process (:class:`Agent`,
  :class:`Router`, :func:`await_route`, :func:`get_replies`, :func:`lget_keys`).
* :mod:`tests.support.rosbag_data`: ROS 2 messages and the hand-written bag of the bag tests.
* :mod:`tests.support.data`: small generators and oracles (:func:`low_rank_pca`,
  :func:`bfs_components`, :func:`query_map`).
* :mod:`tests.support.snapshots`: :class:`ChangingMap`, a query copy synced over map changes.

The last four import rosbags / zenoh / torch: import them from their modules.
"""
from tests.support.netns import ip, network_namespaces
from tests.support.ports import dead_endpoint, free_port, port_is_free
from tests.support.processes import (
    ROOT,
    Proc,
    cli_cmd,
    proc_env,
    start_cli,
    stop_all,
    stop_process,
    text_cache_dir,
    wait_for,
    wait_log,
)
from tests.support.roles import (
    FAST_MAP,
    RES,
    client,
    edge_args,
    fit_pca,
    mapped,
    mapper_args,
    zenoh_client_config,
)

__all__ = [
    "FAST_MAP", "RES", "ROOT", "Proc", "cli_cmd", "client", "dead_endpoint", "edge_args", "fit_pca",
    "free_port", "ip", "mapped", "mapper_args", "network_namespaces", "port_is_free", "proc_env", "start_cli",
    "stop_all", "stop_process", "text_cache_dir", "wait_for", "wait_log", "zenoh_client_config",
]
