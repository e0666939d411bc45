"""The 32-threads-per-world schedule (``Stepper(padmm="warp")``, solver_lanes.py: the sparse factorisation or the
Conjugate Residual solve, the PADMM iterations and post-stabilisation's solve) against the one-thread-per-world
kernels, on Warp's CPU device (cooperative CPU blocks)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp as wp

import kamino
from kamino.warp_backend import backend as wb
from kamino.warp_backend import linear_solve, linear_solve_pattern, solver_lanes
from kamino.warp_backend.pipeline import Stepper
from kamino.warp_backend.workspace import saturated_rows
from tests.helpers import stepper_delassus


def _run(model, cfg, padmm, steps, dtype=np.float64, device="cpu"):
    st = Stepper(model, cfg, dtype, device, padmm=padmm)
    wb.load_state(st, kamino.init_state(model, dtype=dtype), None)
    iters, rho = [], []
    for _ in range(steps):
        st.run(1)
        iters.append(st.work.iters.numpy().copy())
        rho.append(st.work.rho_u.numpy().copy())
    q = st.work.q.numpy().view(dtype).reshape(-1, 7)
    return q, np.array(iters), np.array(rho), st


@pytest.mark.parametrize("layout", ["shared", "device", "inverse"],
                         ids=["factor-in-shared-memory", "factor-in-device-memory", "solve-with-the-inverse"])
def test_warp_schedule_solves_what_the_thread_kernel_solves(layout, monkeypatch):
    # Both places the factorisation works in: shared memory (robot-sized worlds) and device memory (worlds too
    # large to stage, solver_lanes.STAGE_MAX_ENTRIES); and the iterations' solve with L_f^-1 (inverse_pattern),
    # forced on here (the chain of loops' inverse has 2.1 times its factor's entries, above INVERSE_MAX_FILL).
    staged = layout != "device"
    if not staged:
        monkeypatch.setattr(solver_lanes, "STAGE_MAX_ENTRIES", 0)
    monkeypatch.setattr(linear_solve, "INVERSE_MAX_FILL", 100.0 if layout == "inverse" else 0.0)
    # A loop (four-bar, driven into its hinge limits), a contact world (two stacked boxes: cone projection on
    # contact triples, De Saxcé) and a coupling-free chain of loops in one heterogeneous model, at the defaults
    # (adaptive penalty: tail refactorisations inside the iterations; post-stabilisation: the 32-thread solve of
    # the fixed rows) but float64 at a tight tolerance. The two schedules compute the same sums in another order,
    # so they agree to rounding amplified by the iterations (1e-10 m over 60 steps), and take the same iterations
    # and penalties on every step.
    model = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2), kamino.models.chain_of_loops(3)])
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-8)
    q_t, it_t, rho_t, _ = _run(model, cfg, "thread", 60)
    q_w, it_w, rho_w, st = _run(model, cfg, "warp", 60)
    assert st.sparse_factor and st.padmm == "warp"
    assert (st.wk.E > 0) == staged
    assert st.wk.inverse == (layout == "inverse")
    np.testing.assert_allclose(q_w, q_t, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(it_w, it_t)
    np.testing.assert_allclose(rho_w, rho_t, rtol=1e-9)
    assert len(np.unique(rho_t)) > 1  # the penalty did change: the tail was refactorised inside the iterations
    assert it_w.max() < cfg.max_iterations  # converged, not capped
    assert bool(np.all(st.work.converged.numpy()))


def _cr_comparison(budget: int):
    """The scenes of the LLT comparison above on CR with ``budget`` iterations per solve, on both schedules."""
    model = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2), kamino.models.chain_of_loops(3)])
    # one PADMM solve per step (no curvature refinement): its restart adds a second stopping test per step, whose
    # iteration the schedules' rounding moves as often as the first's, beyond the 1 % that the counts are held to
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-8,
                              stabilisation=kamino.Stabilisation(curvature_refinement=False),
                              warp=kamino.WarpSettings(linear_solver="cr", cr_iterations=budget))
    q_t, it_t, rho_t, _ = _run(model, cfg, "thread", 60)
    q_w, it_w, rho_w, st = _run(model, cfg, "warp", 60)
    assert st.padmm == "warp" and st.linear_solver == "cr" and st.wk.cr and not st.sparse_factor
    assert len(np.unique(rho_t)) > 1  # the penalty did change inside the iterations
    assert bool(np.all(st.work.converged.numpy())) and not bool(np.any(st.work.failed.numpy()))
    return cfg, (q_t, it_t, rho_t), (q_w, it_w, rho_w)


def test_warp_schedule_with_cr_solves_what_the_thread_kernel_solves():
    # Conjugate Residual with 32 threads per world against one thread per world, on the scenes of the LLT comparison
    # above (loops driven into their limits, contacts, float64 at a tight tolerance, the adaptive penalty changing
    # inside the iterations, post-stabilisation with the fixed rows' own factor and the 32-thread solve), at a CR
    # budget of 30 iterations (for worlds of 24-66 rows). The operator's sums are the thread kernel's, in its
    # order (cr_pattern's lists of row blocks by body); the dot products are block sums, in another
    # order. So the two agree to rounding amplified by the iterations (1e-10 m over 60 steps, as the LLT's), with the
    # same iterations and penalties on every step.
    _, (q_t, it_t, rho_t), (q_w, it_w, rho_w) = _cr_comparison(30)
    np.testing.assert_allclose(q_w, q_t, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(it_w, it_t)
    np.testing.assert_allclose(rho_w, rho_t, rtol=1e-9)


def test_warp_schedule_with_inexact_cr_solves_converges_like_the_thread_kernel():
    # At 4 CR iterations per solve the solves are inexact: their exit residual, folded into the dual residual,
    # decides when a world converges (the chain of loops takes ~80 PADMM iterations a step instead of 2). PADMM
    # then amplifies the rounding of the dot products' other order into a different stopping iteration now and then,
    # earlier or later (measured: by 1-4 iterations, on 7 of the four-bar's 60 steps and on 25 of the chain's); both
    # stop within the tolerance 1e-8 m/s, which over 60 steps of 1/240 s moves a pose by at most
    # 60 * 1e-8 / 240 = 2.5e-9 m (measured 2.6e-10 m). The rounding, and so which steps move, depends on the CPU that
    # Warp compiles for; what does not is that the moves cancel: no world takes a whole PADMM iteration per step
    # more or fewer on one schedule than on the other (measured: 0.17 per step at most).
    cfg, (q_t, it_t, rho_t), (q_w, it_w, rho_w) = _cr_comparison(4)
    np.testing.assert_allclose(q_w, q_t, rtol=0, atol=60 * cfg.tolerance * cfg.dt)
    assert it_t[:, 2].mean() > 20  # the inexact solves did cost PADMM iterations
    np.testing.assert_array_less(np.abs(it_w.mean(axis=0) - it_t.mean(axis=0)), 1.0)
    np.testing.assert_allclose(rho_w, rho_t, rtol=1e-9)


def test_warp_schedule_with_cr_on_rows_of_four_blocks():
    # A coupling of two joints spans four bodies' blocks (blocks_per_row = 4): cr_pattern lists all four slots of
    # every row. Two position-driven hinges coupled 2:1, next to a four-bar; as exact as the comparison above.
    from kamino.models.shapes import box_inertia

    b = kamino.ModelBuilder()
    la = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(0, 0, 0.5), name="a")
    lb = b.add_body(1.0, box_inertia(1.0, (0.1, 0.1, 1.0)), pos=(1, 0, 0.5), name="b")
    ja = b.add_joint_at(kamino.JointType.REVOLUTE, -1, la, anchor=(0, 0, 1), axis=(0, 1, 0), name="ja")
    jb = b.add_joint_at(kamino.JointType.REVOLUTE, -1, lb, anchor=(1, 0, 1), axis=(0, 1, 0), name="jb",
                        actuation=kamino.Actuation("position", kp=10.0, kd=1.0))
    b.add_coupling(ja, jb, (0.0, 2.0), name="m")
    model = kamino.concat([b.finalize(), kamino.models.fourbar()])
    cfg = kamino.SolverConfig(dt=1.0 / 240.0, tolerance=1e-8, warp=kamino.WarpSettings(linear_solver="cr"))
    q_t, it_t, _, _ = _run(model, cfg, "thread", 30)
    q_w, it_w, _, st = _run(model, cfg, "warp", 30)
    assert st.padmm == "warp" and st.wm.blocks_per_row == 4
    np.testing.assert_allclose(q_w, q_t, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(it_w, it_t)
    assert bool(np.all(st.work.converged.numpy()))


def test_warp_schedule_on_a_robot_at_the_float32_defaults():
    # dr_legs (31 bodies, 204 fixed rows, feet contacts) at SolverConfig(dt) in float32, where post-stabilisation
    # solves with PADMM's own L_f: the float32 rounding of the two summation orders may move an iteration count
    # by one, so the check is the physics: poses within 1e-5 m over 20 steps (the loops close to ~2e-6 m, and the
    # float32 rounding of the factor, amplified by PADMM's tolerance 1e-3 m/s over a few steps of 2.5 ms, stays well
    # below that) and the same mean iterations to 5 %.
    model = kamino.replicate(kamino.models.dr_legs(), 2)
    cfg = kamino.SolverConfig(dt=0.0025)
    q_t, it_t, _, _ = _run(model, cfg, "thread", 20, np.float32)
    q_w, it_w, _, st = _run(model, cfg, "warp", 20, np.float32)
    assert st.post_shares_factor
    np.testing.assert_allclose(q_w[:, :3], q_t[:, :3], rtol=0, atol=1e-5)
    assert abs(it_w.mean() - it_t.mean()) <= 0.05 * it_t.mean()
    assert bool(np.all(st.work.converged.numpy())) and not bool(np.any(st.work.failed.numpy()))


def test_warp_schedule_with_cr_on_a_robot_in_float32():
    # dr_legs (204 fixed rows, 31 bodies, feet contacts) on CR at its default budget in float32: the dot products'
    # float32 rounding in another order may move an iteration count by one, so the check is the physics, with the
    # float32 robot test's reasoning above: poses within 1e-5 m over 20 steps (measured 1.2e-7 m) and the same mean
    # iterations to 5 % (measured equal).
    model = kamino.replicate(kamino.models.dr_legs(), 2)
    cfg = kamino.SolverConfig(dt=0.0025, warp=kamino.WarpSettings(linear_solver="cr"))
    q_t, it_t, _, _ = _run(model, cfg, "thread", 20, np.float32)
    q_w, it_w, _, st = _run(model, cfg, "warp", 20, np.float32)
    assert st.padmm == "warp" and st.linear_solver == "cr"
    np.testing.assert_allclose(q_w[:, :3], q_t[:, :3], rtol=0, atol=1e-5)
    assert abs(it_w.mean() - it_t.mean()) <= 0.05 * it_t.mean()
    assert bool(np.all(st.work.converged.numpy())) and not bool(np.any(st.work.failed.numpy()))


def test_warp_schedule_rejects_what_it_cannot_solve():
    # the 32-thread schedule solves with the block-sparse Jacobian (the sparse LLT or CR), not the dense one
    model = kamino.models.fourbar()
    with pytest.raises(ValueError, match="block-sparse Jacobian"):
        Stepper(model, kamino.SolverConfig(warp=kamino.WarpSettings(jacobian="dense")), np.float32, "cpu", padmm="warp")
    with pytest.raises(ValueError, match="block-sparse Jacobian"):
        Stepper(model, kamino.SolverConfig(warp=kamino.WarpSettings(jacobian="dense", linear_solver="cr")), np.float32,
                "cpu", padmm="warp")
    with pytest.raises(ValueError, match="padmm must be"):
        Stepper(model, kamino.SolverConfig(), np.float32, "cpu", padmm="block")


def test_the_automatic_schedule_follows_the_measured_crossover():
    # pipeline.resolve_padmm: the 32-thread schedule on CUDA where it measures faster (up to 16384 worlds, or worlds
    # of 200 rows or more), with the sparse LLT or CR, one thread per world elsewhere and on every CPU run; under
    # reduction="schur" the 32-thread schedule everywhere (the only one that reduces).
    from types import SimpleNamespace

    from kamino.warp_backend.pipeline import resolve_padmm

    gpu, cpu = SimpleNamespace(is_cuda=True), SimpleNamespace(is_cuda=False)
    cfg = kamino.SolverConfig()
    assert resolve_padmm(cfg, gpu, 4096, 117, None) == "warp"  # four-bar at 4096 worlds
    assert resolve_padmm(cfg, gpu, 16384, 117, None) == "warp"  # four-bar at 16384 worlds
    assert resolve_padmm(cfg, gpu, 65536, 117, None) == "thread"  # four-bar at 65536 worlds
    assert resolve_padmm(cfg, gpu, 16384, 576, None) == "warp"  # ladder32 at 16384 worlds
    assert resolve_padmm(cfg, cpu, 64, 240, None) == "thread"
    dense = kamino.SolverConfig(warp=kamino.WarpSettings(jacobian="dense"))
    assert resolve_padmm(dense, gpu, 64, 240, None) == "thread"
    cr = kamino.SolverConfig(warp=kamino.WarpSettings(linear_solver="cr"))
    assert resolve_padmm(cr, gpu, 64, 240, None) == "warp"
    assert resolve_padmm(cr, gpu, 1, 365, None) == "warp"  # one eight-legged Jansen walker
    assert resolve_padmm(cr, gpu, 65536, 117, None) == "thread"
    assert resolve_padmm(cr, gpu, 65536, 365, None) == "warp"
    assert resolve_padmm(cr, cpu, 64, 240, None) == "thread"
    assert resolve_padmm(cfg, cpu, 64, 240, "warp") == "warp"  # an explicit choice is kept
    schur = kamino.SolverConfig(reduction="schur")  # the schedule that reduces, on every device
    assert resolve_padmm(schur, cpu, 64, 240, None) == "warp"
    assert resolve_padmm(schur, gpu, 65536, 117, None) == "warp"


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[
    pytest.mark.gpu, pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device for Warp")])])
def test_warp_schedule_filters_the_warm_start_as_the_thread_kernel(device, monkeypatch):
    # The warm-start filter (docs/conventions.md "Warm start") with the world's 32 threads (the fixed rows' factor by
    # solver_lanes.factor_kernel, the solve-and-clip by warm_start_filter_kernel) against the one-thread path
    # (linear_solve.factor_fixed, solver.warm_start_filter_kernel), on the same assembled P D_ff P + s I and warm
    # start: two dr_legs in float64 after two steps (loops, limits, feet contacts), with hubs (bodies on more than 24
    # fixed rows: 2 per world, their 6 unknowns each ordered after the fixed rows). The two factorise in another
    # order; with the shift s = 1e-6 the solve amplifies rounding by up to 1/s, so the filtered warm starts agree to
    # 1e-16 / s ~ 1e-10 (measured 6.7e-16). World 1's warm start holds a NaN: its filter is not finite, so it keeps
    # its warm start, and world 0 is filtered all the same. On the GPU (the gpu tier) the same check runs the CUDA
    # kernels.
    monkeypatch.setattr(linear_solve_pattern, "HUB_MIN_ROWS", 24)
    model = kamino.replicate(kamino.models.dr_legs(), 2)
    _, _, _, st = _run(model, kamino.SolverConfig(dt=0.0025), "warp", 2, device=device)
    assert st.filter_lanes and st.filt.hubs == 4 and st.filt.max_tail == 0
    thread = linear_solve.build(model, np.float64, st.device, st.wm.arrays.row_fixed.numpy(), per_world=False,
                                hub_min_rows=st.wm.hub_min_rows, hub_row0=st.wm.arrays.row_maxdim.numpy())
    w = st.work
    nf = int(st.wm.arrays.row_fixed.numpy()[0])
    start = int(st.wm.arrays.grp_maxdim.numpy()[0])  # world 1's first row (rows contiguous per world)
    x0 = np.random.default_rng(0).standard_normal(w.x_p.shape[0])
    x0[start + 7] = np.nan
    out = {}
    for lanes, filt in ((True, st.filt), (False, thread)):
        for a in (w.x, w.x_p, w.y_p, w.y_hat):
            a.assign(x0)
        st._filter_warm_start(filt, lanes)
        out[lanes] = [a.numpy().copy() for a in (w.x, w.x_p, w.y_p, w.y_hat)]
    fixed = np.r_[0:nf, start:start + nf]
    for x, x_p, *copies in out.values():  # y_p and y_hat equal to the filtered x_p, x too on the fixed rows
        for got in copies:
            np.testing.assert_array_equal(got, x_p)
        np.testing.assert_array_equal(x[fixed], x_p[fixed])
    lane, ref = out[True][1], out[False][1]
    np.testing.assert_allclose(lane[:nf], ref[:nf], rtol=0, atol=1e-10)
    assert np.abs(lane[:nf] - x0[:nf]).max() > 0.1  # the random warm start has parts along the null directions
    np.testing.assert_array_equal(lane[nf:start], x0[nf:start])  # world 0's other rows: untouched
    np.testing.assert_array_equal(lane[start:], x0[start:])  # world 1: not finite, kept



def _world_problem(st, f0, v0):
    """World 0's dual problem after a step, as ``kamino.jax_ref.solver.solve`` takes it, from the stepper's rows
    (float64): ``D = J M^-1 J^T + R``, ``v_f = v~_f / P``, the box rows' bounds, the contacts' friction, the warm start
    (``padmm_init``'s ``impulse_scale f0`` and ``v0``, as PADMM read them: ``Work.f0`` and ``v0`` change after it),
    and ``n_fixed``."""
    from kamino.warp_backend.workspace import ROW_SRC_MASK

    w, m, cfg = st.work, st.wm.arrays, st.cfg
    n, nbox = int(w.n_rows.numpy()[0]), int(w.n_box.numpy()[0])
    P, vt, lo_s, hi_s = (a.numpy().astype(np.float64)[:n] for a in (w.P, w.vt, w.lo_s, w.hi_s))
    f0, v0 = np.asarray(f0, np.float64)[:n], np.asarray(v0, np.float64)[:n]
    D = stepper_delassus(st, n)
    lo = np.where(np.isfinite(lo_s), lo_s * P, lo_s)[:nbox]
    hi = np.where(np.isfinite(hi_s), hi_s * P, hi_s)[:nbox]
    mu = w.ct_mu.numpy().astype(np.float64)[w.row_info.numpy()[nbox:n:3] & ROW_SRC_MASK]
    scale_ws = cfg.warmstart_scale * cfg.dt if cfg.warm_start else 0.0
    args = (D, vt / P, lo, hi, mu, np.ones(n, bool), scale_ws * f0, v0)
    return args, int(m.row_fixed.numpy()[0])


def test_warp_schedule_reduces_as_the_jax_reference():
    # SolverConfig.reduction="schur" (docs/formulation.md §7.11) with 32 threads per world against the JAX reference's
    # _solve_schur on the same dual problem: dr_legs under large PD targets (loops: redundant rows in F, D_FF
    # singular; the effort-limited actuator rows in T, one of them saturated; the feet's contact triples), its second
    # step of 2.5 ms in float64 at tolerance 1e-6, the rows, warm start and penalty read from the stepper (no curvature
    # refinement or post-stabilisation: the step's PADMM alone). Both eliminate with the factor of A + eps I and two
    # refinement steps (the Warp side as x_{k+1} = C^-1 (b + eps x_k), the same vector), filter the warm start, run
    # PADMM's rules on (S, v'_T) and recover lambda_F; they round differently (sparse L_f, per-body products and the
    # explicit inverse of the reduced system against dense Cholesky solves), and the refinement amplifies rounding by
    # up to 1 / eps ~ 1e4 along the loops' null space, so impulses (N s, N m s) and velocities (m/s, rad/s) agree to
    # 1e-9 (measured 8.1e-13 and 5.7e-13), with the same iterations (53).
    from kamino.bench import loads
    from kamino.jax_ref import solver

    model = kamino.models.dr_legs()
    cfg = kamino.SolverConfig(dt=0.0025, tolerance=1e-6, reduction="schur", stabilisation=kamino.Stabilisation(
        curvature_refinement=False, post_stabilisation=0))
    st = Stepper(model, cfg, np.float64, "cpu", padmm="warp")
    assert st.schur and st.padmm == "warp"
    offset, scale, _ = loads.rl_control_map(model)
    target = np.zeros(model.num_dofs)
    target[model.actuator_dof] = offset + scale * np.random.default_rng(1).uniform(-1, 1, model.num_actuators)
    wb.load_state(st, kamino.init_state(model, dtype=np.float64), kamino.Control(position_target=jnp.asarray(target)))
    st.run(1)
    rho0 = float(st.work.rho_u.numpy()[0])
    seen, loop = {}, st._padmm_loop

    def padmm_loop():  # the warm start as PADMM reads it
        seen.setdefault("f0", st.work.f0.numpy().copy())
        seen.setdefault("v0", st.work.v0.numpy().copy())
        loop()

    st._padmm_loop = padmm_loop
    st.run(1)
    args, nf = _world_problem(st, seen["f0"], seen["v0"])
    n = len(args[1])
    ref = jax.jit(lambda *a: solver.solve(*a, cfg, None, rho0, nf))(*args)
    w = st.work
    assert n > nf and saturated_rows(w.row_info.numpy())[:nf].any()  # contacts in T; a saturated actuator row
    assert int(w.iters.numpy()[0]) == int(ref.iterations) and bool(ref.converged)
    np.testing.assert_allclose(w.impulse.numpy()[:n], np.asarray(ref.impulse), rtol=0, atol=1e-9)
    np.testing.assert_allclose(w.velocity.numpy()[:n], np.asarray(ref.velocity), rtol=0, atol=1e-9)
