"""The wire contract that servers and clients share: messages and their limits (``protocol``,
``messages``), the per-array compression (``codecs``), sample ids (``ids``) and the tracked
flow's grid and its expansion (``flowgrid``). Needs numpy and msgpack only; the codecs' libraries
are optional. ``commands`` (standard library only) is where every ``v2v-*`` console script starts,
before any package of a command is imported."""
