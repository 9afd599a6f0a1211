"""Archives of videos read in place: tar shards (the WebDataset convention) and zip parts
(OpenVid-1M, VidGen-1M), their member indexes, split zip parts (``part_partaa``,
``part_partab``... as ``split`` cuts them), and brace patterns of archive names
(``webvid-{000000..000999}.tar``, ``OpenVid_part{0..185}.zip``).

A member's entry in an index is a :class:`TarMember` (offset of its data, bytes of content) or a
:class:`ZipMember` (offset of its local header, then the central directory's fields): a
:data:`MemberEntry`. An archive member's id path (``shard.tar/member.mp4``) splits into an
:class:`ArchivePath`."""
from __future__ import annotations

import dataclasses
import io
import re
from typing import Dict, Iterable, List, NamedTuple, Optional, Sequence, Set, Tuple, Union

#: The archive kinds whose members a corpus serves, by extension.
ARCHIVES = (".tar", ".zip")

#: A piece of a split zip part, as ``split -b`` names it after the joined file's stem
#: (``OpenVid_part73_partaa``, ``_partab``...; OpenVid-1M's download script joins them with ``cat``).
PIECE = re.compile(r"^(?P<stem>.+)_part(?P<suffix>[a-z]{2,})$")


@dataclasses.dataclass(frozen=True)
class TarMember:
    """Where a tar member lies: ``offset``, of its data in the archive, and ``size``, bytes of
    content (both ints, bytes)."""

    offset: int
    size: int

    def numbers(self) -> Tuple[int, ...]:
        """``(offset, size)``: what an identity string (``manifest.object_identity``) writes."""
        return (self.offset, self.size)


@dataclasses.dataclass(frozen=True)
class ZipMember:
    """Where a zip member lies and how it is stored: ``offset`` of its local header in the
    archive, ``size`` (bytes of content), then its central-directory fields: ``compressed``
    (bytes), ``crc`` (CRC-32), ``method`` (``zipfile.ZIP_STORED``, ``ZIP_DEFLATED``...) and
    ``flags`` (the general-purpose flag bits). All ints."""

    offset: int
    size: int
    compressed: int
    crc: int
    method: int
    flags: int

    def numbers(self) -> Tuple[int, ...]:
        """``(offset, size, compressed, crc, method, flags)``: what an identity string
        (``manifest.object_identity``) writes."""
        return (self.offset, self.size, self.compressed, self.crc, self.method, self.flags)


#: A member's entry in an archive's index.
MemberEntry = Union[TarMember, ZipMember]


class ArchivePath(NamedTuple):
    """An archive member's id path split: ``archive`` (``shard.tar``, ``dir/part.zip``) and
    ``name``, the member's path inside it (``member.mp4``, ``clips/a.mp4``)."""

    archive: str
    name: str


class MemberIndex(NamedTuple):
    """An archive's member index: ``members``, name -> :data:`MemberEntry` of each member
    served; ``refused``, ``(name, why)`` for each entry that is not: a member's name, or ''
    for a line about the archive that names its members."""

    members: Dict[str, MemberEntry]
    refused: List[Tuple[str, str]]


def last_of_each_name(kind: str, entries: Sequence[Tuple[str, MemberEntry]]) -> MemberIndex:
    """The members of ``entries`` (name, entry; archive order) with one entry per name: of
    several members of one name the last is served, as ``tar -x`` and ``unzip`` leave it
    on disk (each overwrites the one before), and each earlier one is refused, named with its
    offset (``kind``: what a message calls the archive)."""
    members: Dict[str, MemberEntry] = {}
    last: Dict[str, int] = {}
    for k, (name, entry) in enumerate(entries):
        members[name], last[name] = entry, k
    count = {name: 0 for name in last}
    for name, _ in entries:
        count[name] += 1
    refused = [("", f"{kind}: {count[name]} members are named {name}; the last (at offset {members[name].offset}) "
                    f"is served, as tar and unzip extract it, the one at offset {entry.offset} is not")
               for k, (name, entry) in enumerate(entries) if last[name] != k]
    return MemberIndex(members, refused)


