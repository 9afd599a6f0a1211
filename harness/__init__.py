"""Test and benchmark harnesses: servers, corpora and clips with known motion (not installed)."""
