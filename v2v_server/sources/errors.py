"""The two errors a source raises: a video that cannot be used (:class:`VideoError`: that video's
verdict, the rest of the corpus is served) and a corpus that cannot be reached at all
(:class:`StoreError`: the service stops at its start)."""
from __future__ import annotations


class VideoError(RuntimeError):
    """A file that cannot be used as a video (the message says why): missing, unreadable, changed
    since it was listed, not decodable."""


class StoreError(RuntimeError):
    """The corpus cannot be reached at all (a folder that does not exist, no such bucket, refused
    credentials, no library for the URL's protocol); the message names it. ``v2v-serve`` exits
    2 on it."""
