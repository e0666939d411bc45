"""``kamino bench``: the benchmark runs from the command line (here on Warp's CPU device, 2 worlds)."""

import json

import pytest

from kamino import cli


def test_kamino_bench_writes_speed_next_to_error(tmp_path):
    out = tmp_path / "bench.json"
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "--scenes", "fourbar", "--worlds", "2", "--configs", "sparse-llt", "--no-peers",
                  "--closure-steps", "20", "--graph-steps", "2", "--replays", "1", "--repeats", "1", "--out", str(out)])
    assert done.value.code == 0
    (rec,) = json.loads(out.read_text())["records"]
    assert rec["scene"] == "fourbar" and rec["num_worlds"] == 2 and rec["throughput"] > 0
    # the MJCF four-bar's loop, 20 driven steps: closed to well below the 1e-5 m benchmark target
    assert rec["closure_max_m"] < 1e-5
    assert rec["converged_fraction"] == 1.0 and rec["iterations_max"] < 100
