"""The archives of one corpus (tar shards and zip parts, ``sources.shards``) as a ``VideoSource``
reads them: each archive's member index, kept per process and version of the archive; the
pieces of a split zip part, found beside it and read joined; a member opened for decoding; a
listing's archives replaced by their video members."""
from __future__ import annotations

import contextlib
from pathlib import PurePosixPath
from typing import TYPE_CHECKING, Callable, ContextManager, Dict, List, Optional, Sequence, Tuple

from v2v_server.sources.errors import VideoError
from v2v_server.sources.names import control_character, printable
from v2v_server.sources.segments import segment_name, split_segment
from v2v_server.sources.shards import (ARCHIVES, JoinedFile, MemberEntry, ShardIndex, ZipMemberError, gather_pieces, missing_piece, open_member, piece_archive, split_member)

if TYPE_CHECKING:
    from v2v_server.sources.manifest import ListedObject


class Archives:
    """The archives of the corpus at ``root`` (for messages), read through its source's
    primitives: ``open_raw(rel, expected)`` (a context manager giving a file or object as a
    binary file, an object checked against ``expected``, its listing entry), ``exists(rel)``,
    ``siblings(part)`` (names beside a zip part that may be its pieces) and ``version(archive)``
    (what stands for an archive's content; None: read its index again). Holds ``index``: the
    member indexes and split parts' pieces found so far (a store's listing fills it too)."""

    def __init__(self, root: str, open_raw: Callable[..., ContextManager], exists: Callable[[str], bool],
                 siblings: Callable[[str], List[str]], version: Callable[[str], Optional[str]]):
        self.root, self._open_raw, self._exists, self._siblings, self._version = root, open_raw, exists, siblings, version
        #: The member indexes and the pieces of split zip parts.
        self.index = ShardIndex()

    def has_member(self, rel: str, exists) -> bool:
        """Whether the archive member ``rel`` (``shard.tar/member.mp4``, a list entry such as a
        segment's video) is in its archive, which ``exists`` (a zip part: whole or in pieces)."""
        archive, name = split_member(rel)
        try:
            return (exists(archive) or archive.lower().endswith(".zip")) and name in self.members(archive)
        except Exception:  # an unreadable archive: the member is missing
            return False

    def members(self, archive: str) -> Dict[str, MemberEntry]:
        """Member name -> where it lies (``shards.TarMember`` or ``ZipMember``) in the archive at
        ``archive`` (relative path), read once per process and version of the archive
        (``version``): one rewritten in place is read again.

        Raises:
            VideoError: it is missing, or a split part lacks a piece (named).
            tarfile.TarError, zipfile.BadZipFile, OSError: it cannot be read."""
        return self.index.of(archive, self._version(archive), self.open)

    def refused(self, archive: Optional[str] = None) -> List[Tuple[str, str]]:
        """``(where, why)`` for each entry of ``archive`` (read by :meth:`members`; None: of every
        archive read, in order) that is not served (``shards.MemberIndex.refused``):
        ``archive/member``, or the archive for a line naming several members."""
        archives = sorted(self.index.refused) if archive is None else [archive]
        return [(printable(f"{a}/{name}" if name else a), printable(why))
                for a in archives for name, why in self.index.refused.get(a, ())]

    def pieces(self, archive: str) -> List[str]:
        """The files or objects that hold ``archive``: ``[archive]`` when it is one, else (a zip
        part) its pieces ``archive-stem_partaa``, ``_partab``... in order, all present.

        Raises:
            VideoError: it is missing, or a piece of it is (named)."""
        got = self.index.pieces.get(archive)
        if got is not None:
            return got
        if self._exists(archive):
            got = [archive]
        else:
            found = [n for n in self._siblings(archive) if piece_archive(n) == archive] \
                if archive.lower().endswith(".zip") else []
            if not found:
                raise VideoError(f"missing from {self.root}")
            gap = missing_piece(found)
            if gap:
                raise VideoError(f"split zip part: piece {gap} is missing (found {', '.join(sorted(found))})")
            got = sorted(found)
        self.index.pieces[archive] = got
        return got

    @contextlib.contextmanager
    def open(self, archive: str, expected: Optional[ListedObject] = None):
        """The archive at ``archive`` as one binary file: the file or object (checked against
        ``expected``, its listing entry, on a store), or a split part's pieces joined."""
        pieces = self.pieces(archive)
        if pieces == [archive]:
            with self._open_raw(archive, expected) as f:
                yield f
            return
        with contextlib.ExitStack() as stack:
            yield JoinedFile([stack.enter_context(self._open_raw(p)) for p in pieces])

    @contextlib.contextmanager
    def open_member(self, rel: str, entry: Optional[ListedObject] = None):
        """The archive member ``rel`` as a readable, seekable binary file (``shards.open_member``),
        located by its listing ``entry`` (a store's manifest) or its archive's index.

        Raises:
            VideoError: no such member, or it cannot be read (encrypted, corrupt header...)."""
        archive, name = split_member(rel)
        where = self.member_at(rel, entry)
        with self.open(archive, entry) as f:
            try:
                yield open_member(f, name, where)
            except ZipMemberError as e:
                raise VideoError(str(e)) from None

    def member_at(self, rel: str, entry: Optional[ListedObject]) -> MemberEntry:
        """Where the archive member ``rel`` lies in its archive: from its listing ``entry`` (a
        store's manifest), else the archive's index.

        Raises:
            VideoError: the archive has no such member, or cannot be read."""
        if entry is not None and entry.member is not None:
            return entry.member
        archive, name = split_member(rel)
        try:
            where = self.members(archive).get(name)
        except VideoError:
            raise
        except Exception as e:
            raise VideoError(f"{archive_kind(archive)} {archive} cannot be read: {type(e).__name__}: {e}") from None
        if where is None:
            raise VideoError(f"no member {name!r} in the {archive_kind(archive)} {archive}")
        return where

    def expand(self, names: List[str], rejected: List[Tuple[str, str]], extensions: Sequence[str]
               ) -> Tuple[List[str], List[Tuple[str, str]]]:
        """``names`` with each archive replaced by its video members, ``shard.tar/member.mp4``.
        A tar shard follows the WebDataset convention: a sample's files share a key, the video
        is the member with a video extension, the others (``.json``, ``.txt``) are not served
        and not named. A zip part is a folder in a file: each other member is named, as a
        folder's other files are."""
        out = []
        for rel in names:
            if not rel.lower().endswith(ARCHIVES):
                out.append(rel)
                continue
            kind = archive_kind(rel)
            try:
                members = self.members(rel)
            except VideoError as e:
                rejected.append((rel, f"{kind}: {e}"))
                continue
            except Exception as e:  # one unreadable archive never stops the listing
                pieces = self.index.pieces.get(rel) or [rel]
                hint = (f" (read as its pieces {', '.join(pieces)} joined: is a later piece missing?)"
                        if pieces != [rel] else "")
                rejected.append((rel, f"{kind} cannot be read: {type(e).__name__}: {e}{hint}"))
                continue
            rejected += self.refused(rel)
            named = [m for m in members if control_character(m)  # a tar shard's metadata members stay silent
                     and (kind == "zip part" or m.lower().endswith(tuple(extensions)))]
            rejected += [(printable(f"{rel}/{m}"), f"{kind} member: {control_character(m)}") for m in named]
            vids = [m for m in members if m.lower().endswith(tuple(extensions)) and not control_character(m)]
            out += [f"{rel}/{m}" for m in vids]
            if not vids:
                rejected.append((rel, f"{kind} holds no video member"))
            elif kind == "zip part":
                rejected += [(f"{rel}/{m}", f"not a video file (extension {PurePosixPath(m).suffix or 'none'!r})")
                             for m in members if not m.lower().endswith(tuple(extensions)) and m not in named]
        return out, rejected


