"""Who may send on the bench's hub: a per-run secret, and the DBC's transmitters.

The supervisor (``hil run``) makes a secret per run and hands it to the hub and to its nodes
in the environment (``HIL_HUB_SECRET``, hex), never on a command line. A node authenticates in
its bus request with ``hil_node`` (its DBC node name) and ``hil_token`` (HMAC-SHA256 of that
name under the secret); the hub then relays only the messages the DBC names that node the
transmitter of (``BO_ ... <sender>``; the plant also speaks for the simulation's ``SIM``).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from typing import Optional

SECRET_ENV = "HIL_HUB_SECRET"
# which DBC transmitters a bench node may speak for (the plant also sends the simulation's)
# (TESTER: a UDS tester, python -m hil diag: DIAG_REQUEST alone)
NODE_SENDERS = {"PLANT": ("PLANT", "SIM"), "ECU": ("ECU",), "APP": ("APP",),
                "TESTER": ("TESTER",)}


def node_token(secret: bytes, node: str) -> str:
    return hmac.new(secret, b"hil.hub node " + node.encode(), hashlib.sha256).hexdigest()


def credentials(node: Optional[str], secret: Optional[bytes] = None) -> dict:
    """The bus-request fields that make a hub client ``node``: with ``secret``, else the one
    in the environment (none without either)."""
    if secret is None:
        env = os.environ.get(SECRET_ENV)
        secret = bytes.fromhex(env) if env else None
    if node is None or not secret:
        return {}
    return {"hil_node": node, "hil_token": node_token(secret, node)}


def dbc_senders(path=None) -> dict[str, frozenset]:
    """node -> the frame IDs the DBC names it (or the simulation, for the plant) the
    transmitter of."""
    from hil.transport.codec import DBC_PATH, load_dbc

    db = load_dbc(path or DBC_PATH)
    return {node: frozenset(m.frame_id for m in db.messages if set(m.senders) & set(names))
            for node, names in NODE_SENDERS.items()}
