"""One reader for real event-camera recordings: events in time-ordered chunks, frames, sensor size.

Formats (docs/recordings.md lists them with the cameras that write them):

* ``.aedat4`` (iniVation DAVIS / DVXplorer, DV software): events, APS frames with their
  exposure timestamps, IMU samples;
* ``.raw`` Prophesee EVT 2.0 / 2.1 / 3.0 (the version and ``geometry`` from the header);
* ``.dat`` Prophesee DAT, ``.es`` Event Stream (ATIS, Neuromorphic Systems), ``.csv`` (``t,x,y,p``
  with a header line, t in microseconds);
* ``.h5`` / ``.hdf5`` in the event_cnn_minimal layout (:class:`H5Sequence` documents it);
* the IJRR / Event Camera Dataset text layout: a folder (or its ``events.txt``) holding
  ``events.txt`` (``t x y p`` per line, t in seconds), ``images.txt`` (``t images/NAME.png``) and
  ``images/``.

All binary formats but H5 are decoded by ``faery`` (0.7.1, LGPL-3.0, Rust decoders): AEDAT4
events, frames and IMU come through its ``faery.aedat.Decoder``, so no second AEDAT package is
needed. Nothing here decodes a binary event format by hand.

Every reader yields chunks of :data:`EVENT_DTYPE` through the same checks
(:meth:`Recording.chunks`):

* an event outside the sensor raises :class:`RecordingError` (a wrong ``size`` is the usual cause);
* an event earlier than one already yielded (Prophesee streams after a timestamp counter
  overflow, or a damaged file) is dropped, counted in ``Recording.dropped_backward`` and logged
  once per pass, so every chunk and the whole stream stay non-decreasing in t;
* a file that ends early (AEDAT4 cut inside a packet, RAW cut inside a word) keeps the events
  before the cut and logs a warning (``Recording.truncated``);
* an empty file, an unknown extension, a file whose bytes are not the format its name says, or
  a recording without any event raises :class:`RecordingError` naming the file;
* a sensor size out of bounds (:func:`checked_size`: x, y are uint16, at most
  :data:`MAX_SENSOR_PIXELS` pixels), from the file or the caller, raises :class:`RecordingError`
  naming the file and the field when the recording is opened, before anything is sized by it.

Each format is a :class:`FormatReader` in :data:`READERS` (sniff the bytes, the sensor size the
file states, the events, the frames), as tonic's ``io.py`` keeps one ``read_*`` per format.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Optional, Tuple

import numpy as np

from .event_grids import events_to_voxels

__all__ = ["EVENT_DTYPE", "RecordingError", "Frames", "Recording", "open_recording", "read_all", "H5Sequence",
           "FORMATS", "READERS", "FormatReader", "checked_size", "MAX_SENSOR_SIDE", "MAX_SENSOR_PIXELS"]

log = logging.getLogger("trainer.recordings")

#: One event: ``t`` int64 microseconds, ``x`` column and ``y`` row (pixels, uint16),
#: ``p`` polarity int8, +1 (brighter, ON) or -1 (darker, OFF).
EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])

#: Extension -> format name; an ECD/IJRR recording is a folder with ``events.txt``.
FORMATS = {".aedat4": "aedat4", ".raw": "evt", ".dat": "dat", ".es": "es", ".csv": "csv",
           ".h5": "h5", ".hdf5": "h5", ".txt": "ecd"}

#: Largest sensor side, pixels: ``x`` and ``y`` are uint16, so 0 <= x, y <= 65535.
MAX_SENSOR_SIDE = int(np.iinfo(EVENT_DTYPE["x"]).max) + 1

#: Most pixels a sensor size may have (8192 x 8192): a full frame (uint8) or one bin of a voxel
#: grid (int32) is sized by it, and no event camera comes within 50x of it (docs/recordings.md).
MAX_SENSOR_PIXELS = 1 << 26

# Sensor sizes (width, height) of Prophesee RAW headers that carry no ``geometry`` line, by the
# plugin / generation their header names (Prophesee's sensor datasheets).
_PROPHESEE_SIZES = (("gen3", (640, 480)), ("imx636", (1280, 720)), ("gen4", (1280, 720)))
_EVT_WORD_BYTES = {"evt2": 4, "evt2.1": 8, "evt3": 2}
_H5_CHUNK = 1 << 20  # events per chunk read from an H5 file
_TEXT_CHUNK = 1 << 22  # bytes per chunk parsed from events.txt


class RecordingError(ValueError):
    """A recording that cannot be read: ``path`` the file, ``problem`` what is wrong; the
    message names both."""

    def __init__(self, path, problem: str):
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


@dataclass
class Frames:
    """Intensity frames of a recording.

    Attributes:
        t_us: int64 (N,) frame timestamps, microseconds, increasing (AEDAT4: the middle of the
            exposure; ECD and H5: the timestamp stored with the image).
        images: uint8 (N, H, W) grey frames (colour converted to luma).
        exposure_us: int64 (N, 2) exposure start and end, microseconds, or None when the
            format does not store them.
    """
    t_us: np.ndarray
    images: np.ndarray
    exposure_us: Optional[np.ndarray] = None


class Recording:
    """A real recording opened by :func:`open_recording`.

    Attributes:
        path: the file (or ECD folder); ``format``: a value of :data:`FORMATS`.
        width, height: sensor size, pixels.
        size_source: where the size came from: ``"header"``, ``"argument"``, ``"frames"`` or
            ``"inferred from the header's plugin name <name>"``.
        dropped_backward: events dropped for running backwards in the last pass, up to where it stopped
            (v2v-eval: the pass over the grids it scores).
        truncated: whether a pass (over the events, the frames or the IMU) has met the end of the
            file inside a packet or word: a fact of the file, kept once found (a later pass that
            stops before the cut does not clear it).
        text_chunk_bytes: bytes of ``events.txt`` parsed per chunk (ECD layout; 4 MiB).
    """

    def __init__(self, path: Path, fmt: str, width: int, height: int, size_source: str, opts: dict):
        self.path, self.format = path, fmt
        self.width, self.height, self.size_source = int(width), int(height), size_source
        self._opts = opts
        self.dropped_backward = 0
        self.truncated = False
        self.text_chunk_bytes = _TEXT_CHUNK
        self._frames: Optional[Frames] = None
        self._imu = None
        self._read = set()  # "frames", "imu": read once, None included

    def __repr__(self) -> str:
        return f"Recording({str(self.path)!r}, {self.format}, {self.width}x{self.height})"

    def chunks(self, start_us: Optional[int] = None, end_us: Optional[int] = None) -> Iterator[np.ndarray]:
        """Events in time-ordered chunks, never the whole recording at once.

        Args:
            start_us, end_us: keep events with ``start_us <= t < end_us`` (microseconds,
                absolute like the events' ``t``; None: unbounded).

        Yields:
            :data:`EVENT_DTYPE` arrays of >= 1 event, t non-decreasing within and across chunks.

        Raises:
            RecordingError: events outside the sensor, bytes that are not the format, no event.
        """
        self.dropped_backward = 0
        last_t = np.iinfo(np.int64).min
        n_out = 0
        for ev in self._raw_chunks():
            if ev.size == 0:
                continue
            bad = (ev["x"] >= self.width) | (ev["y"] >= self.height)
            if bad.any():
                i = int(np.argmax(bad))
                raise RecordingError(self.path, f"event at x={int(ev['x'][i])}, y={int(ev['y'][i])}, "
                                     f"t={int(ev['t'][i])} us lies outside the {self.width}x{self.height} sensor "
                                     f"(size from {self.size_source}; give the sensor size explicitly if it is wrong)")
            # running maximum: an event earlier than any already yielded is dropped
            run = np.maximum.accumulate(np.concatenate(([last_t], ev["t"])))[:-1]
            back = ev["t"] < run
            if back.any():
                if self.dropped_backward == 0:
                    i = int(np.argmax(back))
                    log.warning("%s: timestamps run backwards (t=%d us after %d us); dropping the events "
                                "earlier than the stream's running maximum", self.path, int(ev["t"][i]), int(run[i]))
                self.dropped_backward += int(back.sum())
                ev = ev[~back]
                if ev.size == 0:
                    continue
            last_t = int(ev["t"][-1])
            if start_us is not None and last_t < start_us:
                continue
            if end_us is not None and ev["t"][0] >= end_us:
                break
            if start_us is not None or end_us is not None:
                lo = 0 if start_us is None else int(np.searchsorted(ev["t"], start_us, "left"))
                hi = ev.size if end_us is None else int(np.searchsorted(ev["t"], end_us, "left"))
                ev = ev[lo:hi]
                if ev.size == 0:
                    continue
            n_out += 1
            yield ev
        if self.dropped_backward:
            log.warning("%s: dropped %d events whose timestamps ran backwards", self.path, self.dropped_backward)
        if n_out == 0 and start_us is None and end_us is None:
            raise RecordingError(self.path, "the recording holds no events")

    def frames(self) -> Optional[Frames]:
        """The recording's intensity frames (:class:`Frames`, read once and kept), or None when
        it has none. Frames whose timestamp does not increase are dropped with a warning."""
        read = READERS[self.format].frames
        if "frames" not in self._read and read is not None:
            self._read.add("frames")
            f = read(self)
            if f is not None:
                # keep each frame later than every frame before it (the events' running-max rule)
                earlier = np.maximum.accumulate(np.concatenate(([np.iinfo(np.int64).min], f.t_us[:-1])))
                ok = f.t_us > earlier
                if not ok.all():
                    log.warning("%s: dropping %d frames whose timestamps do not increase", self.path, int((~ok).sum()))
                    f = Frames(f.t_us[ok], f.images[ok], None if f.exposure_us is None else f.exposure_us[ok])
            self._frames = f
        return self._frames

    def imu(self) -> Optional[np.ndarray]:
        """AEDAT4 IMU samples as faery's structured array (``t`` microseconds, ``temperature``
        deg C, ``accelerometer_*`` g, ``gyroscope_*`` deg/s, ``magnetometer_*``), or None."""
        if self.format != "aedat4":
            return None
        if "imu" not in self._read:
            self._read.add("imu")
            parts = [p for tr, p in _aedat_packets(self) if tr.data_type == "imus"]
            self._imu = np.concatenate(parts) if parts else None
        return self._imu

    def first_t_us(self) -> int:
        """Timestamp of the first event, microseconds (reads only the first chunk)."""
        it = self.chunks()
        ev = next(it)
        it.close()
        return int(ev["t"][0])

    def _raw_chunks(self) -> Iterator[np.ndarray]:
        yield from READERS[self.format].events(self)


# -- the per-format readers: sniff (the bytes are the format), sensor size, events, frames --

@dataclass(frozen=True)
class FormatReader:
    """How one format of :data:`FORMATS` is read (the entries of :data:`READERS`).

    Attributes:
        sniff: ``sniff(path, evt_version) -> options``: checks that the bytes are the format
            and reads what its header states (kept as ``Recording._opts``); raises
            :class:`RecordingError` naming the file.
        sensor_size: ``sensor_size(path, options) -> (width, height, source)``: the size the
            file states, checked by :func:`checked_size`; raises :class:`RecordingError`
            naming the file and the field when it states none or one out of bounds.
        events: ``events(recording)``: raw :data:`EVENT_DTYPE` chunks, checked by
            :meth:`Recording.chunks`.
        frames: ``frames(recording) -> Frames or None``, or None for a format without frames.
    """
    sniff: Callable[[Path, Optional[str]], dict]
    sensor_size: Callable[[Path, dict], Tuple[int, int, str]]
    events: Callable[["Recording"], Iterator[np.ndarray]]
    frames: Optional[Callable[["Recording"], Optional[Frames]]] = None


def checked_size(path, width, height, field: str) -> Tuple[int, int]:
    """A sensor size a file (or the caller) states, checked before anything is sized by it:
    whole numbers, >= 1, each side at most :data:`MAX_SENSOR_SIDE` (the events' uint16 ``x``,
    ``y``) and at most :data:`MAX_SENSOR_PIXELS` pixels (a full frame, a voxel grid).

    Raises:
        RecordingError: naming ``path`` and ``field`` (where the size was read) and the value.
    """
    try:
        w, h = int(width), int(height)
        whole = w == width and h == height
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise RecordingError(path, f"{field}: sensor size {width!r}x{height!r}: not whole numbers")
    if not (1 <= w <= MAX_SENSOR_SIDE and 1 <= h <= MAX_SENSOR_SIDE):
        raise RecordingError(path, f"{field}: sensor size {w}x{h}: each side must be 1 to "
                             f"{MAX_SENSOR_SIDE} pixels (x and y are uint16)")
    if w * h > MAX_SENSOR_PIXELS:
        raise RecordingError(path, f"{field}: sensor size {w}x{h} = {w * h} pixels, over the "
                             f"{MAX_SENSOR_PIXELS} this reader takes (MAX_SENSOR_PIXELS)")
    return w, h


def _to_events(t, x, y, on) -> np.ndarray:
    out = np.empty(len(t), EVENT_DTYPE)
    out["t"], out["x"], out["y"] = t, x, y
    out["p"] = np.where(on, 1, -1)
    return out


def _from_faery(rec: "Recording", packets) -> Iterator[np.ndarray]:
    it = iter(packets)
    while True:
        try:
            ev = next(it)
        except StopIteration:
            return
        except RuntimeError as e:  # faery's decoders report damage and out-of-range pixels so
            msg = str(e)
            if "overflow" in msg:
                raise RecordingError(rec.path, f"an event lies outside the {rec.width}x{rec.height} sensor "
                                     f"({msg}; size from {rec.size_source}; give the sensor size explicitly "
                                     "if it is wrong)") from None
            raise RecordingError(rec.path, f"{rec.format.upper()} decoding failed: {msg}") from None
        yield _to_events(ev["t"], ev["x"], ev["y"], ev["on"])


def _faery_events(rec: "Recording") -> Iterator[np.ndarray]:
    import faery

    kw = {"dimensions_fallback": (rec.width, rec.height)}
    if rec.format == "evt":
        kw["version_fallback"] = rec._opts["evt_version"]
    return _from_faery(rec, faery.events_stream_from_file(rec.path, **kw))


# Prophesee RAW (EVT 2.0 / 2.1 / 3.0)

def _evt_header(path: Path) -> Tuple[dict, int]:
    """Key/value lines of a Prophesee RAW header (``% key value``) and its length in bytes."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    keys, pos = {}, 0
    while pos < len(head) and head[pos:pos + 1] == b"%":
        end = head.find(b"\n", pos)
        if end < 0:
            break
        line = head[pos + 1:end].decode("latin-1").strip()
        pos = end + 1
        if line == "end":
            break
        k, _, v = line.partition(" ")
        keys[k.lower()] = v.strip()
    return keys, pos


