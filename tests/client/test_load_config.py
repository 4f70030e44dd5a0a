"""The load generator's settings and report on edge cases (no server needed): bad settings are refused by
name before any thread starts, and a run where nothing succeeded reports no NaN latencies."""

from __future__ import annotations

import pytest

from fmgs_client.load import LoadConfig, LoadReport


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"texts": ()}, "texts: need one or more strings"),
        ({"texts": "red cup"}, "texts: need one or more strings"),
        ({"clients": 0}, "clients must be >= 1, got 0"),
        ({"requests": -1}, "requests must be >= 0, got -1"),
        ({"render_every": -2}, "render_every must be >= 0, got -2"),
        ({"top_k": -1}, "top_k must be >= 0, got -1"),
        ({"timeout_s": 0.0}, "timeout_s must be a positive number of seconds, got 0.0"),
        ({"max_seconds": float("nan")}, "max_seconds must be a positive number of seconds, got nan"),
    ],
)
def test_bad_settings_are_refused_by_name(kw, match):
    with pytest.raises(ValueError, match=match):
        LoadConfig(**{"scene": "s", "texts": ("a",), **kw})


def test_summary_of_a_run_where_nothing_succeeded_shows_no_nan():
    rep = LoadReport(sent=4, seconds=1.0)
    rep.codes["UNAVAILABLE"] = 4
    s = rep.summary()
    assert "nan" not in s.lower() and "0 OK" in s and "no latencies" in s and "UNAVAILABLE" in s
    rep.ok, rep.latencies_ms = 1, [12.0]
    assert "p50 12.0 ms, p99 12.0 ms" in rep.summary()
