"""The manifest of an object-store corpus: the store's objects as one walk of the bucket found them
(key, size, ETag; archive members with their offset), kept as one sorted JSON line per object, so
a restart and every shard read them without walking the bucket again, and a worker looks up
single entries without loading it (:class:`ManifestIndex`). A ``sources.store.StoreSource``
holds its objects as a :class:`Manifest`, which writes and reads the file."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from v2v_server.sources.shards import MemberEntry, ShardIndex, TarMember, ZipMember, split_member

log = logging.getLogger("v2v.source")

MANIFEST_VERSION = 1


@dataclasses.dataclass(frozen=True)
class ListedObject:
    """A listing's entry for one key: ``size``, bytes of the object (of an archive member: of
    its content); ``tag``, the version tag (``etag_of``; a member's: its archive's, a split
    part's pieces' joined by ``+``; '' when the store gives none); ``member``, where an archive
    member lies in its archive (``shards.TarMember`` or ``ZipMember``), None for an object."""

    size: int
    tag: str
    member: Optional[MemberEntry] = None

    def line(self, key: str) -> list:
        """The manifest's JSON line for ``key`` (see :func:`write_manifest`)."""
        if self.member is None:
            return [key, self.size, self.tag]
        return [key, self.size, self.tag, self.member.offset, *self.member.numbers()[2:]]


def listed_from_line(values: Sequence) -> Tuple[str, ListedObject]:
    """``(key, entry)`` of a manifest line's JSON values (:meth:`ListedObject.line`): after key,
    size and tag, no number for an object, one (the data's offset) for a tar member, five (the
    local header's offset, compressed size, CRC-32, method, flag bits) for a zip member.

    Raises:
        ValueError, TypeError: a line of another shape."""
    key, size, tag, *numbers = values
    size, numbers = int(size), [int(n) for n in numbers]
    if len(numbers) not in (0, 1, 5):
        raise ValueError(f"manifest entry {key!r}: {len(numbers)} numbers after size and tag (0, 1 or 5 expected)")
    member = (None if not numbers else TarMember(numbers[0], size) if len(numbers) == 1
              else ZipMember(numbers[0], size, *numbers[1:]))
    return str(key), ListedObject(size, str(tag), member)


def manifest_path(url: str, cache_dir: Optional[str] = None) -> Path:
    """Where the manifest of the corpus at ``url`` is kept: ``CACHE_DIR/manifests/H.jsonl`` with
    ``cache_dir`` the resolved cache folder
    (:func:`cache_folder`, applied by the caller); H is a hash of the URL. Shards on one host
    share it; shards on other hosts list the store once each and, the store unchanged, write
    the same manifest.

    Raises:
        ValueError: no ``cache_dir`` is given.
    """
    h = hashlib.sha256(url.encode("utf-8")).hexdigest()[:16]
    if not cache_dir:
        raise ValueError(f"the manifest of {url} needs a resolved cache folder")
    return Path(cache_dir) / "manifests" / f"{h}.jsonl"


