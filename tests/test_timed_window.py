"""The throughput benchmark's timing rule (``kamino.bench.timed_window``): every trial resets the simulation, runs the
warm-up blocks untimed and times ``--replays`` blocks, so each figure covers steps
``[warmup * graph_steps, (warmup + replays) * graph_steps)`` of the same driven motion whatever ``--repeats`` is, for
kamino Warp (``kamino.bench.throughput``) and the peers (``kamino.bench.peers``). Here on Warp's CPU device with a few
worlds and steps; the MuJoCo Warp and Newton tests skip where those peers are not installed."""

import argparse

import numpy as np
import pytest

from kamino.bench import scene_path, timed_window

wp = pytest.importorskip("warp")


@pytest.fixture(scope="module")
def throughput():
    from kamino.bench import throughput

    return throughput


@pytest.fixture(scope="module")
def peers():
    from kamino.bench import peers

    return peers


def _args(**kw) -> argparse.Namespace:
    return argparse.Namespace(**{**dict(graph_steps=3, warmup=2, replays=2, repeats=2), **kw})


def test_every_trial_times_the_same_steps():
    """A stand-in simulation (a step counter): each trial's clock starts at step warmup * graph_steps after a reset,
    and the record names that window in steps and simulated seconds."""
    sim = {"step": 0, "starts": []}

    def reset():
        sim["step"] = 0

    def block():
        sim["step"] += 4

    def sync():
        sim["starts"].append(sim["step"])  # the first sync of a trial is just before its clock starts

    rec = timed_window.time_window(reset, block, sync, graph_steps=4, warmup=3, replays=5, repeats=3, dt=0.0025)
    assert sim["starts"] == [12, 32] * 3 and sim["step"] == 32
    assert rec["window_steps"] == [12, 32] and rec["window_s"] == pytest.approx([0.03, 0.08])
    assert len(rec["trials_s"]) == 3 and rec["replays_per_trial"] == 5 and rec["warmup_blocks"] == 3
    assert rec["step_time_s"] == pytest.approx(sorted(rec["trials_s"])[1] / 20)


def _state(st) -> dict:
    from kamino.warp_backend import backend as wb

    return {name: arr.numpy().copy() for name, (arr, _, _) in wb.state_fields(st).items()}


def _assert_same(a: dict, b: dict) -> None:
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_warp_reset_makes_trials_bit_identical(throughput):
    """kamino Warp (the four-bar, 2 worlds, the default configuration): after the reset (``load_state`` of the
    initial state into the buffers the steps run on) a trial ends in the same state, bit for bit (poses, twists,
    time, reactions, contacts, PADMM counters and penalty), as the trial before it and as a freshly built stepper run
    for as many steps: nothing of a trial reaches the next."""
    args = _args()
    with wp.ScopedDevice("cpu"):
        st, state, control = throughput.warp_stepper("fourbar", "default", 2)
        ends = []
        rec = throughput.time_warp(st, state, control, args, after_trial=lambda i: ends.append(_state(st)))
        assert rec["window_steps"] == [6, 12] and len(ends) == 2
        _assert_same(ends[0], ends[1])
        fresh, _, _ = throughput.warp_stepper("fourbar", "default", 2)
        fresh.run(12)
        _assert_same(ends[0], _state(fresh))
        assert float(ends[0]["time"][0]) == pytest.approx(12 * throughput.DT)


