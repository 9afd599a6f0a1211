"""Labelled shot cuts of the bundled clips, shared by ``tests/test_shots.py`` and ``bench.shots``."""

#: The cut frames of the bundled montages, read by eye frame by frame (docs/shots.md lists them);
#: webvid_like_596x336.mp4 is bikes.mp4 forward, then backward (its frame j >= 250 shows bikes
#: frame 498 - j), so each cut c of bikes.mp4 appears again at 499 - c.
LABELLED = {
    "bikes.mp4": [30, 76, 137, 187, 242],
    "webvid_like_596x336.mp4": [30, 76, 137, 187, 242, 257, 312, 362, 423],
    "bbb_camera_596x336.mp4": [],
    "bigbuckbunny.mp4": [],
}