#: How many unmatched names a pairing's one refusal line shows.
SHOWN_UNMATCHED = 5


def pair_members(entries: Sequence[str], members: Sequence[str], video_list: str, archives: str,
                 present: Callable[[str], bool] = lambda entry: False) -> Tuple[List[str], List[Tuple[str, str]]]:
    """The archive members a video list's entries name, for a list that names clips without
    the archive holding them (OpenVid-1M's CSV names ``clip.mp4``, served from
    ``OpenVid_part3.zip/clip.mp4``).

    An entry (a segment's time range kept, ``sources.segments``) names the member whose id is
    the entry (``part.zip/clip.mp4``), else whose path inside its archive is the entry, else,
    for an entry without ``/``, whose file name is the entry (what ``unzip -j`` would write).
    Pure: the same lists give the same ids wherever the archives are read from.

    Args:
        entries: the list's entries, in its order.
        members: ids of the archives' video members (``part.zip/dir/clip.mp4``).
        video_list, archives: the list and the archives as given, for messages.
        present: whether an entry names a file of the corpus itself (a folder's plain file
            beside its archives): such an entry is kept as it is, in its place.

    Returns:
        ``(ids, refused)``: the member ids in the list's order, duplicates dropped; ``(entry,
        reason)`` for each entry that more than one member matches (naming them), and one
        ``(count, reason)`` for all entries no member matches (a list of a whole corpus served
        from some of its parts names most clips in none: one line, the first few named).
    """
    by_id = set(members)
    by_path: Dict[str, List[str]] = {}
    by_file: Dict[str, List[str]] = {}
    for m in members:
        name = split_member(m).name
        by_path.setdefault(name, []).append(m)
        by_file.setdefault(PurePosixPath(name).name, []).append(m)
    out, seen, refused, unmatched = [], set(), [], []
    for entry in entries:
        if present(entry):
            if entry not in seen:
                seen.add(entry)
                out.append(entry)
            continue
        base, times = split_segment(entry)
        found = [base] if base in by_id else by_path.get(base) or ([] if "/" in base else by_file.get(base, []))
        if len(found) > 1:
            refused.append((entry, f"listed in {video_list}: more than one member of {archives} is named so "
                                   f"({', '.join(sorted(found)[:3])}{', ...' if len(found) > 3 else ''}): "
                                   f"name one as part.zip/member in the list"))
            continue
        if not found:
            unmatched.append(entry)
            continue
        rel = segment_name(found[0], *times) if times else found[0]
        if rel not in seen:
            seen.add(rel)
            out.append(rel)
    if unmatched:
        shown = ", ".join(unmatched[:SHOWN_UNMATCHED]) + (", ..." if len(unmatched) > SHOWN_UNMATCHED else "")
        refused.append((f"({len(unmatched)} entr{'y' if len(unmatched) == 1 else 'ies'})",
                        f"listed in {video_list} but no member of {archives}: {shown}"))
    return out, refused