def _sniff_evt(p: Path, evt_version: Optional[str]) -> dict:
    keys, nhead = _evt_header(p)
    if nhead == 0:
        raise RecordingError(p, "not a Prophesee RAW file: no '%' header lines")
    ver = evt_version or keys.get("evt") or keys.get("format")
    ver = {"2.0": "evt2", "2.1": "evt2.1", "3.0": "evt3", "evt2": "evt2", "evt21": "evt2.1",
           "evt3": "evt3"}.get((ver or "").lower().split(";")[0], ver)
    if ver not in _EVT_WORD_BYTES:
        raise RecordingError(p, f"RAW header states no known EVT version ({ver!r}): give evt_version")
    return {"evt_version": ver, "header_bytes": nhead, "keys": keys}


def _evt_size(p: Path, opts: dict) -> Tuple[int, int, str]:
    keys = opts["keys"]
    if "geometry" in keys:
        m = re.fullmatch(r"([+-]?\d+)\s*x\s*([+-]?\d+)", keys["geometry"])
        if m is None:
            raise RecordingError(p, f"the RAW header field 'geometry' is {keys['geometry']!r}, not WIDTHxHEIGHT")
        w, h = checked_size(p, int(m.group(1)), int(m.group(2)), "the RAW header field 'geometry'")
        return w, h, "header"
    named = (keys.get("plugin_name", "") + " " + keys.get("sensor_generation", "")).lower()
    hit = next(((k, s) for k, s in _PROPHESEE_SIZES if k in named), None)
    if hit is None:
        raise RecordingError(p, "the RAW header carries no geometry and names no known sensor: give the "
                             "sensor size (width, height)")
    (w, h), src = hit[1], f"inferred from the header's plugin name {keys.get('plugin_name', '?')}"
    log.warning("%s: the RAW header carries no geometry; assuming %dx%d (%s)", p, w, h, src)
    return w, h, src