def test_warp_window_does_not_depend_on_repeats_or_replays(throughput):
    """``--repeats 1`` and ``--repeats 3`` time the same window and end in the same state; ``--replays 2`` and
    ``--replays 3`` time windows that start at the same step (the records' ``window_steps``/``window_s``)."""
    with wp.ScopedDevice("cpu"):
        st, state, control = throughput.warp_stepper("fourbar", "default", 2)
        one = throughput.time_warp(st, state, control, _args(repeats=1))
        end_one = _state(st)
        three = throughput.time_warp(st, state, control, _args(repeats=3))
        _assert_same(end_one, _state(st))
        assert one["window_steps"] == three["window_steps"] == [6, 12]
        assert one["window_s"] == three["window_s"]
        assert len(one["trials_s"]) == 1 and len(three["trials_s"]) == 3
        recs = [throughput.bench_warp("fourbar", "default", 2, _args(replays=r, repeats=1)) for r in (2, 3)]
    assert [r["window_steps"] for r in recs] == [[6, 12], [6, 15]]
    assert recs[0]["window_s"][0] == recs[1]["window_s"][0] == pytest.approx(6 * throughput.DT)
    assert all(r["throughput"] > 0 and r["replays_per_trial"] == r["window_steps"][1] // 3 - 2 for r in recs)


def test_peer_reset_restores_what_a_trial_changed(peers):
    """The peers' reset (``_snapshot`` / ``_restore``, ``kamino.bench.peers``) on a stand-in Warp simulation: a state
    array and a step counter advanced by a kernel. Every trial ends in the same state, after the window's last step,
    and the record carries the window (no MuJoCo Warp or Newton needed)."""

    @wp.kernel
    def advance(x: wp.array(dtype=wp.float32), counter: wp.array(dtype=wp.int32)):
        i = wp.tid()
        x[i] = x[i] * 0.5 + wp.float32(counter[0])

    @wp.kernel
    def tick(counter: wp.array(dtype=wp.int32)):
        counter[0] = counter[0] + 1

    dev = wp.get_device("cpu")
    sim = argparse.Namespace(x=wp.array(np.arange(4, dtype=np.float32), device=dev),
                             counter=wp.zeros(1, dtype=wp.int32, device=dev))
    initial = peers._snapshot(sim)
    assert len(initial) == 2

    def step():
        wp.launch(advance, dim=4, inputs=[sim.x, sim.counter], device=dev)
        wp.launch(tick, dim=1, inputs=[sim.counter], device=dev)

    step()  # advanced before the timing, as the peers' compile steps do: the reset undoes it
    ends = []
    rec = peers._time_steps(step, lambda: peers._restore(initial), dev, graph_steps=3, warmup=2, replays=2, repeats=3,
                            use_graph=False, after_trial=lambda i: ends.append((sim.x.numpy().copy(),
                                                                                int(sim.counter.numpy()[0]))))
    assert rec["timing"] == "python_loop" and rec["window_steps"] == [6, 12] and len(rec["trials_s"]) == 3
    assert rec["window_s"] == pytest.approx([6 * peers.DT, 12 * peers.DT])
    assert all(c == 12 for _, c in ends)
    for x, _ in ends[1:]:
        np.testing.assert_array_equal(x, ends[0][0])
    expected = np.arange(4, dtype=np.float32)
    for k in range(12):
        expected = expected * np.float32(0.5) + np.float32(k)
    np.testing.assert_array_equal(ends[0][0], expected)


def test_mujoco_warp_trials_cover_the_same_window(peers):
    """MuJoCo Warp (the four-bar, 2 worlds): its ``Data`` copied back before every trial, so that trials end in the
    same ``qpos``/``qvel``/``qacc_warmstart``/``time``, bit for bit, and ``--repeats`` does not move the window."""
    pytest.importorskip("mujoco_warp", reason="MuJoCo Warp (the peer) is not installed")
    scene = str(scene_path("fourbar"))
    dev = wp.get_device("cpu")
    with wp.ScopedDevice(dev):
        _, m, d, _, _ = peers._mjw_build(scene, 2, dev)
        initial = peers._snapshot(d)
        step = peers._mjw_stepper(m, d, 2)
        step()
        ends = []

        def end(_):
            ends.append([getattr(d, f).numpy().copy() for f in ("qpos", "qvel", "qacc_warmstart", "time")])

        recs = [peers._time_steps(step, lambda: peers._restore(initial), dev, graph_steps=3, warmup=2, replays=2,
                                  repeats=r, use_graph=False, after_trial=end) for r in (1, 2)]
    assert [r["window_steps"] for r in recs] == [[6, 12], [6, 12]]
    assert len(ends) == 3
    for other in ends[1:]:
        for a, b in zip(ends[0], other, strict=True):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(ends[0][3], 12 * peers.DT, rtol=1e-6)


def test_solver_kamino_trials_cover_the_same_window(peers):
    """Newton's SolverKamino (the four-bar, 2 worlds, DVI): ``_newton_reset`` before every trial, so that trials end
    in the same body poses and ``--repeats`` does not move the window."""
    pytest.importorskip("newton", reason="Newton (the peer) is not installed")
    scene = str(scene_path("fourbar"))
    dev = wp.get_device("cpu")
    result = peers._new_result("newton_solver_kamino", "dvi", scene, 2)
    with wp.ScopedDevice(dev):
        built = peers._newton_build(scene, 2, dev, "mjcf")
        sim = peers._newton_sim(built, "dvi")
        reset = peers._newton_reset(sim, result)
        step = peers._newton_stepper(built, sim)
        step()
        step()
        ends = []
        recs = [peers._time_steps(step, reset, dev, graph_steps=2, warmup=2, replays=2, repeats=r, use_graph=False,
                                  after_trial=lambda _: ends.append(sim.states[0].body_q.numpy().copy()))
                for r in (1, 2)]
    assert [r["window_steps"] for r in recs] == [[4, 8], [4, 8]]
    assert int(sim.counter.numpy()[0]) == 8
    for other in ends[1:]:
        np.testing.assert_array_equal(other, ends[0])
