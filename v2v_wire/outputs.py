"""The per-output array contract: one :class:`ArraySpec` per array a sample can carry.

Everything that decides an output's name, wire dtype, shape, channel axis or float conversion
reads this table: the workers narrowing a sample's arrays (``wire_dtype``), the Ray rows
(``column_dtype``, ``row_array``), the shared-memory slot sizing (``max_sample_bytes``), the
client's conversion to tensors (``float_divisor``, ``channel_axis``) and the trainer's collate.
Adding an output is one entry here plus its producer (``v2v_server.samples.make``).

Shapes are per sample, in the recipe's terms: ``L`` = sequence length (voxel grids per
sample), ``B`` = num_bins (temporal bins per voxel grid), ``S`` = crop size (pixels; H = W = S),
``n`` = points per side of a tracked flow option's grid; a batch adds a leading axis.

============== =============== ============================== =================================
array          wire dtype      shape (per sample, on the wire) on the client (``raw=False``)
============== =============== ============================== =================================
voxels         int8/16/32 [1]  (L, B, S, S)                   float32 signed event counts
frames         uint8           (L + 1, S, S) [2]              float32 in [0, 1] (/ 255)
flow           float16/32 [3]  (L, 2, S, S) (x, y) pixels     float32
polarity_counts uint8 [4]      (L, 2, B, S, S)                float32 counts
flow_grid      float32         (L, 2, n, n) carries ``flow``  expanded to dense ``flow`` [5]
============== =============== ============================== =================================

[1] the narrowest that holds every count of the sample (batch), never wrapped or clipped;
[2] the client and the Ray rows insert a channel axis: (L + 1, 1, S, S);
[3] the recipe's ``flow_dtype``;
[4] N+ (channel 0, positive) and N- (channel 1, negative) of each bin (Lou et al. 2025,
Sec. 3: the counts whose difference N+ - N- is the voxel), saturating at 255; opt-in;
[5] bilinear with ``protocol.flow_grid_taps`` (``v2v_client.flowgrid``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Mapping, Optional, Tuple

import numpy as np

__all__ = ["ArraySpec", "ARRAYS", "OUTPUTS", "DEFAULT_OUTPUTS", "ARRAY_OUTPUT", "output_of", "spec_of",
           "wire_dtype", "narrowest", "max_sample_bytes", "row_array", "zeros_row", "wire_row", "wire_zeros_row", "column_outputs",
           "narrow_int_dtype"]


@dataclass(frozen=True)
class ArraySpec:
    """One array of a sample on the wire.

    Attributes:
        name: the array's name on the wire.
        output: the output (``OUTPUTS``) it carries: its own name, or the output it is a compact
            form of (``flow_grid`` carries ``flow``).
        dtypes: wire dtypes it may have, narrowest first.
        narrowing: how a producer picks among ``dtypes``: ``"counts"`` the narrowest that holds
            every value (integers; never wrapped), ``"recipe"`` the recipe's ``flow_dtype``,
            ``"fixed"`` always ``dtypes[0]``.
        axes: the per-sample shape in recipe terms, one symbol per axis: ``"L"``, ``"L+1"``,
            ``"B"`` (num_bins), ``"S"`` (crop size, pixels), ``"n"`` (tracked grid points per
            side) or a literal size such as ``"2"``.
        channel_axis: axis of the channels in the per-sample tensor the client gives (after
            ``insert_channel``): 1 for every array (bins, x/y, polarity), None for none.
        insert_channel: the wire array has no channel axis; the client and the Ray rows insert
            one of size 1 at ``channel_axis``.
        column_dtype: the one dtype of its Ray Data column (Ray blocks need one per column);
            None for arrays that are not Ray columns. The recipe's ``flow_dtype`` for
            ``"recipe"``.
        float_divisor: the client's float conversion: float32 of the wire value divided by this
            (255 for 8-bit intensities); None: float32 of the value (counts, pixels).
        expand: the client makes the dense output of this compact form (``flow_grid``).
        default: served when a client names no outputs; opt-in outputs are made only for
            clients that ask.
    """

    name: str
    output: str
    dtypes: Tuple[str, ...]
    narrowing: str
    axes: Tuple[str, ...]
    channel_axis: Optional[int] = 1
    insert_channel: bool = False
    column_dtype: Optional[str] = None
    float_divisor: Optional[float] = None
    expand: bool = False
    default: bool = True

    def shape(self, sequence_length: int, num_bins: int, crop_size: int, grid: int = 0) -> Tuple[int, ...]:
        """The per-sample wire shape for a recipe (``grid``: tracked grid points per side)."""
        dims = {"L": sequence_length, "L+1": sequence_length + 1, "B": num_bins, "S": crop_size, "n": grid}
        return tuple(dims[a] if a in dims else int(a) for a in self.axes)

    def itemsize(self) -> int:
        """Bytes per value of its widest wire dtype."""
        return max(np.dtype(d).itemsize for d in self.dtypes)


#: The table, in wire order. ``flow_grid`` is the compact form of ``flow`` (tracked options).
ARRAYS: Dict[str, ArraySpec] = {s.name: s for s in (
    ArraySpec("voxels", "voxels", ("int8", "int16", "int32"), "counts", ("L", "B", "S", "S"),
              column_dtype="int16"),
    ArraySpec("frames", "frames", ("uint8",), "fixed", ("L+1", "S", "S"), insert_channel=True,
              column_dtype="uint8", float_divisor=255.0),
    ArraySpec("flow", "flow", ("float16", "float32"), "recipe", ("L", "2", "S", "S"), column_dtype="recipe"),
    ArraySpec("polarity_counts", "polarity_counts", ("uint8",), "fixed", ("L", "2", "B", "S", "S"),
              column_dtype="uint8", default=False),
    ArraySpec("flow_grid", "flow", ("float32",), "fixed", ("L", "2", "n", "n"), expand=True),
)}

#: Outputs a sample can carry, in wire order.
OUTPUTS: Tuple[str, ...] = tuple(s.name for s in ARRAYS.values() if s.output == s.name)
#: Outputs served when a client names none (the opt-in ones are left out).
DEFAULT_OUTPUTS: Tuple[str, ...] = tuple(s.name for s in ARRAYS.values() if s.output == s.name and s.default)
#: Arrays on the wire that carry an output in another form than its own name: ``flow_grid`` is
#: the compact ``flow`` of the tracked flow options (see ``protocol.flow_grid_taps``).
ARRAY_OUTPUT: Dict[str, str] = {s.name: s.output for s in ARRAYS.values() if s.output != s.name}


def output_of(array_name: str) -> str:
    """The output (``OUTPUTS``) a wire array carries: ``flow_grid`` carries ``flow``; any other
    array carries the output of its own name."""
    return ARRAY_OUTPUT.get(array_name, array_name)


def spec_of(array_name: str) -> ArraySpec:
    """The :class:`ArraySpec` of a wire array.

    Raises:
        KeyError: naming the array and the known ones.
    """
    try:
        return ARRAYS[array_name]
    except KeyError:
        raise KeyError(f"unknown array {array_name!r}; known: {list(ARRAYS)}") from None


def narrow_int_dtype(arr: np.ndarray, dtypes=("int8", "int16", "int32")) -> np.dtype:
    """Narrowest of ``dtypes`` (integer dtypes, narrowest first) that holds every value of the
    integer array ``arr``.

    Counts are never wrapped or clipped: a value outside the widest raises ``OverflowError``.
    """
    if arr.size == 0:
        return np.dtype(dtypes[0])
    lo, hi = int(arr.min()), int(arr.max())
    for dt in dtypes:
        info = np.iinfo(dt)
        if info.min <= lo and hi <= info.max:
            return np.dtype(dt)
    raise OverflowError(f"event counts in [{lo}, {hi}] do not fit {dtypes[-1]}")


def wire_dtype(array_name: str, a: np.ndarray, flow_dtype: str = "float16") -> np.dtype:
    """The dtype a producer sends array ``a`` of ``array_name`` in (its spec's ``narrowing``):
    for ``"counts"`` the narrowest that holds every value, where an array already in a
    narrower wire dtype than the widest is taken as narrowed by its producer (the kernel picks
    int8/int16 itself) and not scanned again; ``flow_dtype`` (the recipe's) for ``"recipe"``;
    ``dtypes[0]`` for ``"fixed"``.

    Raises:
        KeyError: an unknown array. OverflowError: counts beyond the widest dtype.
    """
    s = spec_of(array_name)
    if s.narrowing == "counts":
        if a.dtype.name in s.dtypes[:-1]:
            return a.dtype
        return narrow_int_dtype(a, s.dtypes)
    if s.narrowing == "recipe":
        if flow_dtype not in s.dtypes:
            raise ValueError(f"{array_name} dtype must be one of {list(s.dtypes)}, got {flow_dtype!r}")
        return np.dtype(flow_dtype)
    return np.dtype(s.dtypes[0])


def narrowest(array_name: str, a: np.ndarray) -> np.ndarray:
    """``a`` narrowed again to the narrowest dtype that holds it when its spec narrows by
    ``"counts"`` (a batch stacked from samples of several widths, or a subset of one); any
    other array as it is."""
    if spec_of(array_name).narrowing != "counts":
        return a
    return a.astype(narrow_int_dtype(a, ARRAYS[array_name].dtypes), copy=False)


def max_sample_bytes(sequence_length: int, num_bins: int, crop_size: int, align: int = 1) -> int:
    """Bytes of the largest sample of the default outputs a recipe can make: each at its widest
    wire dtype (the compact ``flow_grid`` is never larger than the dense ``flow`` it replaces),
    each array's start rounded up to ``align`` bytes. Opt-in outputs are left out (a sample
    that carries one may not fit a slot sized so, and then travels as frames)."""
    total = 0
    for s in ARRAYS.values():
        if s.output != s.name or not s.default:
            continue
        total += int(np.prod(s.shape(sequence_length, num_bins, crop_size))) * s.itemsize() + align
    return total


def row_array(array_name: str, a: np.ndarray, flow_dtype: str, sample_id: str = "") -> np.ndarray:
    """A sample's array as its Ray Data column holds it: in ``column_dtype`` (the recipe's
    ``flow_dtype`` for ``"recipe"``), with the channel axis inserted where the spec says, C-contiguous.

    Raises:
        OverflowError: naming ``sample_id``, for integer values outside the column dtype (never wrapped).
    """
    s = spec_of(array_name)
    dt = np.dtype(flow_dtype if s.column_dtype == "recipe" else s.column_dtype)
    if dt.kind in "iu" and a.dtype != dt and a.size:
        info = np.iinfo(dt)
        if int(a.min()) < info.min or int(a.max()) > info.max:
            raise OverflowError(f"{sample_id}: {array_name} values in [{a.min()}, {a.max()}] do not fit {dt.name}")
    a = a.astype(dt, copy=False)
    if s.insert_channel:
        a = np.expand_dims(a, s.channel_axis)
    return np.ascontiguousarray(a)


def zeros_row(array_name: str, sequence_length: int, num_bins: int, crop_size: int, flow_dtype: str) -> np.ndarray:
    """A Ray row's array of zeros (a padding row) in its column's dtype and layout."""
    s = spec_of(array_name)
    return row_array(array_name, np.zeros(s.shape(sequence_length, num_bins, crop_size), s.dtypes[0]), flow_dtype)


def wire_row(output: str, sequence_length: int, num_bins: int, crop_size: int, flow_dtype: str) -> Tuple[tuple, str]:
    """(shape, dtype) of one row of ``output`` as the wire carries a sample's array: its wire
    shape and narrowest dtype (``flow_dtype``, the recipe's, for ``flow``)."""
    s = spec_of(output)
    return tuple(s.shape(sequence_length, num_bins, crop_size)), flow_dtype if s.column_dtype == "recipe" \
        else s.dtypes[0]


def wire_zeros_row(output: str, stream: Mapping) -> np.ndarray:
    """One row of zeros of ``output`` as a server's reply of padding rows only carries it
    (:func:`wire_row`), from the server's stream info (``sequence_length``, ``num_bins``,
    ``crop_size``, ``flow_dtype``)."""
    return np.zeros(*wire_row(output, stream["sequence_length"], stream["num_bins"], stream["crop_size"],
                              stream.get("flow_dtype", "float16")))


def column_outputs(names: Mapping) -> Tuple[str, ...]:
    """The outputs among ``names`` (e.g. a Ray batch's columns), in wire order."""
    return tuple(o for o in OUTPUTS if o in names)
