"""``kamino.bench.ppo_collect`` end to end on Warp's CPU device: the four-bar task through brax's wrappers, 2
environments x 3 env steps, at a zero action and at full random actions."""

import json

import pytest


@pytest.fixture(scope="module")
def ppo_collect():
    pytest.importorskip("warp")
    pytest.importorskip("brax")
    from kamino.bench import ppo_collect

    return ppo_collect


@pytest.mark.slow  # 31-38 s of CI (its four-bar steps compile twice); GPU benchmarks run the module itself
def test_records_the_solver_in_the_collection_loop(ppo_collect, tmp_path):
    """Both runs append one record each. At a zero action the four-bar rests at its reset and its solves need
    few iterations; random actions drive the crank and cost more. Every solve converges. At rest the loop stays
    closed to the 1e-5 m the solver holds at its defaults; random PD targets whip the crank, and there the bound is
    1e-4 m (dr_legs under random actions ends at 3-5e-5 m: docs/envs.md, "The solver in PPO's regime")."""
    out = tmp_path / "collect.jsonl"
    common = ["fourbar_track", "--num-envs", "2", "--unroll", "3", "--out", str(out)]
    assert ppo_collect.main([*common, "--action-scale", "0"]) == 0
    assert ppo_collect.main([*common, "--set", "tolerance=0.001"]) == 0
    still, moving = (json.loads(line) for line in out.read_text().splitlines())
    for rec in (still, moving):
        it = rec["iterations"]
        assert rec["num_envs"] == 2 and rec["unroll"] == 3 and rec["decimation"] == 5
        assert 0 <= it["mean"] <= it["max"] <= 200 and it["p50"] <= it["p99"] <= it["max"]
        assert rec["unconverged_fraction"] == 0.0
        assert rec["collect_env_steps_per_s"] > 0
    assert still["closure_max_m"] < 1e-5 and moving["closure_max_m"] < 1e-4
    assert moving["solver_overrides"] == {"tolerance": 0.001} and moving["effort_limits"]
    assert moving["iterations"]["mean"] > still["iterations"]["mean"]


def test_bad_arguments_are_named(ppo_collect):
    with pytest.raises(SystemExit):
        ppo_collect.parse_args(["--set", "tolerance"])
    with pytest.raises(SystemExit):
        ppo_collect.parse_args(["--action-scale", "2"])


def test_an_unknown_policy_is_named(ppo_collect):
    """``--policy`` takes a shipped policy's name or an existing run: anything else fails before an environment is
    built, naming what it got and the shipped policies."""
    with pytest.raises(FileNotFoundError, match=r"no_such_policy.*dr_legs_walk"):
        ppo_collect.main(["--policy", "no_such_policy"])