def _evt_events(rec: "Recording") -> Iterator[np.ndarray]:
    yield from _faery_events(rec)
    o = rec._opts
    if (rec.path.stat().st_size - o["header_bytes"]) % _EVT_WORD_BYTES[o["evt_version"]]:
        rec.truncated = True
        log.warning("%s: the file ends inside a %d-byte %s word (truncated); keeping the events before the cut",
                    rec.path, _EVT_WORD_BYTES[o["evt_version"]], o["evt_version"].upper())


# Prophesee DAT, Event Stream: faery reads the header; CSV states no size

def _sniff_faery_header(p: Path, evt_version: Optional[str]) -> dict:
    import faery

    try:
        w, h = faery.events_stream_from_file(p, dimensions_fallback=(1280, 720)).dimensions()
    except Exception as e:  # faery raises a bare Exception or RuntimeError for bad headers
        raise RecordingError(p, f"{FORMATS.get(p.suffix.lower(), '?').upper()} header unreadable: {e}") from None
    return {"dimensions": (w, h)}


def _sniff_dat(p: Path, evt_version: Optional[str]) -> dict:
    """A DAT file's header: faery reads it, but takes its fallback for a ``Width`` or ``Height``
    it cannot parse (99999, -5), so the two text fields are read and checked here too."""
    opts = _sniff_faery_header(p, evt_version)
    keys, _ = _evt_header(p)
    if "width" in keys or "height" in keys:
        field = "the DAT header fields 'Width' and 'Height'"
        stated = [keys.get(k, "") for k in ("width", "height")]
        if not all(re.fullmatch(r"[+-]?\d+", v) for v in stated):
            raise RecordingError(p, f"{field}: sensor size {stated[0]!r}x{stated[1]!r}: not whole numbers")
        opts["dimensions"] = checked_size(p, int(stated[0]), int(stated[1]), field)
    return opts


