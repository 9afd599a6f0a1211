"""A deterministic simulator of the whole delivery path (docs/simulator.md).

The REAL delivery core (``v2v_server.delivery``: scheduler, ledger, batcher, journal) and the
REAL client protocol objects (``v2v_client.session.ServerSession`` and ``HeldBatches``, the
resume state ``v2v_client.endpoint.ConsumerRecord``, ``StreamLoader``'s receipts) run under a
seeded scheduler, a simulated clock and a simulated network, with trainers, DDP ranks and
DataLoader workers that pause, die and resume, servers that stall and crash, and hostile
clients; the invariants are checked after every step (``oracle.py``).

``python -m harness.delivery_sim --scenario NAME --seed N --trace`` replays one seed.
"""
