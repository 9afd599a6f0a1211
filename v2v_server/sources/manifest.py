"""The manifest of an object-store corpus: its listing (key, size, ETag; archive members with their
offset) kept as one sorted JSON line per object, so a restart and every shard read one listing
without walking the bucket, and a worker looks up single entries without loading it
(:class:`ManifestIndex`). A ``sources.store.StoreSource`` holds its listing as a
:class:`StoreListing`, which writes and reads it."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from v2v_server.sources.shards import ShardIndex, split_member

log = logging.getLogger("v2v.source")

MANIFEST_VERSION = 1


def manifest_path(url: str, state_dir: Optional[str] = None, cache_dir: Optional[str] = None) -> Path:
    """Where the manifest of the corpus at ``url`` is kept: ``STATE_DIR/manifest-H.jsonl`` when
    the server has a ``state_dir`` (it then travels with the delivery journal), else
    ``CACHE_DIR/manifests/H.jsonl`` with ``cache_dir`` the resolved cache folder
    (:func:`cache_folder`, applied by the caller); H is a hash of the URL. Shards on one host
    share it; shards on other hosts list the store once each and, the store unchanged, write
    the same manifest.

    Raises:
        ValueError: neither ``state_dir`` nor ``cache_dir`` is given.
    """
    h = hashlib.sha256(url.encode("utf-8")).hexdigest()[:16]
    if state_dir:
        return Path(state_dir) / f"manifest-{h}.jsonl"
    if not cache_dir:
        raise ValueError(f"the manifest of {url} needs a state_dir or a resolved cache folder")
    return Path(cache_dir) / "manifests" / f"{h}.jsonl"


def write_manifest(path: Path, url: str, objects: Dict[str, Tuple[int, str]],
                   refused: Optional[Dict[str, List[Tuple[str, str]]]] = None) -> None:
    """Write ``objects`` (key relative to the prefix -> (size in bytes, ETag), or for a
    member of an archive ``shard.tar/member`` -> (size, the archive's ETag, offset of the
    member's data in the shard), ``part.zip/member`` -> (size, the part's ETag, offset of its
    local header, compressed size, CRC-32, method, flag bits): :func:`member_entry`) atomically:
    a header line ``{"v2v_manifest": 1, "url", "objects", "listed_at"}`` (and ``"refused"``:
    archive -> ``[[member or '', why], ...]``, the archive entries not served,
    ``shards.ShardIndex.refused``, when there are any: a restart names them again without
    reading the archive), then one ``[key, size, etag(, offset...)]`` JSON line per entry,
    sorted by key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        header = {"v2v_manifest": MANIFEST_VERSION, "url": url, "objects": len(objects),
                  "listed_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        if any(refused.values() if refused else ()):
            header["refused"] = {a: [list(r) for r in rs] for a, rs in sorted(refused.items()) if rs}
        f.write(json.dumps(header, ensure_ascii=False) + "\n")
        for key in sorted(objects):
            f.write(json.dumps([key, *objects[key]], ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def read_manifest(path: Path, url: str) -> Optional[Dict[str, Tuple[int, str]]]:
    """The objects of the manifest at ``path`` (see :func:`write_manifest`), or None when there
    is none, it is of another URL or version, or it is cut short (a crash while written by
    another process: it is then listed again)."""
    try:
        with open(path, encoding="utf-8") as f:
            header = json.loads(f.readline() or "null")
            if not isinstance(header, dict) or header.get("v2v_manifest") != MANIFEST_VERSION or header.get("url") != url:
                return None
            objects = {}
            for line in f:
                key, size, etag, *offset = json.loads(line)
                objects[key] = (int(size), str(etag), *(int(o) for o in offset))
    except (OSError, ValueError, TypeError):
        return None
    return objects if len(objects) == header.get("objects") else None


def manifest_refused(path: Path, url: str) -> Dict[str, List[Tuple[str, str]]]:
    """The archive entries not served that the manifest at ``path`` names (see
    :func:`write_manifest`): archive -> ``(member or '', why)``; empty when it names none or
    is not a manifest of ``url``."""
    try:
        with open(path, encoding="utf-8") as f:
            header = json.loads(f.readline() or "null")
    except (OSError, ValueError):
        return {}
    if not isinstance(header, dict) or header.get("url") != url or not isinstance(header.get("refused"), dict):
        return {}
    return {str(a): [(str(r[0]), str(r[1])) for r in rs if isinstance(r, list) and len(r) == 2]
            for a, rs in header["refused"].items() if isinstance(rs, list)}


class ManifestIndex:
    """Look up single entries of a manifest (see :func:`write_manifest`) without loading it: a
    binary search over the memory-mapped file, whose lines are sorted by key. What a worker
    uses to check an object's ETag, so that a 10-million-object manifest costs it pages of the
    file, not a dictionary of every key. None when the file is absent or of another URL."""

    def __init__(self, mm, start: int):
        self.mm, self.start = mm, start

    @classmethod
    def open(cls, path: Path, url: str) -> Optional["ManifestIndex"]:
        import mmap

        try:
            with open(path, "rb") as f:
                header = json.loads(f.readline() or b"null")
                start = f.tell()
                if (not isinstance(header, dict) or header.get("v2v_manifest") != MANIFEST_VERSION
                        or header.get("url") != url or os.fstat(f.fileno()).st_size <= start):
                    return None
                return cls(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ), start)
        except (OSError, ValueError):
            return None

    def _line_at(self, pos: int) -> Tuple[int, int]:
        """(start, end) of the first whole line beginning at or after ``pos``."""
        if pos > self.start:
            nl = self.mm.find(b"\n", pos - 1)
            pos = len(self.mm) if nl < 0 else nl + 1
        end = self.mm.find(b"\n", pos)
        return pos, (len(self.mm) if end < 0 else end)

    def get(self, key: str) -> Optional[tuple]:
        """The entry of ``key``: (size, ETag[, offset...]), or None."""
        lo, hi = self.start, len(self.mm)
        while lo < hi:
            mid = (lo + hi) // 2
            a, b = self._line_at(mid)
            if a >= hi:  # no line starts in [mid, hi): look left
                hi = mid
                continue
            k, size, etag, *offset = json.loads(self.mm[a:b])
            if k == key:
                return (int(size), str(etag), *(int(o) for o in offset))
            if k < key:
                lo = b + 1
            else:
                hi = a
        return None


class StoreListing:
    """The listing a store source holds: key relative to the prefix -> (size in bytes, ETag[,
    where an archive member lies]: :func:`member_entry`) of every object under ``url`` and of the
    members of its archives (whose indexes go to ``shards``), kept as the manifest file at ``path``
    (None: none is kept) unless ``refresh`` asks for a new listing. The server loads a whole
    listing once; a worker, which holds none, looks single entries up in the manifest file
    (:class:`ManifestIndex`)."""

    def __init__(self, url: str, path: Optional[str], refresh: bool, shards: ShardIndex):
        self.url, self.path, self.refresh, self.shards = url, path, refresh, shards
        #: The listing this process holds, None until one is read or made.
        self.objects: Optional[Dict[str, tuple]] = None
        self._index: Optional[ManifestIndex] = None
        self._index_tried = False

    def read(self) -> Optional[Dict[str, tuple]]:
        """The manifest's listing; None when there is none to read (no manifest kept, a new
        listing asked for, the file absent, damaged or of another URL)."""
        if self.path and not self.refresh:
            objects = read_manifest(Path(self.path), self.url)
            if objects is not None:
                self.shards.refused.update(manifest_refused(Path(self.path), self.url))
            return objects
        return None

    def keep(self, objects: Dict[str, tuple]) -> None:
        """Hold ``objects`` (a listing or manifest) and give the archive members it has to ``shards``."""
        self.objects = objects
        for rel, v in objects.items():
            if len(v) >= 3:
                self.shards.add(rel, index_entry(v))

    def listed(self, objects: Dict[str, tuple]) -> None:
        """Hold ``objects``, a listing just made of the store, and write it as the manifest."""
        self.save(objects)
        self.refresh = False
        self.keep(objects)

    def save(self, objects: Dict[str, tuple]) -> None:
        """Write ``objects`` as the manifest (a failure is logged: the store is listed again
        at the next start)."""
        if self.path:
            try:
                write_manifest(Path(self.path), self.url, objects, self.shards.refused)
                log.info("manifest written to %s", self.path)
            except OSError as e:
                log.warning("cannot write the manifest %s: %s (the store is listed again at the next start)",
                            self.path, e)

    def save_members(self) -> None:
        """Write the archive members read from their indexes (no listing) as the manifest."""
        objects = {f"{archive}/{m}": member_entry(e, "") for archive, ms in self.shards.members.items()
                   for m, e in ms.items()}
        self.save(objects)
        self.objects = objects

    def entry(self, rel: str) -> Optional[tuple]:
        """The listing's entry for ``rel``: from the listing this process holds (the server),
        else looked up in the manifest file (a worker: one entry, not the whole manifest)."""
        if self.objects is not None:
            return self.objects.get(rel)
        if self.path and not self._index_tried:
            self._index, self._index_tried = ManifestIndex.open(Path(self.path), self.url), True
        return self._index.get(rel) if self._index is not None else None

    def identity(self, rel: str, objects) -> Optional[str]:
        """:func:`object_identity` of ``rel`` (an object, or an archive member) held in the
        ``objects`` listed here (the object, or its archive or archive's pieces), from their
        entries: None when one is not listed or has no version tag."""
        held = [self.entry(o) for o in objects]
        if any(e is None or not e[1] for e in held):
            return None
        where = None
        if split_member(rel) is not None:
            entry = self.entry(rel)
            if entry is None or len(entry) < 3:
                return None
            where = index_entry(entry)
        return object_identity(rel, sum(int(e[0]) for e in held), "+".join(e[1] for e in held), where)


def object_identity(rel: str, size: int, tag: str, where: Optional[Tuple[int, ...]]) -> str:
    """The identity (``VideoSource.identity``) of the object ``rel``, or of the archive member
    ``rel`` at index entry ``where`` (``shards``), whose object or pieces hold ``size`` bytes at
    the version tag ``tag`` (their ETags joined by ``+``)."""
    member = split_member(rel)
    if member is None:
        return f"object {size} {tag}"
    return f"{member[0][-3:].lower()} {size} {tag} member {' '.join(map(str, where))}"


def member_entry(entry: Tuple[int, ...], etag: str) -> tuple:
    """The manifest's entry of an archive member from its index ``entry`` (``shards``: offset,
    size, then a zip member's fields) and its archive's ``etag``: (size, ETag, offset, ...)."""
    return (entry[1], etag, entry[0], *entry[2:])


def index_entry(v: tuple) -> Tuple[int, ...]:
    """The index entry (``shards``) of the manifest's member entry ``v`` (:func:`member_entry`)."""
    return (v[2], v[0], *v[3:])


def etag_of(info: dict) -> str:
    """The version tag of an object in a listing or ``info()`` answer: S3's ETag, GCS's
    generation, Azure's etag (quotes stripped). GCS's generation goes first: gcsfs answers
    with an ``etag`` too, which on Google changes with the object's metadata and on emulators
    is the content's MD5 (the same bytes written again keep it); the generation is new with
    every write and only then."""
    for k in ("generation", "ETag", "etag", "md5Hash"):
        v = info.get(k)
        if v:
            return str(v).strip('"')
    return ""