def tar_members(f) -> MemberIndex:
    """The member index of the tar read from the binary file object ``f``: name ->
    :class:`TarMember` (offset of its data, size; bytes) of every regular file, in one pass over the headers (the data
    between them is skipped by seeking; an object-store file fetches the blocks that hold
    headers); of several members of one name the last (:func:`last_of_each_name`). Refused:
    a sparse member (GNU ``tar -S``), whose bytes are not stored in one piece, a hard or
    symbolic link (served, it would be its target again under a second id), and a member whose
    size runs past the end of the shard (a shard cut short, or a lying header): only that
    member, the ones before it are served.

    Raises:
        tarfile.TarError: not a tar archive.
    """
    import tarfile

    end = f.seek(0, io.SEEK_END)
    f.seek(0)
    with tarfile.open(fileobj=f, mode="r:") as tar:
        try:
            for _ in tar:
                pass
        except tarfile.ReadError:  # "unexpected end of data": the last header's size runs past the end
            if not tar.members:
                raise
        every = tar.members
    cut = [(m.name, f"tar shard: its bytes {m.offset_data}-{m.offset_data + m.size} run past the end of the shard "
                    f"({end} bytes): cut short or corrupt, not served")
           for m in every if m.isfile() and not m.issparse() and m.offset_data + m.size > end]
    files = [m for m in every if m.isfile() and (m.issparse() or m.offset_data + m.size <= end)]
    kept = last_of_each_name("tar shard", [(m.name, TarMember(m.offset_data, m.size))
                                           for m in files if not m.issparse()])
    sparse = [(m.name, f"tar shard: a sparse member (tar -S): its {m.size} bytes are not stored in one piece, "
                       f"not served") for m in files if m.issparse()]
    links = [(m.name, f"tar shard: a {'hard' if m.islnk() else 'symbolic'} link to {m.linkname}: not served (a "
                      f"link in a shard is not followed; its target is served under its own name)")
             for m in every if (m.islnk() or m.issym()) and m.name not in kept.members]
    return MemberIndex(kept.members, cut + sparse + links + kept.refused)


#: Bytes of a zip local header before its name (``zipfile.sizeFileHeader``).
LOCAL_HEADER = 30


def zip_members(f) -> MemberIndex:
    """The member index of the zip read from the binary file object ``f``: name ->
    :class:`ZipMember` (offset of its local header, size, compressed size, CRC-32, method,
    flag bits) of every file, from its central directory, read by
    ``zipfile`` (ZIP64 included; on a store, the blocks at the end of the object). Folders
    are left out. Refused (:attr:`MemberIndex.refused`), the rest served:

    * a member whose bytes run into the central directory or past the end of the file (sizes
      that lie, or a part cut short): only that member, named; its neighbours are served;
    * of the rest, members whose bytes overlap (several central-directory entries at one local
      header, or one member's compressed bytes running over the next one's header: the layout
      of an overlapping "zip bomb", whose one kernel each member would inflate again), each
      group in one line; ``unzip -t`` refuses such a part whole;
    * of several members of one name, all but the last (:func:`last_of_each_name`).

    A member's extent is its local header, name and compressed bytes (its extra field, known
    only from the local header, is not read here: ``open_member`` checks that header).

    Raises:
        zipfile.BadZipFile: no end record, or a central directory that is truncated or corrupt.
        OSError, ValueError: the file cannot be read.
    """
    import zipfile

    with zipfile.ZipFile(f) as z:
        infos = [i for i in z.infolist() if not i.is_dir()]
        directory = z.start_dir
    size = f.seek(0, io.SEEK_END)
    refused: List[Tuple[str, str]] = []
    bad: Set[int] = set()
    spans = sorted((i.header_offset, i.header_offset + LOCAL_HEADER + _name_bytes(i) + i.compress_size, n)
                   for n, i in enumerate(infos))
    for start, stop, n in spans:
        if stop > directory:
            past = f"past the end of the file ({size} bytes)" if stop > size else \
                f"into the central directory (at {directory})"
            refused.append((infos[n].filename, f"zip part: its bytes {start}-{stop} run {past}: corrupt or hostile, "
                                               f"not served"))
            bad.add(n)
    group, end = [], -1
    for start, stop, n in [span for span in spans if span[2] not in bad] + [(1 << 64, 1 << 64, -1)]:
        if start < end:
            group.append(n)
            end = max(end, stop)
            continue
        if len(group) > 1:
            names = [infos[k].filename for k in group]
            shown = ", ".join(names[:5]) + (f", ... ({len(names)} in all)" if len(names) > 5 else "")
            lo, hi = min(infos[k].header_offset for k in group), end
            refused.append(("", f"zip part: members {shown} overlap (bytes {lo}-{hi} are shared by {len(group)} "
                                f"central-directory entries, the layout of a zip bomb): none of them is served, "
                                f"as unzip -t refuses the part"))
            bad.update(group)
        group, end = [n], stop
    kept = last_of_each_name("zip part", [(i.filename, ZipMember(i.header_offset, i.file_size, i.compress_size, i.CRC,
                                                                 i.compress_type, i.flag_bits))
                                          for n, i in enumerate(infos) if n not in bad])
    return MemberIndex(kept.members, refused + kept.refused)