def _header_size(p: Path, opts: dict) -> Tuple[int, int, str]:
    w, h = checked_size(p, *opts["dimensions"], "the header's sensor size")
    return w, h, "header"


def _csv_size(p: Path, opts: dict) -> Tuple[int, int, str]:
    raise RecordingError(p, "CSV files do not state the sensor size: give it (width, height)")


# AEDAT4 (iniVation)

def _sniff_aedat4(p: Path, evt_version: Optional[str]) -> dict:
    with open(p, "rb") as fh:
        magic = fh.read(16)
    if not magic.startswith(b"#!AER-DAT4.0"):
        raise RecordingError(p, f"not an AEDAT4 file: it starts with {magic[:12]!r}, not '#!AER-DAT4.0'")
    import faery

    try:
        with faery.aedat.Decoder(path=p) as dec:
            tracks = [t for t in dec.tracks() if t.data_type == "events"]
    except RuntimeError as e:
        raise RecordingError(p, f"AEDAT4 header unreadable: {e}") from None
    if not tracks:
        raise RecordingError(p, "the AEDAT4 file has no event track")
    return {"track_id": tracks[0].id, "dimensions": tuple(tracks[0].dimensions)}


def _aedat4_size(p: Path, opts: dict) -> Tuple[int, int, str]:
    w, h = checked_size(p, *opts["dimensions"], "the event track's dimensions")
    return w, h, "header"


