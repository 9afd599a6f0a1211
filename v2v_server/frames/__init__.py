"""What a pass reads of a source's videos: the one way into a video (``video_read.read_video``),
decoding, scaling and the kept rows, the host's caches beside a source (the frame cache and the
corpus index, ``host_caches.HostCaches``), shot cuts and where windows lie, the one window pass and
its record, ``--check``'s verdicts."""