def _name_bytes(info) -> int:
    """Bytes of a zip member's name as its headers hold it (UTF-8 with flag bit 11, else CP437)."""
    try:
        return len(info.orig_filename.encode("utf-8" if info.flag_bits & 0x800 else "cp437"))
    except UnicodeEncodeError:  # decoded with another metadata encoding: the bound without its name
        return 0


def archive_members(archive: str, f) -> MemberIndex:
    """The member index of ``archive`` (a name ending in ``.tar`` or ``.zip``) read from ``f``:
    :func:`tar_members` or :func:`zip_members`; their errors."""
    return zip_members(f) if archive.lower().endswith(".zip") else tar_members(f)


class SizedReader(io.RawIOBase):
    """A read-only, seekable binary file of ``size`` bytes at position ``pos``: seeks stay within
    ``[0, size]`` and only move the position; a subclass reads from it (``readinto``)."""

    def __init__(self, size: int):
        super().__init__()
        self.size, self.pos = size, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence]
        self.pos = min(max(0, base + pos), self.size)
        return self.pos


class MemberFile(SizedReader):
    """A read-only, seekable window ``[offset, offset + size)`` of the binary file ``f``: a tar
    member or a stored zip member, read in place (FFmpeg decodes it like a file of its own)."""

    def __init__(self, f, offset: int, size: int):
        super().__init__(size)
        self.f, self.offset = f, offset

    def readinto(self, b) -> int:
        n = min(len(b), self.size - self.pos)
        if n <= 0:
            return 0
        self.f.seek(self.offset + self.pos)
        data = self.f.read(n)
        b[:len(data)] = data
        self.pos += len(data)
        return len(data)


class ZipMemberError(ValueError):
    """A zip member that cannot be read (the message names the member and why)."""


def open_member(f, name: str, entry: MemberEntry):
    """The member ``name`` of the archive read from ``f``, given its index ``entry``, as a
    readable, seekable binary file: a tar member or a stored zip member is a :class:`MemberFile` over its bytes in place; a compressed zip member (deflate, bzip2,
    LZMA) is ``zipfile``'s streaming reader over its compressed bytes, which checks the CRC-32
    at the end (a seek backwards starts decompressing again from the member's start).

    Raises:
        ZipMemberError: the local header at the entry's offset is not this member's (no
            header, or one of another name), or the member is encrypted or compressed by a
            method ``zipfile`` does not read.
        OSError: the archive cannot be read.
    """
    if isinstance(entry, TarMember):
        return MemberFile(f, entry.offset, entry.size)
    import struct
    import zipfile

    offset, size, csize, crc, method, flags = entry.numbers()
    f.seek(offset)
    head = f.read(zipfile.sizeFileHeader)
    fields = struct.unpack(zipfile.structFileHeader, head) if len(head) == zipfile.sizeFileHeader else None
    if fields is None or fields[0] != zipfile.stringFileHeader:
        raise ZipMemberError(f"zip member {name}: no local header at offset {offset} (corrupt archive)")
    name_len, extra_len = fields[-2], fields[-1]
    raw = f.read(name_len)
    local = raw.decode("utf-8" if fields[3] & 0x800 else "cp437", "replace").split("\x00")[0]
    if local != name:
        raise ZipMemberError(f"zip member {name}: the local header at offset {offset} names {local!r}, not this "
                             f"member (entries that share a header, or a corrupt part): not served")
    data = offset + zipfile.sizeFileHeader + name_len + extra_len
    if flags & 0x1:
        raise ZipMemberError(f"zip member {name}: encrypted (not served)")
    if method == zipfile.ZIP_STORED:
        return MemberFile(f, data, size)
    if method not in (zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA):
        raise ZipMemberError(f"zip member {name}: compression method {method} is not read (stored, deflate, "
                             f"bzip2 and LZMA are)")
    info = zipfile.ZipInfo(name)
    info.compress_type, info.file_size, info.compress_size, info.CRC, info.flag_bits = method, size, csize, crc, flags
    return CompressedMember(zipfile.ZipExtFile(MemberFile(f, data, csize), "r", info), size)


