"""pytest plugin: run exactly the node ids listed in ``$REPLAY_FILE``, in that order.

Replays a failing random order (pytest-randomly) without the plugin that made it, so the
tests before a failure can be bisected::

    python -m pytest --collect-only -q -p randomly --randomly-seed=2026 | grep :: > order.txt
    REPLAY_FILE=order.txt PYTHONPATH=scripts python -m pytest -q -p replay_order
"""
import os


def pytest_collection_modifyitems(session, config, items):
    """Keep the listed items, in the file's order; deselect the rest."""
    with open(os.environ["REPLAY_FILE"]) as fh:
        order = [ln.rstrip("\n") for ln in fh if ln.strip()]
    rank = {nid: i for i, nid in enumerate(order)}
    config.hook.pytest_deselected(items=[it for it in items if it.nodeid not in rank])
    items[:] = sorted((it for it in items if it.nodeid in rank), key=lambda it: rank[it.nodeid])