def _aedat_packets(rec: "Recording"):
    """(track, packet) pairs of the AEDAT4 file; a file cut inside a packet ends the pass
    with a warning (``truncated``)."""
    import faery

    try:
        with faery.aedat.Decoder(path=rec.path) as dec:
            yield from dec
    except RuntimeError as e:
        rec.truncated = True
        log.warning("%s: AEDAT4 decoding stopped (%s): the file is truncated or damaged; keeping what came "
                    "before", rec.path, e)


def _aedat4_events(rec: "Recording") -> Iterator[np.ndarray]:
    tid = rec._opts["track_id"]
    for tr, p in _aedat_packets(rec):
        if tr.id == tid and len(p):
            yield _to_events(p["t"], p["x"], p["y"], p["on"])


def _aedat4_frames(rec: "Recording") -> Optional[Frames]:
    ts, ims, exp = [], [], []
    for tr, fr in _aedat_packets(rec):
        if tr.data_type != "frame":
            continue
        img = fr.pixels
        if img.ndim == 3:  # colour DAVIS: to luma
            import cv2

            img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
        x0, y0 = int(fr.offset_x), int(fr.offset_y)
        if x0 < 0 or y0 < 0 or x0 + img.shape[1] > rec.width or y0 + img.shape[0] > rec.height:
            raise RecordingError(rec.path, f"frame {len(ts)}: its region {img.shape[1]}x{img.shape[0]} at offset "
                                 f"({x0}, {y0}) lies outside the {rec.width}x{rec.height} sensor")
        full = np.zeros((rec.height, rec.width), np.uint8)  # frames may be a region of interest
        full[y0:y0 + img.shape[0], x0:x0 + img.shape[1]] = img
        ims.append(full)
        e0, e1 = int(fr.exposure_start_t), int(fr.exposure_end_t)
        exp.append((e0, e1))
        ts.append((e0 + e1) // 2)
    if not ts:
        return None
    return Frames(np.array(ts, np.int64), np.stack(ims), np.array(exp, np.int64))


# H5 (event_cnn_minimal layout)

def _sniff_h5(p: Path, evt_version: Optional[str]) -> dict:
    with open(p, "rb") as fh:
        magic = fh.read(16)
    if not magic.startswith(b"\x89HDF\r\n\x1a\n"):
        raise RecordingError(p, "not an HDF5 file")
    import h5py

    with h5py.File(p, "r") as f:
        for k in ("events/xs", "events/ys", "events/ts", "events/ps"):
            if k not in f:
                raise RecordingError(p, f"missing '{k}' (the event_cnn_minimal H5 layout is read; Prophesee "
                                     "HDF5 is not)")
    return {}


def _h5_size(p: Path, opts: dict) -> Tuple[int, int, str]:
    import h5py

    with h5py.File(p, "r") as f:
        if "sensor_resolution" in f.attrs:
            res = f.attrs["sensor_resolution"]
            if np.ndim(res) != 1 or len(res) < 2:
                raise RecordingError(p, f"the attribute 'sensor_resolution' is {res!r}, not (height, width)")
            w, h = checked_size(p, res[1], res[0], "the attribute 'sensor_resolution'")
            return w, h, "header"
        if "images" in f and len(f["images"]):
            first = sorted(f["images"].keys())[0]
            shape = f["images"][first].shape
            w, h = checked_size(p, shape[1], shape[0], f"the image 'images/{first}'")
            return w, h, "frames"
    raise RecordingError(p, "no sensor_resolution and no images: give the sensor size (width, height)")


def _h5_events(rec: "Recording") -> Iterator[np.ndarray]:
    import h5py

    with h5py.File(rec.path, "r") as f:
        ev = f["events"]
        n = ev["ts"].shape[0]
        for a in range(0, n, _H5_CHUNK):
            b = min(n, a + _H5_CHUNK)
            yield _to_events(np.round(ev["ts"][a:b].astype(np.float64) * 1e6), ev["xs"][a:b], ev["ys"][a:b],
                             ev["ps"][a:b] > 0)


def _h5_frames(rec: "Recording") -> Optional[Frames]:
    import h5py

    with h5py.File(rec.path, "r") as f:
        if "images" not in f or not len(f["images"]):
            return None
        ims, ts = _h5_images(f)
    return Frames(np.array([round(t * 1e6) for t in ts], np.int64), ims)


# IJRR / Event Camera Dataset text layout (a folder)

def _sniff_ecd(root: Path, evt_version: Optional[str]) -> dict:
    ev = root / "events.txt"
    if ev.stat().st_size == 0:
        raise RecordingError(ev, "empty file")
    return {"events_txt": ev, "frames": _read_ecd_frames(root)}


def _ecd_size(root: Path, opts: dict) -> Tuple[int, int, str]:
    fr = opts["frames"]
    if fr is None:
        raise RecordingError(root, "no images to take the sensor size from: give the size (width, height)")
    w, h = checked_size(root, fr.images.shape[2], fr.images.shape[1], "the images of images.txt")
    return w, h, "frames"


def _ecd_events(rec: "Recording") -> Iterator[np.ndarray]:
    with open(rec._opts["events_txt"], "rb") as fh:
        rest = b""
        while True:
            block = fh.read(rec.text_chunk_bytes)
            if not block and not rest.strip():
                break
            data = rest + block
            if block:
                cut = data.rfind(b"\n") + 1
                data, rest = data[:cut], data[cut:]
            else:
                rest = b""
            if not data.strip():
                continue
            vals = np.array(data.split(), dtype=np.float64)
            if vals.size % 4:
                raise RecordingError(rec._opts["events_txt"], "lines must hold 't x y p' (4 numbers each)")
            vals = vals.reshape(-1, 4)
            if (vals[:, 1:3] < 0).any():
                raise RecordingError(rec._opts["events_txt"], "negative pixel coordinates")
            yield _to_events(np.round(vals[:, 0] * 1e6), vals[:, 1], vals[:, 2], vals[:, 3] > 0)


def _read_ecd_frames(root: Path) -> Optional[Frames]:
    import cv2

    txt = root / "images.txt"
    if not txt.is_file():
        return None
    ts, ims = [], []
    for line in txt.read_text().split("\n"):
        if not line.strip() or line.startswith("#"):
            continue
        t, name = line.split()[:2]
        img = cv2.imread(str(root / name), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise RecordingError(root / name, "image listed in images.txt cannot be read")
        ts.append(round(float(t) * 1e6))
        ims.append(img)
    return Frames(np.array(ts, np.int64), np.stack(ims)) if ts else None


#: Format name -> its reader (tonic's ``io.py`` keeps one ``read_*`` per format the same way).
READERS = {
    "aedat4": FormatReader(_sniff_aedat4, _aedat4_size, _aedat4_events, _aedat4_frames),
    "evt": FormatReader(_sniff_evt, _evt_size, _evt_events),
    "dat": FormatReader(_sniff_dat, _header_size, _faery_events),
    "es": FormatReader(_sniff_faery_header, _header_size, _faery_events),
    "csv": FormatReader(lambda p, v: {}, _csv_size, _faery_events),
    "h5": FormatReader(_sniff_h5, _h5_size, _h5_events, _h5_frames),
    "ecd": FormatReader(_sniff_ecd, _ecd_size, _ecd_events, lambda rec: rec._opts["frames"]),
}


def open_recording(path, size: Optional[Tuple[int, int]] = None, evt_version: Optional[str] = None) -> Recording:
    """Open a real recording; the format from the extension (a folder: the ECD text layout).

    Args:
        path: the file, or an ECD/IJRR folder holding ``events.txt``.
        size: (width, height) of the sensor, pixels: required for CSV, used for a Prophesee RAW
            or DAT whose header carries no geometry, and overriding the size any file states.
            Without it a RAW header without geometry takes its size from the plugin / sensor
            generation it names (Gen3: 640x480; IMX636 / Gen4.x: 1280x720) with a warning.
        evt_version: ``"evt2"``, ``"evt2.1"`` or ``"evt3"`` for a RAW header that does not
            state it.

    Returns:
        a :class:`Recording`.

    Raises:
        RecordingError: missing or empty file, unknown extension, bytes that do not start as
            the format does (no AEDAT4 magic, no RAW header, not an H5 file or not the
            event_cnn_minimal layout), a size that cannot be known, or a size (stated by the
            file or ``size``) out of bounds (:func:`checked_size`: the message names the field).
    """
    p = Path(path)
    if p.is_dir() or p.name == "events.txt":
        root = p if p.is_dir() else p.parent
        if not (root / "events.txt").is_file():
            raise RecordingError(p, "a folder recording needs events.txt (the IJRR/ECD text layout)")
        p, fmt = root, "ecd"
    else:
        if not p.is_file():
            raise RecordingError(p, "no such file")
        if p.stat().st_size == 0:
            raise RecordingError(p, "empty file (0 bytes)")
        fmt = FORMATS.get(p.suffix.lower())
        if fmt is None or fmt == "ecd":
            raise RecordingError(p, f"unknown recording extension {p.suffix!r} (known: {', '.join(sorted(FORMATS))}, "
                                 "or an ECD folder)")
    reader = READERS[fmt]
    opts = reader.sniff(p, evt_version)
    if size is not None:
        w, h = checked_size(p, size[0], size[1], "the size argument")
        src = "argument"
    else:
        w, h, src = reader.sensor_size(p, opts)
    return Recording(p, fmt, w, h, src, opts)


def read_all(rec: Recording, start_us: Optional[int] = None, end_us: Optional[int] = None) -> np.ndarray:
    """All events of ``rec`` (between ``start_us`` and ``end_us``) as one :data:`EVENT_DTYPE`
    array: for tests and short recordings only (a Prophesee HD hour is tens of GB)."""
    parts = list(rec.chunks(start_us, end_us))
    return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)


def _h5_images(f) -> Tuple[np.ndarray, np.ndarray]:
    """The ``images`` group of an open event_cnn_minimal H5 file in name order: uint8 luma
    (N, H, W) (colour images converted) and their ``timestamp`` attributes, float64 (N,) seconds."""
    names = sorted(f["images"].keys())
    ims = np.stack([f["images"][k][:] for k in names])
    if ims.ndim == 4:  # colour: to luma
        import cv2

        ims = np.stack([cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in ims])
    return ims, np.array([float(f["images"][k].attrs["timestamp"]) for k in names])


class H5Sequence:
    """An event sequence in the event_cnn_minimal / V2V reference H5 layout, read whole.

    Layout: ``events/xs, ys, ts, ps`` (pixels, seconds, polarity in {0, 1} or {-1, 1}, ``ts``
    non-decreasing), ``images/imageNNNNNNNNN`` (H, W) uint8 with a ``timestamp`` attribute
    (seconds), optional ``flow/flowNNNNNNNNN`` (2, H, W) float32 flow in pixels with a
    ``timestamp`` attribute; root attribute ``sensor_resolution`` = (H, W) if present
    (trainer/evaluate.py's docstring gives the flow convention). :func:`open_recording` reads
    the same files in chunks.

    Attributes:
        path: the file.
        height, width: sensor size, pixels.
        images: uint8 (N, H, W) frames; ``image_ts`` float64 (N,) seconds.
        flows: float32 (M, 2, H, W) ground-truth flows (pixels, NaN where unknown) or
            ``None``; ``flow_ts`` float64 (M,) seconds, or ``None`` when a flow has no
            ``timestamp`` attribute.

    :meth:`voxels` builds the discrete voxel grids between consecutive images,
    :meth:`flow_voxels` the voxels and ground truth to score flow on (module docstring).
    Raises ``KeyError`` naming a missing group/dataset, ``ValueError`` for fewer than two
    images.
    """

    def __init__(self, path: str):
        import h5py

        self.path = str(path)
        with h5py.File(self.path, "r") as f:
            for k in ("events/xs", "events/ys", "events/ts", "events/ps", "images"):
                if k not in f:
                    raise KeyError(f"{self.path}: missing '{k}' (expected the event_cnn_minimal H5 layout)")
            ev = f["events"]
            self.xs, self.ys = ev["xs"][:], ev["ys"][:]
            self.ts, self.ps = ev["ts"][:].astype(np.float64), ev["ps"][:]
            if len(f["images"]) < 2:
                raise ValueError(f"{self.path}: need at least two images, found {len(f['images'])}")
            self.images, self.image_ts = _h5_images(f)
            if "sensor_resolution" in f.attrs:
                self.height, self.width = (int(v) for v in f.attrs["sensor_resolution"][:2])
            else:
                self.height, self.width = self.images.shape[1:3]
            self.flows, self.flow_ts = None, None
            if "flow" in f and len(f["flow"]):
                fn = sorted(f["flow"].keys())
                self.flows = np.stack([f["flow"][k][:] for k in fn]).astype(np.float32)
                if all("timestamp" in f["flow"][k].attrs for k in fn):
                    self.flow_ts = np.array([float(f["flow"][k].attrs["timestamp"]) for k in fn])

    def voxels(self, num_bins: int) -> Tuple[np.ndarray, np.ndarray]:
        """``events_to_voxels`` between consecutive image timestamps: int32 (N-1, B, H, W)
        and event counts int32 (N-1, H, W)."""
        return events_to_voxels(self.xs, self.ys, self.ts, self.ps, self.image_ts, num_bins, self.height, self.width)

    def flow_voxels(self, num_bins: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxels, event counts and the ground truth to score optical flow on, following the
        module docstring's convention: ``(voxels int32 (K, B, H, W), counts int32 (K, H, W),
        flows float32 (K, 2, H, W))``; with flow timestamps K = M - 1 intervals between
        consecutive ``flow_ts`` scored against ``flows[1:]``, else K = min(M, N - 1) image
        intervals scored against ``flows[:K]``.

        Raises:
            KeyError: the file has no flow group.
            ValueError: flow timestamps that do not increase.
        """
        if self.flows is None:
            raise KeyError(f"{self.path}: no 'flow' group, cannot evaluate optical flow")
        if self.flow_ts is not None:
            if self.flow_ts.size < 2 or np.any(np.diff(self.flow_ts) <= 0):
                raise ValueError(f"{self.path}: flow timestamps must increase (>= 2 flows)")
            vox, counts = events_to_voxels(self.xs, self.ys, self.ts, self.ps, self.flow_ts, num_bins,
                                           self.height, self.width)
            return vox, counts, self.flows[1:]
        vox, counts = self.voxels(num_bins)
        k = min(len(self.flows), len(vox))
        return vox[:k], counts[:k], self.flows[:k]