def archive_kind(archive: str) -> str:
    """``"zip part"`` or ``"tar shard"``: what a message calls the archive ``archive``."""
    return "zip part" if archive.lower().endswith(".zip") else "tar shard"


def archive_problems(objects: Dict[str, ListedObject], unreadable: Dict[str, str], extensions: Sequence[str]
                     ) -> List[Tuple[str, str]]:
    """``(archive, reason)`` for each archive of a store's listing ``objects`` (key -> entry,
    members included) that gives no video member (it could not be read, ``unreadable``:
    archive -> why, or holds none) and each split zip part with a piece missing."""
    parts, problems = gather_pieces([k for k in objects if split_member(k) is None], set(objects))
    members = [m for m in map(split_member, objects) if m is not None]
    held, vids = {a for a, _ in members}, {a for a, m in members if m.lower().endswith(tuple(extensions))}
    for archive in sorted([k for k in objects if k.lower().endswith(ARCHIVES)] + list(parts)):
        if archive not in held:
            why = unreadable.get(archive, "no member listed (--refresh-manifest reads it again)")
            problems.append((archive, f"{archive_kind(archive)} cannot be read: {why}"))
        elif archive not in vids:
            problems.append((archive, f"{archive_kind(archive)} holds no video member"))
    return sorted(problems)
