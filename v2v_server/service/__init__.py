"""The ZeroMQ service that wires the pure parts to processes and sockets: the server loop, the
worker processes and their pool, sockets, shared-memory batches, the in-process server."""
