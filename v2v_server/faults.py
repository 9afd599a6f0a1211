"""One log line per cause of a fault: what every stage that meets a failing volume, folder or
device uses so that a fault met on every video or every tick is one line (its count kept by a
counter). Below every stage of the server, as ``checks`` is."""
from __future__ import annotations

import logging

_warned: set = set()


def warn_once(logger: logging.Logger, key: tuple, msg: str, *args) -> bool:
    """Log ``msg % args`` as a warning the first time this process meets ``key`` (a cause: what
    failed and the errno's name), nothing after: a fault met on every video or every tick is
    one line, its count kept by a counter. Returns whether it logged."""
    if key in _warned:
        return False
    _warned.add(key)
    logger.warning(msg, *args)
    return True


def cause_of(e: BaseException) -> str:
    """The errno's name of an ``OSError`` (``ENOTDIR``), else the exception's class name."""
    import errno

    n = getattr(e, "errno", None)
    return errno.errorcode.get(n, type(e).__name__) if n else type(e).__name__
