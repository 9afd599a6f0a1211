"""The line v2v-train ends with (``trainer.feed_report.feed_line``): fed or starved, and what
would feed a starved run from the server's own figures."""
from __future__ import annotations

from trainer.feed_report import feed_line

STARVED = {"samples_per_s": 44.7, "data_wait_fraction": 0.56, "model_samples_per_s": 113.0}


def test_a_run_that_hardly_waited_was_fed_and_the_model_sets_the_pace():
    line = feed_line({"samples_per_s": 60.0, "data_wait_fraction": 0.02, "model_samples_per_s": 61.2},
                     {"workers": 14, "frame_cache_gb": 0, "busy_s": {"decode": 9.0, "simulate": 1.0}})
    assert line.startswith("fed: 60.0 samples/s, waiting 2 % of the time") and "61.2" in line


def test_a_starved_run_is_told_how_many_workers_would_feed_it():
    line = feed_line(STARVED, {"workers": 14, "frame_cache_gb": 20.0, "busy_s": {"decode": 5.0, "simulate": 5.0}})
    # 44.7 / 14 = 3.19 samples/s a worker; 113 / 3.19 -> 36 workers
    assert line.startswith("starved: 44.7 samples/s, waiting 56 % of the time for batches; the model alone trains 113.0")
    assert "about 22 more decode worker(s) at this recipe (36 in all, 3.19 samples/s each)" in line
    assert "--frame-cache-gb" not in line  # it has one


def test_a_starved_run_decoding_without_a_frame_cache_is_told_what_one_would_give():
    line = feed_line(STARVED, {"workers": 14, "frame_cache_gb": 0, "busy_s": {"decode": 6.0, "simulate": 3.0,
                                                                             "flow": 1.0}})
    # decode is 60 % of the workers' time: 3.19 / 0.4 = 7.98 samples/s a worker -> 15 workers
    assert "or --frame-cache-gb (decode is 60 % of the workers' time, paid once per video with it: then about 15 " \
           "in all)" in line


def test_without_the_servers_figures_or_a_timed_step_the_line_says_so():
    assert "the server did not report its workers" in feed_line(STARVED, None)
    assert feed_line({"samples_per_s": None, "data_wait_fraction": None, "model_samples_per_s": None}) == \
        "not measured: no step after the first"
