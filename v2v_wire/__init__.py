"""The wire contract that servers and clients share: messages and their limits (``protocol``,
``plan_messages``, ``worker_messages``), an epoch's plan and its shards (``plan``,
``plan_shards``), the per-array compression (``codecs``), sample ids (``ids``) and the tracked
flow's grid and its expansion (``flowgrid``). Needs numpy and msgpack only; the codecs' libraries
are optional. ``commands`` (standard library only) is where every ``v2v-*`` console script starts,
before any package of a command is imported."""
