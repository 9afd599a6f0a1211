"""Listing a corpus folder: a recursive, sorted walk for video files that names every entry it
leaves out (other extensions, links leaving the root, loops, unreadable folders, names that cannot
be sample ids). ``sources.local.LocalSource`` lists a folder with it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Sequence, Tuple, Union

from v2v_server.sources.names import name_problem, name_suffix, printable


def scan_corpus(root: Path, extensions: Sequence[str]) -> Tuple[List[Path], List[Tuple[Path, str]]]:
    """Walk ``root`` recursively (sorted, symlink loops cut) for video files.

    Returns ``(videos, rejected)``: video paths relative to ``root`` with an accepted
    extension, and ``(relative path, reason)`` for every other entry met: other extensions,
    symlink loops, dangling links, links that leave the corpus root, unreadable folders, and
    names that are not valid UTF-8 (a sample id is its path, and ids travel as UTF-8; such a
    name is reported with its undecodable bytes escaped, ``\\xff``).
    """
    videos, rejected = scan_corpus_names(root, extensions)
    return [Path(v) for v in videos], [(Path(r), why) for r, why in rejected]


def scan_corpus_names(root: Union[str, Path], extensions: Sequence[str]) -> Tuple[List[str], List[Tuple[str, str]]]:
    """:func:`scan_corpus` with POSIX strings for paths, sorted; ``"."`` names ``root``
    itself. Only symbolic links are resolved (a folder's other entries lie where the folder
    does), so the walk costs one directory read per folder and a path resolution per link:
    linear in the entries."""
    root = Path(root)
    videos: List[str] = []
    rejected: List[Tuple[str, str]] = []
    try:
        real_root = root.resolve(strict=True)
    except (OSError, RuntimeError) as e:
        return [], [(".", f"folder cannot be resolved: {e}")]
    seen_dirs = set()
    stack = [("", str(root), str(real_root))]  # (path relative to root, path, resolved path)
    while stack:
        rel_dir, d, real = stack.pop()
        if real in seen_dirs:
            continue
        seen_dirs.add(real)
        try:
            with os.scandir(d) as it:
                entries = sorted(it, key=lambda e: e.name)
        except OSError as e:
            rejected.append((rel_dir or ".", f"folder cannot be read: {e.strerror or e}"))
            continue
        for entry in entries:
            rel = f"{rel_dir}/{entry.name}" if rel_dir else entry.name
            if name_problem(rel) is not None:
                rejected.append((printable(rel), name_problem(rel)))
                continue
            try:
                link = entry.is_symlink()
                if link:
                    target = Path(entry.path).resolve(strict=True)
                    if not target.is_relative_to(real_root):
                        rejected.append((rel, "points outside the corpus root"))
                        continue
                    real_target, is_dir = str(target), target.is_dir()
                    is_file = not is_dir and target.is_file()
                else:
                    real_target = os.path.join(real, entry.name)
                    is_dir = entry.is_dir(follow_symlinks=False)
                    is_file = not is_dir and entry.is_file(follow_symlinks=False)
            except RuntimeError:
                rejected.append((rel, "symlink loop"))
                continue
            except OSError as e:
                reason = "symlink loop" if e.errno == 40 else "dangling symlink" if entry.is_symlink() else str(e)
                rejected.append((rel, reason))
                continue
            suffix = name_suffix(entry.name)
            if is_dir:
                stack.append((rel, entry.path, real_target))
            elif suffix.lower() in extensions and is_file:
                videos.append(rel)
            else:
                rejected.append((rel, f"not a video file (extension {suffix or 'none'!r})"))
    videos.sort()
    rejected.sort(key=lambda r: r[0])
    return videos, rejected


def find_videos(root: Path, extensions: Sequence[str]) -> List[Path]:
    """Video files under ``root`` (see ``scan_corpus``), relative to ``root``."""
    return scan_corpus(root, extensions)[0]