class CompressedMember(SizedReader):
    """A compressed zip member (``reader``: zipfile's streaming reader, ``size``: bytes of
    content) whose seeks move only a position until the next read: FFmpeg's probes of the
    size (a seek to the end and back) then cost no decompression, and a seek backwards
    restarts decompression from the member's start once, when read from."""

    def __init__(self, reader, size: int):
        super().__init__(size)
        self.reader = reader
        #: The first read that failed (corrupt data: a bad CRC-32, a broken stream): it is raised
        #: once, as :class:`ZipMemberError`, and later reads find the end (FFmpeg retries a read).
        self.error: Optional[str] = None

    def readinto(self, b) -> int:
        if self.pos >= self.size or self.error is not None:
            return 0
        try:
            if self.reader.tell() != self.pos:
                self.reader.seek(self.pos)
            data = self.reader.read(len(b))
        except Exception as e:  # zipfile.BadZipFile, zlib.error, EOFError, lzma.LZMAError, OSError
            self.error = f"zip member {self.reader.name}: corrupt data ({type(e).__name__}: {e})"
            raise ZipMemberError(self.error) from None
        b[:len(data)] = data
        self.pos += len(data)
        return len(data)


class JoinedFile(SizedReader):
    """The binary files ``files`` read one after another as one read-only, seekable file: a
    split zip part read as the archive ``cat`` would join, without joining it."""

    def __init__(self, files: Sequence):
        self.files, self.starts = list(files), [0]
        for f in self.files:
            self.starts.append(self.starts[-1] + f.seek(0, io.SEEK_END))
        super().__init__(self.starts[-1])

    def readinto(self, b) -> int:
        import bisect

        want, done = min(len(b), self.size - self.pos), 0
        while done < want:  # a read across pieces is whole: zipfile reads headers in one call
            i = bisect.bisect_right(self.starts, self.pos) - 1
            f = self.files[i]
            f.seek(self.pos - self.starts[i])
            data = f.read(min(want - done, self.starts[i + 1] - self.pos))
            if not data:
                break  # a piece shorter than it was: the reader finds the archive cut short
            b[done:done + len(data)] = data
            done += len(data)
            self.pos += len(data)
        return done


def piece_archive(name: str) -> Optional[str]:
    """The zip part that ``name`` is a piece of (``a/X_partab`` -> ``a/X.zip``), or None."""
    m = PIECE.match(name)
    if m is None:
        return None
    stem = m.group("stem")
    return stem if stem.lower().endswith(".zip") else stem + ".zip"


def _suffixes(first: str):
    """``split``'s suffixes from ``first`` on: ``aa, ab, ..., az, ba...``."""
    s = list(first)
    while True:
        yield "".join(s)
        i = len(s) - 1
        while i >= 0 and s[i] == "z":
            s[i] = "a"
            i -= 1
        if i < 0:
            return
        s[i] = chr(ord(s[i]) + 1)


def piece_names(part: str):
    """The names the pieces of the zip part ``part`` would have, in order (``a/X.zip`` ->
    ``a/X_partaa``, ``a/X_partab``...), without end: what a reader without a listing (plain
    HTTP) asks for until one is missing."""
    stem = part[:-len(".zip")] if part.lower().endswith(".zip") else part
    return (f"{stem}_part{suffix}" for suffix in _suffixes("aa"))


def missing_piece(pieces: Sequence[str]) -> Optional[str]:
    """The first piece absent from ``pieces`` (names of one part's pieces, any order), which
    ``split`` numbers ``aa, ab...`` without a gap; None when none is missing before the last."""
    found = sorted(pieces)
    m = PIECE.match(found[0])
    stem, width = m.group("stem"), len(m.group("suffix"))
    for have, want in zip(found, _suffixes("a" * width)):
        if have != f"{stem}_part{want}":
            return f"{stem}_part{want}"
    return None


def gather_pieces(names: Iterable[str], whole: Set[str]) -> Tuple[Dict[str, List[str]], List[Tuple[str, str]]]:
    """``(parts, rejected)`` of the split pieces among ``names`` (others are left out): each
    zip part whose pieces are all present -> its pieces in order, and ``(name, reason)`` for a
    part with a piece missing (named) and for the pieces of a part present whole (in ``whole``)."""
    groups: Dict[str, List[str]] = {}
    for n in names:
        part = piece_archive(n)
        if part is not None:
            groups.setdefault(part, []).append(n)
    parts, rejected = {}, []
    for part, pieces in sorted(groups.items()):
        gap = missing_piece(pieces)
        if part in whole:
            rejected += [(p, f"a piece of the zip part {part}, which is present whole (read from it)") for p in pieces]
        elif gap:
            rejected.append((part, f"split zip part: piece {gap} is missing (found {', '.join(sorted(pieces))})"))
        else:
            parts[part] = sorted(pieces)
    return parts, rejected


