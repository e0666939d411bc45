"""The throughput benchmark's loads and batch statistics (``kamino.bench.loads``), on Warp's CPU device with a few
worlds: the ``rl`` load's random starts are loop-closed, different per world and set down on the ground; its control
draws stay in their range, hold for one control period and replay after a reset; and the statistics folded on the
device during the steps equal the same figures read back on the host after every step."""

import argparse

import numpy as np
import pytest

import kamino
from kamino.bench import loads

wp = pytest.importorskip("warp")

#: the forward-kinematics tolerance (kamino.forward_kinematics, 1e-6 per constraint row) in float32 poses: an
#: anchor distance combines three rows and the float32 rounding of poses of order 1 m (6e-8 each)
FK_CLOSURE = 5e-6


@pytest.fixture(scope="module")
def throughput():
    from kamino.bench import throughput

    return throughput


def _args(**kw) -> argparse.Namespace:
    return argparse.Namespace(**{**dict(graph_steps=4, warmup=1, replays=3, repeats=1, no_progress=True), **kw})


def test_rl_starts_are_closed_distinct_and_on_the_ground(throughput):
    """dr_legs (a floating robot with loops in its legs): three worlds, three configurations; each closes every loop
    to the FK tolerance, has its actuated coordinates within the drawn band, and rests its lowest support point on
    the ground (z = 0)."""
    from kamino.envs.geometry import support_points

    base = kamino.models.dr_legs()
    model = kamino.replicate(base, 3)
    q = loads.random_configurations(base, model, loads.RL_FRACTION, seed=1).reshape(3, base.num_bodies, 7)
    assert np.min([np.max(np.abs(q[i] - q[j])) for i in range(3) for j in range(i)]) > 1e-2  # worlds differ
    for w in range(3):
        assert throughput.closure_distance(base, q[w]) <= FK_CLOSURE
    pts, bodies, radii = support_points(base)
    from kamino.hostmath import quat_to_matrix as host_quat_to_matrix

    for w in range(3):
        z = [(q[w, b, :3] + host_quat_to_matrix(q[w, b, 3:].astype(float)) @ p)[2] - r
             for p, b, r in zip(pts, bodies, radii, strict=True)]
        assert abs(min(z)) <= 1e-5  # float32 poses of a robot under 1 m
    lo, hi, effort = loads.actuator_ranges(base)
    assert not effort.any() and np.all(lo < hi)
    q_act = np.stack([kamino.dof_state(base, kamino.init_state(base, np.float32).replace(body_q=q[w]))[0]
                      [base.actuator_dof] for w in range(3)])
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * loads.RL_FRACTION
    assert np.all(np.abs(q_act - centre) <= half + 1e-4)  # the FK tolerance on a coordinate


def test_rl_draws_hold_a_period_stay_in_range_and_replay(throughput):
    """The four-bar's motor under the ``rl`` load: per world a torque in ``[-2, 2] N m`` that holds for a control
    period (8 steps of 2.5 ms at 50 Hz), changes between periods, differs between worlds, and repeats after a
    reset."""
    from kamino.warp_backend import backend as wb

    st, state, control = throughput.warp_stepper("fourbar", "default", 3, load="rl", seed=3)
    dofs = st.wm.model.actuator_dof

    def efforts(n):
        out = []
        for _ in range(n):
            st.run(1)
            out.append(st.work.effort.numpy()[dofs].copy())
        return np.array(out)

    first = efforts(17)
    period = round(1.0 / (loads.RL_RATE * throughput.DT))
    assert period == 8
    assert np.all(np.abs(first) <= loads.MOTOR_AMPLITUDE)
    assert np.all(first[:period] == first[0]) and np.all(first[period:2 * period] == first[period])
    assert np.all(first[period] != first[0]) and len(set(first[0].tolist())) == 3
    wb.load_state(st, state, control)
    assert np.array_equal(efforts(17), first)


@pytest.mark.parametrize("load", loads.LOADS)
def test_batch_stats_equal_the_host_readings(throughput, load):
    """The device-folded statistics of the timed blocks (``BatchStats`` in ``bench_warp``'s record) against the same
    figures read back after every step on the host: iterations mean, max and 99th percentile, the converged share,
    the failed worlds, and the closure (``closure_distance`` in float64 of the float32 poses: to float32 rounding)."""
    from kamino.warp_backend import backend as wb

    args = _args()
    rec = throughput.bench_warp("fourbar", "default", 3, args, load)
    assert rec["batch_steps"] == args.replays * args.graph_steps and rec["batch_world_steps"] == 3 * rec["batch_steps"]
    st, state, control = throughput.warp_stepper("fourbar", "default", 3, load=load)
    wb.load_state(st, state, control)
    st.run(args.warmup * args.graph_steps)
    iters, conv, failed, closure = [], [], [], 0.0
    for _ in range(rec["batch_steps"]):
        st.run(1)
        iters.append(st.work.iters.numpy().copy())
        conv.append(st.work.converged.numpy().copy())
        failed.append(st.work.failed.numpy().copy())
        closure = max(closure, throughput.closure_distance(st.wm.model, st.work.q.numpy().reshape(-1, 7)))
    iters = np.array(iters)
    assert rec["iterations_mean"] == pytest.approx(iters.mean(), rel=1e-12)
    assert rec["iterations_max"] == iters.max()
    assert rec["iterations_p99"] == int(np.sort(iters.ravel())[int(np.ceil(0.99 * iters.size)) - 1])
    assert rec["converged_share"] == pytest.approx(np.mean((np.array(conv) != 0) & (np.array(failed) == 0)))
    assert rec["failed_worlds"] == int(np.count_nonzero(np.array(failed).any(axis=0)))
    # the device computes the anchors in float32 from poses of order 1 m: a few ulp (6e-8 m) each
    assert rec["closure_batch_max_m"] == pytest.approx(closure, abs=3e-7)
    assert 0 < rec["closure_batch_max_m"] <= 1e-4  # the four-bar's loop holds under either load