def write_manifest(path: Path, url: str, objects: Dict[str, ListedObject],
                   refused: Optional[Dict[str, List[Tuple[str, str]]]] = None) -> None:
    """Write ``objects`` (key relative to the prefix, or ``shard.tar/member`` for an archive's
    member -> :class:`ListedObject`) atomically:
    a header line ``{"v2v_manifest": 1, "url", "objects", "listed_at"}`` (and ``"refused"``:
    archive -> ``[[member or '', why], ...]``, the archive entries not served,
    ``shards.ShardIndex.refused``, when there are any: a restart names them again without
    reading the archive), then one JSON line per entry, sorted by key: ``[key, size, etag]`` for
    an object; ``[key, size, etag, offset of its data]`` for a tar member; ``[key, size, etag,
    offset of its local header, compressed size, CRC-32, method, flag bits]`` for a zip member
    (the archive's ETag; sizes and offsets in bytes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        header = {"v2v_manifest": MANIFEST_VERSION, "url": url, "objects": len(objects),
                  "listed_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        if any(refused.values() if refused else ()):
            header["refused"] = {a: [list(r) for r in rs] for a, rs in sorted(refused.items()) if rs}
        f.write(json.dumps(header, ensure_ascii=False) + "\n")
        for key in sorted(objects):
            f.write(json.dumps(objects[key].line(key), ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def read_manifest(path: Path, url: str) -> Optional[Dict[str, ListedObject]]:
    """The objects of the manifest at ``path`` (see :func:`write_manifest`), or None when there
    is none, it is of another URL or version, it is cut short (a crash while written by
    another process) or a line is of another shape: it is then listed again."""
    try:
        with open(path, encoding="utf-8") as f:
            header = json.loads(f.readline() or "null")
            if not isinstance(header, dict) or header.get("v2v_manifest") != MANIFEST_VERSION or header.get("url") != url:
                return None
            objects = {}
            for line in f:
                key, entry = listed_from_line(json.loads(line))
                objects[key] = entry
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

    def get(self, key: str) -> Optional[ListedObject]:
        """The entry of ``key``, or None.

        Raises:
            ValueError, TypeError: its line is of another shape (a damaged manifest)."""
        lo, hi = self.start, len(self.mm)
        while lo < hi:
            mid = (lo + hi) // 2
            a, b = self._line_at(mid)
            if a >= hi:  # no line starts in [mid, hi): look left
                hi = mid
                continue
            values = json.loads(self.mm[a:b])
            k = values[0]
            if k == key:
                return listed_from_line(values)[1]
            if k < key:
                lo = b + 1
            else:
                hi = a
        return None


class Manifest:
    """The objects a store source holds: key relative to the prefix -> :class:`ListedObject` of
    every object under ``url`` and of the members of its archives (whose indexes go to
    ``shards``), kept as the manifest file at ``path`` (None: none is kept) unless ``refresh``
    asks for a new walk of the store. The server loads them all once; a worker, which holds
    none, looks single entries up in the manifest file (:class:`ManifestIndex`)."""

    def __init__(self, url: str, path: Optional[str], refresh: bool, shards: ShardIndex):
        self.url, self.path, self.refresh, self.shards = url, path, refresh, shards
        #: The listing this process holds, None until one is read or made.
        self.objects: Optional[Dict[str, ListedObject]] = None
        self._index: Optional[ManifestIndex] = None
        self._index_tried = False

    def read(self) -> Optional[Dict[str, ListedObject]]:
        """The manifest's listing; None when there is none to read (no manifest kept, a new
        listing asked for, the file absent, damaged or of another URL)."""
        if self.path and not self.refresh:
            objects = read_manifest(Path(self.path), self.url)
            if objects is not None:
                self.shards.refused.update(manifest_refused(Path(self.path), self.url))
            return objects
        return None

    def keep(self, objects: Dict[str, ListedObject]) -> None:
        """Hold ``objects`` (a listing or manifest) and give the archive members it has to ``shards``."""
        self.objects = objects
        for rel, v in objects.items():
            if v.member is not None:
                self.shards.add(rel, v.member)

    def listed(self, objects: Dict[str, ListedObject]) -> None:
        """Hold ``objects``, a listing just made of the store, and write it as the manifest."""
        self.save(objects)
        self.refresh = False
        self.keep(objects)

    def save(self, objects: Dict[str, ListedObject]) -> None:
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
        objects = {f"{archive}/{m}": ListedObject(e.size, "", e) for archive, ms in self.shards.members.items()
                   for m, e in ms.items()}
        self.save(objects)
        self.objects = objects

    def entry(self, rel: str) -> Optional[ListedObject]:
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
        if any(e is None or not e.tag for e in held):
            return None
        where = None
        if split_member(rel) is not None:
            entry = self.entry(rel)
            if entry is None or entry.member is None:
                return None
            where = entry.member
        return object_identity(rel, sum(e.size for e in held), "+".join(e.tag for e in held), where)


def object_identity(rel: str, size: int, tag: str, where: Optional[MemberEntry]) -> str:
    """The identity (``VideoSource.identity``) of the object ``rel``, or of the archive member
    ``rel`` at ``where`` in its archive, whose object or pieces hold ``size`` bytes at the
    version tag ``tag`` (their ETags joined by ``+``): ``object SIZE TAG``, or ``tar SIZE TAG
    member OFFSET SIZE`` (``zip ... member`` and the zip member's six numbers,
    ``ZipMember.numbers``)."""
    member = split_member(rel)
    if member is None:
        return f"object {size} {tag}"
    return f"{member.archive[-3:].lower()} {size} {tag} member {' '.join(map(str, where.numbers()))}"


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