def expand_braces(pattern: str) -> List[str]:
    """The names a brace pattern stands for, in order: ``{000..003}`` is a zero-padded numeric
    range (as the WebDataset tools write shard names), ``{a,b}`` a list; several braces
    multiply. ``shards-{0..1}-{a,b}.tar`` -> ``shards-0-a.tar, shards-0-b.tar, shards-1-a.tar...``

    Raises:
        ValueError: a brace that is neither form.
    """
    import re

    m = re.search(r"\{([^{}]*)\}", pattern)
    if m is None:
        return [pattern]
    body = m.group(1)
    r = re.fullmatch(r"(\d+)\.\.(\d+)", body)
    if r:
        lo, hi = int(r.group(1)), int(r.group(2))
        width = len(r.group(1)) if r.group(1).startswith("0") else 0
        items = [str(i).zfill(width) for i in range(lo, hi + 1)]
    elif "," in body:
        items = body.split(",")
    else:
        raise ValueError(f"{pattern}: brace {{{body}}} is neither a range {{000..009}} nor a list {{a,b}}")
    head, tail = pattern[:m.start()], pattern[m.end():]
    return [x for item in items for x in expand_braces(head + item + tail)]


def split_pattern(videos: str) -> Tuple[str, Optional[List[str]]]:
    """``(root, names)`` of a corpus given as a brace pattern of archives
    (``s3://b/webvid-{000000..000009}.tar``: root ``s3://b/``, names ``webvid-000000.tar``...;
    the root is the pattern up to the last ``/`` before the first brace), or ``(videos, None)``
    for a folder or prefix; a single ``.tar`` or ``.zip`` is a pattern of one. A local folder
    that exists is that folder, whatever its name holds (``clips{2024}``, ``a{1,2}``).

    Raises:
        ValueError: a brace that is neither form (``expand_braces``)."""
    import os

    brace = videos.find("{")
    if brace >= 0 and "://" not in videos and os.path.isdir(videos):
        return videos, None
    if brace < 0 and not videos.lower().endswith(ARCHIVES):
        return videos, None
    cut = videos.rfind("/", 0, brace if brace >= 0 else len(videos)) + 1
    return videos[:cut] or ".", expand_braces(videos[cut:])


def split_member(rel: str) -> Optional[ArchivePath]:
    """``ArchivePath("shard.tar", "member.mp4")`` or ``ArchivePath("part.zip", "member.mp4")``
    for an archive member's id path (the first ``.tar/`` or ``.zip/`` ends the archive's
    name), else None."""
    low = rel.lower()
    hits = [i for i in (low.find(".tar/"), low.find(".zip/")) if i >= 0]
    if not hits:
        return None
    i = min(hits)
    return ArchivePath(rel[:i + 4], rel[i + 5:])


class ShardIndex:
    """The member indexes of one source's archives: archive -> member name -> :data:`MemberEntry`,
    each read from the archive (:func:`archive_members`) once per process
    and version of the archive, or given by a listing that holds them (a store's manifest);
    and the pieces of its split zip parts (part -> pieces in order, one name for a whole one)."""

    def __init__(self):
        self.members: Dict[str, Dict[str, MemberEntry]] = {}
        #: Archive -> its entries not served, ``(member name or '', why)`` (:class:`MemberIndex`).
        self.refused: Dict[str, List[Tuple[str, str]]] = {}
        self._versions: Dict[str, Optional[str]] = {}
        #: Zip part -> its pieces in order (``[part]`` itself when whole), as found.
        self.pieces: Dict[str, List[str]] = {}

    def of(self, archive: str, version: Optional[str], open_archive) -> Dict[str, MemberEntry]:
        """The index of ``archive``, read (``open_archive(archive)``: a context manager giving it
        as a binary file) when it is not held or when ``version``, what stands for the
        archive's content, differs from the one it was read at; None: always read it.

        Raises:
            tarfile.TarError, zipfile.BadZipFile, OSError, VideoError: the archive cannot be
                read (as :func:`archive_members` and ``open_archive``)."""
        if archive not in self.members or version is None or self._versions.get(archive, "") != version:
            with open_archive(archive) as f:
                self.members[archive], self.refused[archive] = archive_members(archive, f)
            self._versions[archive] = version
        return self.members[archive]

    def add(self, rel: str, entry: MemberEntry) -> None:
        """Hold the member ``rel`` (``shard.tar/member.mp4``) found by a listing, its ``entry``."""
        archive, name = split_member(rel)
        self.members.setdefault(archive, {})[name] = entry
