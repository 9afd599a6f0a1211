"""Every sample of the bundled clips equals the committed table (tests/sample_hashes.py)."""
import json

from tests import sample_hashes


def test_bundled_samples_equal_the_committed_table():
    want = json.loads(sample_hashes.TABLE.read_text())
    got = sample_hashes.compute()
    assert set(got) == set(want)
    for recipe in want:
        assert got[recipe] == want[recipe], recipe
