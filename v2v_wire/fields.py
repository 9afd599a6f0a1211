"""Reading the fields of a decoded message: one rule per kind of field for every typed message
of the wire (worker <-> server in ``worker_messages``, server <-> client in ``plan_messages``). An error names the message and the field and shows what came,
cut to 60 characters, so a bad peer's message is one readable log line."""
from __future__ import annotations

from typing import Optional, Tuple, Type

from v2v_wire.protocol import ProtocolError

_ITEM_NAMES = {str: "strings", dict: "maps", int: "integers"}


def show(v) -> str:
    """``repr(v)``, at most 60 characters (longer ones end in ``...``)."""
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


class FieldReader:
    """Reads fields of a decoded message (a dict from msgpack), raising ``error``.

    Args:
        error: the ``ProtocolError`` subclass raised, whose text is ``"<kind> message: field
            '<name>' must be <what>, got <value>"``.
    """

    def __init__(self, error: Type[ProtocolError]):
        self.error = error

    def bad(self, kind: str, name: str, want: str, v) -> ProtocolError:
        """The error for field ``name`` of a ``kind`` message that is not ``want``."""
        return self.error(f"{kind} message: field {name!r} must be {want}, got {show(v)}")

    def integer(self, h: dict, kind: str, name: str, lo: int = 0, default=None) -> int:
        """``h[name]`` (``default`` when absent): an integer in ``[lo, 2**63)``, never a bool."""
        v = h.get(name, default)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v < 2 ** 63:
            raise self.bad(kind, name, f"an integer >= {lo}", v)
        return v

    def string(self, h: dict, kind: str, name: str, field_name: Optional[str] = None) -> str:
        """``h[name]``: a string (``field_name``: how the error names it, default ``name``)."""
        v = h.get(name)
        if not isinstance(v, str):
            raise self.bad(kind, field_name or name, "a string", v)
        return v

    def optional_string(self, h: dict, kind: str, name: str) -> Optional[str]:
        """``h[name]``: a string, or None when absent or null."""
        v = h.get(name)
        if v is not None and not isinstance(v, str):
            raise self.bad(kind, name, "a string or absent", v)
        return v

    def items(self, h: dict, kind: str, name: str, item: type, default=None) -> Tuple:
        """``h[name]`` (``default`` when absent): a list of ``item`` s (never bools), as a tuple."""
        v = h.get(name, default)
        if not isinstance(v, (list, tuple)) or not all(isinstance(x, item) and not isinstance(x, bool) for x in v):
            raise self.bad(kind, name, f"a list of {_ITEM_NAMES.get(item, item.__name__)}", v)
        return tuple(v)

    def mapping(self, h: dict, kind: str, name: str, values: Optional[tuple] = None) -> dict:
        """``h[name]`` (empty when absent): a map with string keys and, when ``values`` is given,
        values of those types (never a bool)."""
        v = h.get(name, {})
        if not isinstance(v, dict) or not all(isinstance(k, str) and (values is None or isinstance(x, values)
                                                                      and not isinstance(x, bool))
                                              for k, x in v.items()):
            want = "a map of strings to " + ("anything" if values is None else "/".join(t.__name__ for t in values))
            raise self.bad(kind, name, want, v)
        return v
