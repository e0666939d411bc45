"""One Warp "stepper" per (model, config, precision, device): buffers, the launch sequence of a step,
and its CUDA-graph capture.

The sequence follows the backend contract (docs/architecture.md): kinematics -> collision -> dynamics ->
PADMM -> integrate. Every launch is on a ``(num_worlds, max_count)`` grid or one thread per world;
nothing loops over worlds or bodies on the host, and nothing reads back to the host inside a step.
On a CUDA device the PADMM loop is a ``wp.capture_while`` on the device counter of worlds still
iterating, so a step (or a block of steps) is one CUDA graph; on the CPU the same kernel runs all
iterations in one launch.
"""

from __future__ import annotations

import os
import threading

import numpy as np
import warp as wp

from kamino.config import (
    ANGULAR_DAMPING,
    CONTACT_BAUMGARTE,
    CONTACT_DEADBAND,
    CONTACT_MATCH_DISTANCE,
    HEALTH_TURN,
    LIMIT_BAUMGARTE,
    LIMIT_MARGIN,
    LOOP_OPEN_BOUND,
    REPROJECTION_GAP,
    REPROJECTION_PASSES,
    RESTART_TOLERANCE,
    RESTITUTION_THRESHOLD,
    WARM_START_FILTER_SHIFT,
    SolverConfig,
    joint_deadband,
)
from kamino.model import Model
from kamino.tables import DYN_ACTUATOR, health_speed_bound, row_tables, world_reach
from kamino.warp_backend import linear_solve
from kamino.warp_backend import solver_rules as rules
from kamino.warp_backend.contacts import contact_kernels
from kamino.warp_backend.integrate import end_step_kernels
from kamino.warp_backend.linear_solve_pattern import fixed_row_types
from kamino.warp_backend.model_data import WarpModel, warp_model
from kamino.warp_backend.post_stabilisation import post_stabilisation_kernels
from kamino.warp_backend.rows import step_row_kernels
from kamino.warp_backend.solver import LINEAR_CR, LINEAR_DENSE, LINEAR_SPARSE, padmm_iterate_kernel, solver_kernels
from kamino.warp_backend.solver_lanes import (
    LANES,
    SCHUR_ELIMINATE,
    SCHUR_RECOVER,
    SCHUR_RHS,
    factor_kernel,
    iterate_kernel,
    schur_buffers,
    schur_list_cap,
    shared_entries,
    shared_rows,
    warp_kernels,
)
from kamino.warp_backend.workspace import allocate

#: linear_solver="auto" takes the Conjugate Residual path above this many constraint rows per world on a GPU with
#: one thread per world: measured on an H100 at 4096 worlds, LLT is faster up to 240 rows and CR 14x faster at 576.
#: The CPU (one thread per world, a few worlds per core) keeps the sparse LLT at every size: at 4 worlds on 2 cores
#: it is 1.2-1.5x faster than CR on ladder32 (576 rows), olaf, dr_legs and the animatronic (1089 rows), as fast
#: on bdx, and it solves the eight-legged Jansen walker to the tolerance where CR at 9 iterations did not.
AUTO_CR_ROWS = 300
#: threads per block of the one-thread-per-world kernels
PER_WORLD_BLOCK = 32

#: held by whatever drives Warp's stream of a CUDA device from the host (building a stepper and its uploads, an eager
#: step from loading the state to reading the result, a graph capture, freeing a stepper): every stepper of a device
#: works on that one stream, and a capture on it would take in another thread's copies and launches, or fail on
#: them. Steps on one GPU's stream run one after the other anyway.
CUDA_STREAM_LOCK = threading.RLock()


def resolve_linear_solver(cfg: SolverConfig, max_rows: int, padmm: str = "thread", cuda: bool = False) -> str:
    """``"llt"`` or ``"cr"`` for ``cfg`` on worlds of up to ``max_rows`` rows (CR needs the sparse J; under the
    32-thread schedule, ``padmm="warp"``, ``"auto"`` is the sparse factor at every size; ``"auto"`` takes CR only with
    one thread per world on a GPU (``cuda``) above ``AUTO_CR_ROWS`` rows)."""
    choice = cfg.warp.linear_solver
    if choice == "auto":
        large = cuda and padmm != "warp" and max_rows > AUTO_CR_ROWS
        choice = "cr" if (cfg.warp.jacobian == "sparse" and large) else "llt"
    if choice == "cr" and cfg.warp.jacobian == "dense":
        raise ValueError("SolverConfig.warp: linear_solver='cr' works on the block-sparse Jacobian; "
                         "use jacobian='sparse' (or linear_solver='llt' with jacobian='dense')")
    return choice


#: the automatic PADMM schedule (``padmm=None``, :func:`resolve_padmm`), from the H100 measurements at the defaults
#: (benchmarks/README.md, every scene with the peers; the lane kernel against one thread per world, same card):
#: 32 threads per world wins on every scene up to 16384 worlds (at 16384: ladder8 1.56x, bdx 1.38x, the four-bar
#: 1.04x) and on worlds of 200 rows or more at any count (dr_legs, olaf, ladder32, the animatronic); one thread per
#: world wins on small worlds at 65536 (the four-bar 1.40x, bdx 1.54x, ladder8 1.03x), where the thread kernels
#: alone fill the GPU.
WARP_SCHEDULE_MAX_WORLDS = 16384
WARP_SCHEDULE_MIN_ROWS = 200


def resolve_padmm(cfg: SolverConfig, device, num_worlds: int, max_rows: int, padmm: str | None) -> str:
    """The PADMM schedule: ``padmm`` if given, else ``"warp"`` on a CUDA device where the configuration uses the
    block-sparse Jacobian (``jacobian="sparse"``, with the sparse LLT or Conjugate Residual) and the worlds are few
    (:data:`WARP_SCHEDULE_MAX_WORLDS`) or large (:data:`WARP_SCHEDULE_MIN_ROWS`), and on any device under
    ``reduction="schur"`` (the only schedule that reduces; on the CPU its 32 threads run as fibers); else
    ``"thread"``."""
    if padmm is not None:
        if padmm not in ("thread", "warp"):
            raise ValueError(f"padmm must be 'thread' or 'warp' (got {padmm!r})")
        return padmm
    if cfg.reduction == "schur" and cfg.warp.jacobian == "sparse":
        return "warp"
    size_wins = num_worlds <= WARP_SCHEDULE_MAX_WORLDS or max_rows >= WARP_SCHEDULE_MIN_ROWS
    return "warp" if (device.is_cuda and cfg.warp.jacobian == "sparse" and size_wins and max_rows > 0) else "thread"


class Stepper:
    """Device buffers and launches for stepping ``model`` with ``cfg``.

    ``padmm``: ``"thread"`` runs PADMM with one thread per world (``solver.py``, LLT or CR); ``"warp"`` runs the
    sparse factorisation (or Conjugate Residual's operator), the warm-start filter, the PADMM iterations and
    post-stabilisation's solve with 32 threads per world (``solver_lanes.py``; ``jacobian="sparse"``,
    ``linear_solver`` ``"llt"`` or ``"cr"``); ``None`` chooses by device, configuration and size
    (:func:`resolve_padmm`).
    """

    def __init__(self, model: Model, cfg: SolverConfig, np_dtype, device=None, padmm: str | None = None,
                 wm: WarpModel | None = None):
        self.device = wp.get_device(device)
        self.cfg = cfg
        self.np_dtype = np.dtype(np_dtype)
        #: the model on the device (uploaded here unless given: one per precision and device serves every stepper)
        self.wm = wm = warp_model(model, self.np_dtype, str(self.device)) if wm is None else wm
        #: the step as a JAX FFI call, built on the first traced step (kamino/warp_backend/jit.py)
        self.ffi = None
        padmm = resolve_padmm(cfg, self.device, wm.num_worlds, wm.max_rows, padmm)
        self.linear_solver = resolve_linear_solver(cfg, wm.max_rows, padmm, self.device.is_cuda)
        self.dense = cfg.warp.jacobian == "dense"
        llt = self.linear_solver == "llt"
        #: SolverConfig.reduction = "schur" (docs/formulation.md §7.11): the 32-thread schedule, the sparse factor
        self.schur = cfg.reduction == "schur"
        if self.schur and (padmm != "warp" or not llt or self.dense):
            raise ValueError("SolverConfig.reduction='schur' runs on the Warp backend's 32-thread schedule with the "
                             "sparse factor (padmm='warp', jacobian='sparse', linear_solver='llt'); got "
                             f"padmm={padmm!r}, jacobian={cfg.warp.jacobian!r}, linear_solver={self.linear_solver!r}: "
                             "use those, backend='jax' or reduction='none'")
        if cfg.redundant_limits:
            raise ValueError("SolverConfig.redundant_limits is implemented in the JAX reference only (float64); "
                             "use backend='jax' or leave it off")
        if padmm == "warp" and self.dense:
            raise ValueError("padmm='warp' solves with the block-sparse Jacobian (the sparse LLT or CR): use "
                             f"jacobian='sparse' (got jacobian={cfg.warp.jacobian!r})")
        self.padmm = padmm
        #: the fixed rows' penalty and whether the limit and contact rows' penalty adapts (kamino.jax_ref.solver.solve)
        self.adaptive = cfg.penalty.mode == "adaptive"
        self.rho_free = cfg.penalty.rho_free if self.adaptive else cfg.penalty.rho
        #: the fixed rows' diagonal shifts in PADMM's factor: ``eta + rho_free``, and ``eta + rho`` on a saturated
        #: effort-limited row (``Work.sat``)
        self.padmm_shifts = (cfg.penalty.eta + self.rho_free, cfg.penalty.eta + cfg.penalty.rho)
        #: the LLT solve with block-sparse rows and one thread per world factorises sparsely (linear_solve.py)
        self.sparse_factor = llt and not self.dense
        with wp.ScopedDevice(self.device):
            # under the 32-thread schedule each world's rows are contiguous (its threads read consecutive rows)
            self.work = allocate(wm, cfg.integrator == "euler", self.dense, llt and not self.sparse_factor,
                                 rows_per_world=padmm == "warp", cr=not llt)
            if self.sparse_factor:
                self.sf = linear_solve.build(model, self.np_dtype, self.device, wm.arrays.row_maxdim.numpy(),
                                           per_world=padmm == "warp", hub_min_rows=wm.hub_min_rows,
                                           inverse=padmm == "warp")
                self.spk = linear_solve.sparse_llt_kernels(self.np_dtype)
            self.sp = self.sf.arrays if self.sparse_factor else linear_solve.empty(self.np_dtype, self.device)
            #: post-stabilisation solves with PADMM's sparse factor of the fixed rows when that factor carries the
            #: projection's shifts (SolverConfig.projection_shifts: the adaptive penalty); else with a factor of its own
            #: (not under the reduction: its L_f is the factor of the eliminated rows alone)
            self.post_shares_factor = (self.sparse_factor and cfg.shares_padmm_factor(self.np_dtype)
                                       and not self.schur)
            #: post-stabilisation's own factor (``None`` where it shares PADMM's or does not run) and, under
            #: padmm="warp", the compiled ``solver_lanes.factor_kernel`` that factorises it
            self.post, self.post_factor = None, None
            if cfg.stabilisation.post_stabilisation and not self.post_shares_factor:
                # the fixed rows' own pattern and factor (no tail rows), in the layout and with the update lists of
                # the schedule that factorises it: the world's 32 threads under padmm="warp" (the fan-out triples of
                # solver_lanes.factor_kernel), else one thread per world (linear_solve.factor_fixed's pairs)
                self.post = linear_solve.build(model, self.np_dtype, self.device, wm.arrays.row_fixed.numpy(),
                                             per_world=padmm == "warp", hub_min_rows=wm.hub_min_rows,
                                             hub_row0=wm.arrays.row_maxdim.numpy())
                self.spk = linear_solve.sparse_llt_kernels(self.np_dtype)
            #: post-stabilisation's Gauss-Newton passes (REPROJECTION_PASSES): the fixed rows' factor at the projected
            #: pose, on their own pattern, for one-thread-per-world kernels under either schedule
            self.gn = None
            if cfg.stabilisation.post_stabilisation and REPROJECTION_PASSES and int(wm.max_cts) > 0:
                self.gn = linear_solve.build(model, self.np_dtype, self.device, wm.arrays.row_fixed.numpy(),
                                             per_world=False, fan=False, hub_min_rows=wm.hub_min_rows,
                                             hub_row0=wm.arrays.row_maxdim.numpy())
            #: the warm-start filter's factor of the fixed rows (shift WARM_START_FILTER_SHIFT; docs/conventions.md,
            #: "Warm start"), on the fixed rows' own pattern (no tail rows), in the layout of the schedule that
            #: factorises and applies it: the world's 32 threads under padmm="warp" (``filter_lanes``), else one
            #: thread per world
            self.filt = None
            self.filter_lanes = padmm == "warp"
            if cfg.warm_start and not self.schur and int(wm.arrays.row_fixed.numpy().max(initial=0)) > 0:
                self.filt = linear_solve.build(model, self.np_dtype, self.device, wm.arrays.row_fixed.numpy(),
                                               per_world=self.filter_lanes, hub_min_rows=wm.hub_min_rows,
                                               hub_row0=wm.arrays.row_maxdim.numpy())
                self.spk = linear_solve.sparse_llt_kernels(self.np_dtype)
            #: the reduced problem's buffers (solver_lanes.schur_struct; empty without the reduction)
            self.sch = self._schur_buffers(model) if self.schur else schur_buffers(self.np_dtype, self.device, 0, 0,
                                                                                   0, 0, 0)
            if padmm == "warp":
                wp.config.enable_cpu_blocks = True  # CPU launches run a world's 32 threads as cooperative fibers
                E = shared_entries(self.sf.max_nnz) if self.sparse_factor else 0
                filter_E = shared_entries(self.filt.max_nnz) if self.filt is not None else None
                self.wk = warp_kernels(self.np_dtype, shared_rows(wm.max_slots), E, cr=not llt, filter_E=filter_E,
                                       inverse=self.sparse_factor and self.sf.inv_total > 0 and not self.schur,
                                       schur=self.schur)
                # post-stabilisation's own factor: factor_kernel staged for its pattern, PADMM's or the warm-start
                # filter's compiled kernel where the staging size (and no inversion) is theirs
                if self.post is not None:
                    post_E = shared_entries(self.post.max_nnz)
                    if self.wk.factor is not None and not self.wk.inverse and post_E == self.wk.E:
                        self.post_factor = self.wk.factor
                    elif self.wk.filter_factor is not None and post_E == filter_E:
                        self.post_factor = self.wk.filter_factor
                    else:
                        self.post_factor = factor_kernel(self.np_dtype, post_E)
        self.rk = step_row_kernels(self.np_dtype, cfg.stabilisation.curvature_correction, cfg.integrator == "midpoint")
        self.sk = solver_kernels(self.np_dtype, self.dense, llt and not self.sparse_factor, not llt,
                                 bool(cfg.warm_start), self.adaptive)
        # world health: only where post-stabilisation's extra pass projected, when its screen (a gap of
        # REPROJECTION_GAP + the dead band) is below the bound
        screened = (cfg.stabilisation.post_stabilisation > 0
                    and REPROJECTION_GAP + joint_deadband(self.np_dtype) < LOOP_OPEN_BOUND)
        self.ik = end_step_kernels(self.np_dtype, self.dense, screened)
        #: world health: each world's linear speed bound (kamino.tables.health_speed_bound)
        speed_bound = health_speed_bound(world_reach(model), cfg.dt)
        self.speed_bound = wp.array(speed_bound.astype(self.np_dtype), device=self.device)
        self.ck = contact_kernels(self.np_dtype) if model.num_pairs else None
        self.pk = post_stabilisation_kernels(self.np_dtype) if cfg.stabilisation.post_stabilisation else None
        #: PADMM's effort-limited rows switch to the larger penalty when they saturate, and the world's factor is
        #: redone (kamino.jax_ref.solver.solve, "Saturation"): at most one switch per actuator row and step, so on
        #: the CPU (no capture_while) a step launches PADMM that many times plus one. The Conjugate Residual path
        #: keeps the larger penalty on every effort-limited row instead (``solver.scale``'s ``always_sat``): with
        #: the proximal shift on those rows its inexact solves stalled PADMM on standing robots (olaf's loops
        #: 1.07e-5 m, dr_legs at 30 CR iterations unconverged; tests/test_robots.py)
        tab = row_tables(model)
        dyn_world = np.repeat(np.arange(wm.num_worlds), tab.world_dyn_count)
        act_rows = np.bincount(dyn_world[tab.dyn_kind == DYN_ACTUATOR], minlength=1)
        #: (under the reduction a saturation recomputes the reduced problem's inverse inside the launch)
        self.max_switches = int(act_rows.max()) if self.adaptive and llt and not self.schur else 0
        self.use_graph = self.device.is_cuda
        self.padmm_chunk = cfg.max_iterations if not self.use_graph else min(cfg.max_iterations, 8)
        self._graphs: dict[int, object] = {}
        #: the ``(module, block size)`` pairs :meth:`precompile` compiled (``None`` before it ran)
        self.precompiled: frozenset | None = None
        #: while :meth:`precompile` records a step: the ``(module, block size)`` of each launch
        self._recording: set | None = None
        #: callables ``f(stepper)`` enqueued at the start of every step (captured with it), e.g. a
        #: kernel that sets the controls from the device-side time
        self.pre_step: list = []
        #: callables ``f(stepper)`` enqueued at the end of every step (captured with it), e.g. a kernel that folds
        #: the step's iterations into statistics
        self.post_step: list = []

    def _schur_buffers(self, model: Model):
        """The reduced problem's buffers (``solver_lanes.schur_buffers``): room for every dynamics row of a world
        (the effort-limited actuator rows among them) and its limit and contact rows in ``T``; the elimination's
        shift ``eta + rho_free`` (``kamino.jax_ref.solver._solve_schur``: the adaptive penalty's, in either penalty
        mode) and the warm-start filter's shift."""
        cfg, wm = self.cfg, self.wm
        tab = row_tables(model)
        tail = wm.arrays.row_maxdim.numpy() - wm.arrays.row_fixed.numpy()
        tm = int(np.max(np.asarray(tab.world_dyn_count) + tail, initial=0))
        cap = schur_list_cap(fixed_row_types(model).rows, wm.blocks_per_row, self._np_max())
        return schur_buffers(self.np_dtype, self.device, wm.num_worlds, wm.total_rows, max(tm, 1), self._np_max(),
                             max(int(wm.max_bodies), 1), cfg.penalty.eta + cfg.penalty.rho_free,
                             WARM_START_FILTER_SHIFT if cfg.warm_start else 0.0, cap)

    def _np_max(self) -> int:
        """The fixed positions (fixed rows and hub unknowns) of the largest world (at least 1)."""
        return max(int(self.sf.arrays.n_pos.numpy().max(initial=0)), 1)

    def _schur(self, mode: int) -> None:
        """The reduction's launch ``mode``: the elimination (``solver_lanes.schur_kernel``), the reduced right-hand
        side or the recovery (``solver_lanes.schur_solve_kernel``)."""
        cfg, w = self.cfg, self.work
        inputs = [self.wm.blocks_per_row, cfg.penalty.eta, self.rho_free, cfg.penalty.rho, w.row_stride, self.sp,
                  w.n_rows, w.frozen, w.row_body, w.row_J, w.reg, w.P, w.vt, w.inv_inertia_w, w.lo_s, w.hi_s,
                  w.row_info, w.rho_u]
        kernel = self.wk.schur if mode == SCHUR_ELIMINATE else self.wk.schur_solve
        self._launch_lanes(kernel, inputs=inputs if mode == SCHUR_ELIMINATE else [mode, *inputs],
                           outputs=[self.sch, w.p_ref, w.x, w.x_p, w.y_p, w.y_hat, w.z_p, w.z_hat, w.impulse,
                                    w.velocity, w.failed])

    # --- launches -------------------------------------------------------------------------------
    def _launch(self, kernel, dim, inputs: list, outputs: list) -> None:
        """Launch a kernel whose signature is ``(m, *inputs, *outputs)``: the model's arrays, then what the kernel
        reads, then what it writes (an array it reads and writes is an output), on ``dim``. One-thread-per-world
        kernels use blocks of 32 threads, so that a few thousand worlds spread over every multiprocessor (a world's
        thread does serial work)."""
        if all(int(d) > 0 for d in (dim if isinstance(dim, tuple) else (dim,))):
            block = PER_WORLD_BLOCK if not isinstance(dim, tuple) else 256
            if self._recording is not None:
                self._recording.add((kernel.module, block))
                return
            wp.launch(kernel, dim=dim, inputs=[self.wm.arrays, *inputs], outputs=outputs, device=self.device,
                      block_dim=block)

    def launch_step(self) -> None:
        """Enqueue one step (capturable: no host synchronisation)."""
        cfg, wm, w = self.cfg, self.wm, self.work
        rk, sk, ik, ck = self.rk, self.sk, self.ik, self.ck
        W, nblk = wm.num_worlds, wm.blocks_per_row
        dt = cfg.dt
        midpoint = cfg.integrator == "midpoint"
        h = 0.5 * dt if midpoint else dt
        delta = joint_deadband(self.np_dtype)
        self.precompile()
        recording = self._recording is not None
        for hook in () if recording else self.pre_step:
            hook(self)
        if midpoint:
            self._launch(rk.advance_poses, (W, wm.max_bodies), inputs=[h, w.q, w.u],
                            outputs=[w.q_eval])  # the midpoint pose
        self._launch(rk.dof_blocks, (W, wm.max_dofs), inputs=[w.q_eval, w.effort],
                        outputs=[w.dof_JF, w.dof_JB, w.q_dof, w.tau_explicit])
        self._launch(rk.bodies, (W, wm.max_bodies),
                        inputs=[dt, h, w.q_eval, w.wrench, w.tau_explicit, w.dof_JF, w.dof_JB, w.u],
                        outputs=[w.inertia_w, w.inv_inertia_w, w.u_f, w.q_pred])
        self._launch(rk.dof_rates, (W, wm.max_dofs), inputs=[w.u, w.u_f, w.dof_JF, w.dof_JB, w.q_pred],
                        outputs=[w.qd_minus, w.qd_free, w.q_dof_pred])
        self._launch(rk.dyn_rows, (W, wm.max_dyn),
                        inputs=[nblk, dt, h, w.row_stride, w.dof_JF, w.dof_JB, w.q_dof, w.qd_minus, w.effort,
                                w.position_target, w.velocity_target, w.act_force, w.pas_force],
                        outputs=[w.row_body, w.row_J, w.vstar, w.reg, w.lo, w.hi, w.f0, w.v0, w.row_info])
        self._launch(rk.joint_rows, (W, wm.max_cts),
                        inputs=[nblk, h, cfg.stabilisation.baumgarte, delta, w.row_stride, w.q_eval, w.q, w.q_pred,
                                w.u_f, w.kin_force],
                        outputs=[w.row_body, w.row_J, w.vstar, w.reg, w.lo, w.hi, w.f0, w.v0, w.row_info])
        self._launch(rk.coupling_rows, (W, wm.max_cpl),
                        inputs=[nblk, h, cfg.stabilisation.baumgarte, delta, w.row_stride, w.dof_JF, w.dof_JB, w.q_dof,
                                w.q_dof_pred, w.q, w.u_f, w.cpl_force],
                        outputs=[w.row_body, w.row_J, w.vstar, w.reg, w.lo, w.hi, w.f0, w.v0, w.row_info])
        self._launch(rk.limits, (W, wm.max_lim), inputs=[dt, LIMIT_MARGIN, LIMIT_BAUMGARTE, w.q_dof, w.qd_free],
                        outputs=[w.lim_side, w.lim_active, w.lim_bias])
        self._launch(rk.pack_limits, W,
                        inputs=[nblk, w.row_stride, w.lim_active, w.lim_side, w.lim_bias, w.lim_force, w.dof_JF,
                                w.dof_JB],
                        outputs=[w.row_body, w.row_J, w.vstar, w.reg, w.lo, w.hi, w.f0, w.v0, w.row_info, w.n_lim])
        if ck is not None:
            self._launch(ck.narrow_phase, (W, wm.max_pairs), inputs=[dt, cfg.contact_margin, w.u_f, w.q_eval],
                            outputs=[w.cand_pos, w.cand_normal, w.cand_dist, w.cand_valid])
            self._launch(ck.pack, W, inputs=[dt, cfg.contact_margin, CONTACT_DEADBAND, RESTITUTION_THRESHOLD,
                                                w.q_eval, w.u, w.u_f, w.cand_pos, w.cand_normal, w.cand_dist,
                                                w.cand_valid],
                            outputs=[w.ct_pair, w.ct_body_a, w.ct_body_b, w.ct_pos, w.ct_normal, w.ct_dist, w.ct_mu,
                                     w.ct_restitution, w.ct_found, w.n_con])
        self._launch(sk.count_rows, W, inputs=[w.n_lim, w.n_con, w.frozen], outputs=[w.n_box, w.n_rows, w.failed])
        if ck is not None:
            self._launch(ck.contact_rows, (W, wm.max_contacts),
                            inputs=[nblk, dt, CONTACT_BAUMGARTE, CONTACT_DEADBAND, RESTITUTION_THRESHOLD,
                                    CONTACT_MATCH_DISTANCE, w.row_stride, w.n_con, w.n_box, w.ct_pair, w.ct_body_a,
                                    w.ct_body_b, w.ct_pos, w.ct_normal, w.ct_dist, w.ct_mu, w.ct_restitution,
                                    w.q_eval, w.u, w.con_pair, w.con_force, w.con_velocity, w.con_point_b],
                            outputs=[w.row_body, w.row_J, w.reg, w.lo, w.hi, w.row_info, w.vstar, w.f0, w.v0])
        # dynamics: v_f (and the dense J, M^-1 J^T), Delassus (dense path) and preconditioning (§7.2, §8)
        rows = (W, wm.max_rows)
        self._launch(sk.prebake, rows, inputs=[nblk, w.row_stride, w.n_rows, w.vstar, w.row_body, w.row_J, w.u_f,
                                                  w.inv_inertia_w], outputs=[w.vt, w.Jd, w.MJd])
        assembled = self.linear_solver == "llt" and not self.sparse_factor  # the dense Delassus matrix
        if assembled:
            if self.dense:
                self._launch(sk.delassus_dense, rows, inputs=[w.row_stride, w.n_rows, w.Jd, w.MJd, w.reg],
                                outputs=[w.D])
            else:
                self._launch(sk.delassus_sparse, rows, inputs=[nblk, w.row_stride, w.n_rows, w.row_body, w.row_J,
                                                                  w.reg, w.inv_inertia_w], outputs=[w.D])
        self._launch(sk.precondition, rows, inputs=[nblk, w.row_stride, w.n_rows, w.n_box, w.row_body, w.row_J,
                                                       w.reg, w.inv_inertia_w, w.D], outputs=[w.P])
        shift_f, shift_b = self.padmm_shifts
        scale_ws = cfg.warmstart_scale * dt if cfg.warm_start else 0.0
        self._launch(sk.scale, rows, inputs=[shift_f, shift_b, scale_ws, w.row_stride, w.n_rows, w.P, w.lo, w.hi,
                                                w.f0], outputs=[w.vt, w.lo_s, w.hi_s, w.row_info, w.D])
        if self.sparse_factor and not self.schur:  # (under the reduction: the elimination's factor, below)
            self._launch(self.spk.assemble_fixed, (W, self.sf.max_nnz),
                            inputs=[nblk, shift_f, shift_b, w.row_stride, w.row_body, w.row_J, w.row_info, w.reg, w.P,
                                    w.inertia_w, w.inv_inertia_w], outputs=[self.sp])
            self._launch(self.spk.assemble_tail, rows,
                            inputs=[nblk, w.row_stride, w.n_rows, w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg,
                                    w.P, w.inv_inertia_w], outputs=[self.sp])
        # PADMM (§7), optionally refined (curvature along the solved velocity)
        w.remaining.fill_(W)
        self._launch(sk.padmm_init, W,
                        inputs=[scale_ws, cfg.max_iterations, cfg.penalty.eta, cfg.penalty.rho, w.row_stride,
                                w.n_rows, w.n_box, w.frozen, w.f0, w.v0, w.P, w.lo_s, w.hi_s, w.ct_mu, w.row_info],
                        outputs=[w.x, w.x_p, w.y_p, w.y_hat, w.z_p, w.z_hat, w.p_ref, w.rho_u, w.pending, w.iters,
                                 w.r_p, w.r_d, w.r_c, w.a_p, w.c_p, w.it_cap, w.k_rho, w.converged, w.done,
                                 w.remaining, w.sdiag, w.D])
        if self.filt is not None:  # the warm start without its nearly null directions
            self._filter_warm_start(self.filt, self.filter_lanes)
        if self.schur:  # L_f of A + eps I on F (D~_f with the elimination's shift, the effort-limited rows
            # decoupled), then the reduced problem
            self._launch(self.wk.schur_decouple, (W, self.sf.max_nnz),
                         inputs=[nblk, self.sch.eps, shift_b, w.row_stride, w.row_body, w.row_J, w.row_info, w.reg,
                                 w.P, w.inertia_w, w.inv_inertia_w, w.lo_s, w.hi_s], outputs=[self.sp])
            self._launch_lanes(self.wk.factor,
                               inputs=[cfg.penalty.eta, 0, nblk, shift_f, shift_b, w.row_stride, wm.arrays.row_fixed,
                                       w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w,
                                       w.inv_inertia_w, w.rho_u], outputs=[w.pending, self.sp])
            self._schur(SCHUR_ELIMINATE)
        elif self.padmm == "warp" and self.sparse_factor:
            self._launch_lanes(self.wk.factor,
                                  inputs=[cfg.penalty.eta, 0, nblk, shift_f, shift_b, w.row_stride, w.n_rows,
                                          w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w,
                                          w.inv_inertia_w, w.rho_u], outputs=[w.pending, self.sp])
        elif self.padmm == "warp":  # CR: the row blocks grouped by body for the operator
            self._launch(self.wk.cr_pattern, W, inputs=[nblk, w.row_stride, w.n_rows, w.row_body],
                            outputs=[w.cr_end, w.cr_ent])
        elif self.sparse_factor:
            self._launch(self.spk.factor, W, inputs=[cfg.penalty.eta, w.row_stride, w.n_rows, w.rho_u],
                            outputs=[self.sp])
        self._padmm_loop()
        self._launch(sk.padmm_finish, rows, inputs=[w.row_stride, w.n_rows, w.n_box, w.P, w.y_p, w.z_p, w.ct_mu,
                                                       w.row_info], outputs=[w.impulse, w.velocity, w.failed])
        if self.schur:
            self._schur(SCHUR_RECOVER)
        stab = cfg.stabilisation
        if stab.curvature_refinement and stab.curvature_correction and (wm.max_cts or wm.max_cpl):
            self._launch(ik.integrate, (W, wm.max_bodies),
                            inputs=[nblk, h, ANGULAR_DAMPING * dt, w.row_stride, w.n_rows, w.impulse, w.Jd, w.row_body,
                                    w.row_J, w.u_f, w.inv_inertia_w, w.q_eval],
                            outputs=[w.u_new, w.q_new, w.failed])
            self._launch(rk.advance_poses, (W, wm.max_bodies), inputs=[h, w.q_eval, w.u_new],
                            outputs=[w.q_pred])  # q_pred along u+
            self._launch(rk.refine_joint_rows, (W, wm.max_cts),
                            inputs=[nblk, h, cfg.stabilisation.baumgarte, delta, w.row_stride, w.q_eval, w.q, w.q_pred,
                                    w.u_new, w.row_body, w.row_J, w.u_f, w.P, w.converged],
                            outputs=[w.vstar, w.vt])
            self._launch(rk.refine_coupling_rows, (W, wm.max_cpl),
                            inputs=[nblk, h, cfg.stabilisation.baumgarte, delta, w.row_stride, w.q_dof, w.q, w.q_pred,
                                    w.u_new, w.row_body, w.row_J, w.u_f, w.P, w.converged],
                            outputs=[w.vstar, w.vt])
            if self.schur:  # v'_T of the refined v_f
                self._schur(SCHUR_RHS)
            w.remaining.fill_(W)
            self._launch(sk.padmm_resume, W,
                            inputs=[cfg.max_iterations, w.row_stride, w.n_rows, w.frozen, w.iters, w.y_p, w.z_p],
                            outputs=[w.y_hat, w.z_hat, w.a_p, w.c_p, w.it_cap, w.k_rho, w.converged, w.done,
                                     w.remaining])
            self._padmm_loop()
            self._launch(sk.padmm_finish, rows, inputs=[w.row_stride, w.n_rows, w.n_box, w.P, w.y_p, w.z_p,
                                                           w.ct_mu, w.row_info],
                            outputs=[w.impulse, w.velocity, w.failed])
            if self.schur:
                self._schur(SCHUR_RECOVER)
        # integrate, split the forces, commit (§6)
        self._launch(ik.integrate, (W, wm.max_bodies),
                        inputs=[nblk, h, ANGULAR_DAMPING * dt, w.row_stride, w.n_rows, w.impulse, w.Jd, w.row_body,
                                w.row_J, w.u_f, w.inv_inertia_w, w.q_eval],
                        outputs=[w.u_new, w.q_new, w.failed])
        if cfg.stabilisation.post_stabilisation:  # position projections (post_stabilisation.py)
            if self.post_shares_factor:  # L_f of PADMM's factor: the same matrix, the tail is not read
                post = self.sp
            else:
                post = self.post.arrays
                shift_f, shift_b = cfg.projection_shifts(self.np_dtype)
                self._launch(self.spk.assemble_fixed, (W, self.post.max_nnz),
                                inputs=[nblk, shift_f, shift_b, w.row_stride, w.row_body, w.row_J, w.row_info, w.reg,
                                        w.P, w.inertia_w, w.inv_inertia_w], outputs=[post])
                if self.padmm == "warp":  # n_rows = the fixed rows' count: L_f alone (the factor has no tail rows)
                    self._launch_lanes(self.post_factor,
                                       inputs=[0.0, 0, nblk, shift_f, shift_b, w.row_stride, wm.arrays.row_fixed,
                                               w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w,
                                               w.inv_inertia_w, w.rho_u], outputs=[w.pending, post])
                else:
                    self._launch(self.spk.factor_fixed, W, inputs=[w.row_stride], outputs=[post])
            passes = cfg.stabilisation.post_stabilisation
            for k in range(passes + 1):  # the last pass: unconverged worlds, gaps left open
                extra = int(k == passes)
                self._launch(self.pk.residual, rows, inputs=[delta, extra, w.row_stride, w.q_new, w.P],
                                outputs=[w.reproject, w.x, w.remaining])
                if self.padmm == "warp":
                    self._launch_lanes(self.wk.solve_fixed, inputs=[extra, w.row_stride, post, w.converged,
                                                                       w.reproject, w.P], outputs=[w.x])
                else:
                    self._launch(self.pk.solve, W, inputs=[extra, w.row_stride, post, w.converged, w.reproject, w.P],
                                    outputs=[w.x])
                self._launch(self.pk.displace, (W, wm.max_bodies),
                                inputs=[nblk, extra, w.row_stride, w.converged, w.reproject, w.row_body, w.row_J, w.x,
                                        w.inv_inertia_w],
                                outputs=[w.failed, w.q_new])
            if self.gn is not None:
                for extra in range(2, 2 + REPROJECTION_PASSES):
                    self._gauss_newton_pass(extra, delta)
        # world health: a world whose bodies pass the speed bounds, or whose joints the step left open past the
        # bound, fails on this step
        self._launch(ik.speed_check, (W, wm.max_bodies), inputs=[HEALTH_TURN / dt, self.speed_bound, w.u_new],
                     outputs=[w.failed])
        if wm.max_cts:
            self._launch(ik.closure_check, (W, wm.max_cts),
                            inputs=[LOOP_OPEN_BOUND, w.converged, w.reproject, w.q_new, w.q], outputs=[w.failed])
        self._launch(ik.dof_forces, (W, wm.max_dofs), inputs=[w.failed, w.tau_explicit],
                        outputs=[w.act_force, w.pas_force, w.lim_force])
        self._launch(ik.row_forces, rows, inputs=[1.0 / dt, w.row_stride, w.n_box, w.failed, w.impulse, w.row_info],
                        outputs=[w.act_force, w.pas_force, w.kin_force, w.cpl_force, w.lim_force])
        if ck is not None:
            self._launch(ck.commit_contacts, (W, wm.max_contacts),
                            inputs=[1.0 / dt, w.row_stride, w.failed, w.n_con, w.n_box, w.ct_pair, w.ct_body_b,
                                    w.ct_pos, w.ct_normal, w.ct_dist, w.q_eval, w.impulse, w.velocity],
                            outputs=[w.con_pair, w.con_pos, w.con_normal, w.con_dist, w.con_force, w.con_velocity,
                                     w.con_point_b])
        self._launch(ik.commit_bodies, (W, wm.max_bodies), inputs=[w.failed, w.q_new, w.u_new], outputs=[w.q, w.u])
        if recording:
            self._recording.add((ik.commit_time.module, 256))
        else:
            wp.launch(ik.commit_time, dim=W, inputs=[dt, int(cfg.max_unconverged_steps)],
                      outputs=[w.converged, w.frozen, w.failed, w.time, w.unconverged], device=self.device,
                      block_dim=256)
        for hook in () if recording else self.post_step:
            hook(self)

    def _filter_warm_start(self, filt: linear_solve.SparseFactor, lanes: bool) -> None:
        """The warm-start filter (docs/conventions.md, "Warm start"): ``P D_ff P + s I`` assembled into ``filt`` (one
        thread per entry; ``s = WARM_START_FILTER_SHIFT`` on every fixed row), factorised, and the warm start's
        fixed rows filtered with it. ``lanes``: with the world's 32 threads (``solver_lanes.factor_kernel`` on the
        fixed rows only, ``solver_lanes.warm_start_filter_kernel``; ``filt`` built ``per_world``), else one thread
        per world (``linear_solve.factor_fixed``, ``solver.warm_start_filter_kernel``)."""
        w, W, s = self.work, self.wm.num_worlds, WARM_START_FILTER_SHIFT
        sp = filt.arrays
        self._launch(self.spk.assemble_fixed, (W, filt.max_nnz),
                     inputs=[self.wm.blocks_per_row, s, s, w.row_stride, w.row_body, w.row_J, w.row_info, w.reg, w.P,
                             w.inertia_w, w.inv_inertia_w], outputs=[sp])
        vectors = [w.x, w.x_p, w.y_p, w.y_hat]
        if lanes:  # n_rows = the fixed rows' count: L_f alone (the factor has no tail rows)
            self._launch_lanes(self.wk.filter_factor,
                               inputs=[0.0, 0, self.wm.blocks_per_row, s, s, w.row_stride, self.wm.arrays.row_fixed,
                                       w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w,
                                       w.inv_inertia_w, w.rho_u], outputs=[w.pending, sp])
            self._launch_lanes(self.wk.warm_start_filter,
                               inputs=[s, w.row_stride, sp, w.frozen, w.lo_s, w.hi_s], outputs=vectors)
        else:
            self._launch(self.spk.factor_fixed, W, inputs=[w.row_stride], outputs=[sp])
            self._launch(self.sk.warm_start_filter, W, inputs=[s, w.row_stride, sp, w.frozen, w.lo_s, w.hi_s],
                         outputs=vectors)

    def _gauss_newton_pass(self, extra: int, delta: float) -> None:
        """Post-stabilisation's Gauss-Newton pass ``extra`` (2, 3, ...): in the worlds whose anchors are still open
        past ``REPROJECTION_GAP`` (``w.reproject``, counted in ``w.remaining``, PADMM's counter, idle by now), the
        joint rows' Jacobian at the projected pose, the projection's factor with it, one solve and displacement.
        Nothing runs when no world is open (``wp.capture_if``; a conditional node in a captured graph)."""
        cfg, wm, w = self.cfg, self.wm, self.work
        W, nblk, rows = wm.num_worlds, wm.blocks_per_row, (wm.num_worlds, wm.max_rows)
        w.remaining.zero_()
        self._launch(self.pk.residual, rows, inputs=[delta, extra, w.row_stride, w.q_new, w.P],
                     outputs=[w.reproject, w.x, w.remaining])

        def project() -> None:
            gn = self.gn.arrays
            shift_f, shift_b = cfg.projection_shifts(self.np_dtype)
            self._launch(self.pk.jacobian, (W, wm.max_cts), inputs=[nblk, extra, w.row_stride, w.reproject, w.q_new],
                         outputs=[w.row_body, w.row_J])
            self._launch(self.pk.assemble, (W, self.gn.max_nnz),
                         inputs=[nblk, shift_f, shift_b, extra, w.row_stride, w.reproject, w.row_body, w.row_J,
                                 w.row_info, w.reg, w.P, w.inertia_w, w.inv_inertia_w], outputs=[gn])
            self._launch(self.pk.factor, W, inputs=[extra, w.row_stride, w.reproject], outputs=[gn])
            self._launch(self.pk.solve, W, inputs=[extra, w.row_stride, gn, w.converged, w.reproject, w.P],
                         outputs=[w.x])
            self._launch(self.pk.displace, (W, wm.max_bodies),
                         inputs=[nblk, extra, w.row_stride, w.converged, w.reproject, w.row_body, w.row_J, w.x,
                                 w.inv_inertia_w], outputs=[w.failed, w.q_new])

        if self._recording is not None:  # (a dry run records the launches of both branches)
            project()
        else:
            wp.capture_if(w.remaining, on_true=project)

    def invalidate_graphs(self) -> None:
        """Forget the captured graphs (after changing ``pre_step`` or the config-dependent launches)."""
        self._graphs.clear()

    def _launch_lanes(self, kernel, inputs: list, outputs: list) -> None:
        """Launch a 32-threads-per-world kernel (``solver_lanes.py``), one block of ``LANES`` threads per world, whose
        signature is ``(m, *inputs, *outputs)`` (:meth:`_launch`)."""
        if self._recording is not None:
            self._recording.add((kernel.module, LANES))
            return
        wp.launch_tiled(kernel, dim=[self.wm.num_worlds], inputs=[self.wm.arrays, *inputs], outputs=outputs,
                        block_dim=LANES, device=self.device)

    def precompile(self) -> None:
        """Compile every Warp module a step launches, once, before the first step. Each kernel is a module of its
        own, which Warp otherwise compiles at its first launch, one after another. On a CUDA device the modules
        compile in parallel (``wp.force_load`` with a thread per CPU core; NVRTC runs outside Python's lock); on
        the CPU one after another, as at their first launches. The modules come from a dry run of
        :meth:`launch_step` that records each launch's kernel and block size instead of launching it
        (``pre_step`` and ``post_step`` hooks are left out: their kernels compile at their first launch).

        It runs under :data:`CUDA_STREAM_LOCK` (the dry run's fills go through Warp's stream), so that a thread that
        reaches a stepper another thread is compiling (``Engine.compile_in_background``) waits for the modules
        instead of launching before they are loaded. A failure leaves the stepper uncompiled: the next call raises
        the same error in its own thread."""
        if self.precompiled is not None:  # compiled already: no lock taken
            return
        with CUDA_STREAM_LOCK:
            if self.precompiled is not None or self._recording is not None:
                return  # another thread compiled it meanwhile, or this is this thread's own dry run
            self._recording = set()
            try:
                self.launch_step()
                launches = frozenset(self._recording)
            finally:
                self._recording = None
            workers = (os.cpu_count() or 1) if self.device.is_cuda else 0
            for block in sorted({b for _, b in launches}):
                wp.force_load(self.device, [m for m, b in launches if b == block], block_dim=block,
                              max_workers=workers)
            self.precompiled = launches

    def _padmm_loop(self) -> None:
        """PADMM iterations until every world is done: ``wp.capture_while`` on the device counter of worlds
        still iterating when capturing a CUDA graph, else launches running each world to its cap or to a switch
        (one more than the switches a step can have, ``max_switches``). After each launch the worlds whose
        effort-limited rows saturated have their factor redone (``Work.pending``)."""
        cfg, w = self.cfg, self.work
        W, nblk = self.wm.num_worlds, self.wm.blocks_per_row
        shift_f, shift_b = self.padmm_shifts
        problem = rules.fill_struct(rules.problem_struct(self.np_dtype), w, nblk=nblk,
                                    cr_budget=int(cfg.warp.cr_iterations), eta=cfg.penalty.eta, rho_free=self.rho_free,
                                    rho_box=cfg.penalty.rho, tol=cfg.tolerance, restart_tol=RESTART_TOLERANCE,
                                    **({"vt": self.sch.vt} if self.schur else {}))
        carry = rules.fill_struct(rules.carry_struct(self.np_dtype), w)
        vectors = [w.row_info, w.x, w.y, w.z, w.cr_r, w.cr_p, w.cr_Ap, w.cr_Ar, w.cr_w]
        modes = (self.adaptive, bool(cfg.acceleration), bool(cfg.fixed_iterations))
        if self.padmm == "warp":
            lane_iterate = iterate_kernel(self.np_dtype, self.wk.R, self.wk.cr, *modes, self.wk.inverse, self.schur)

            def iterate(chunk):
                self._launch_lanes(lane_iterate, inputs=[problem, chunk], outputs=[carry, self.sp, *vectors, self.sch])
                if self.max_switches:  # the factor of the worlds whose effort-limited rows saturated
                    self._launch_lanes(self.wk.factor,
                                          inputs=[cfg.penalty.eta, 1, nblk, shift_f, shift_b, w.row_stride, w.n_rows,
                                                  w.row_body, w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w,
                                                  w.inv_inertia_w, w.rho_u], outputs=[w.pending, self.sp])
        else:
            linear = LINEAR_CR if self.linear_solver == "cr" else LINEAR_SPARSE if self.sparse_factor else (
                LINEAR_DENSE)
            thread_iterate = padmm_iterate_kernel(self.np_dtype, linear, *modes)

            def iterate(chunk):
                self._launch(thread_iterate, W, inputs=[problem, chunk], outputs=[carry, self.sp, w.D, *vectors])
                if self.max_switches and self.sparse_factor:
                    self._launch(self.spk.refactor, W,
                                    inputs=[nblk, shift_f, shift_b, cfg.penalty.eta, w.row_stride, w.n_rows, w.row_body,
                                            w.row_J, w.row_info, w.ct_pair, w.reg, w.P, w.inertia_w, w.inv_inertia_w,
                                            w.rho_u], outputs=[w.pending, self.sp])
                elif self.max_switches:
                    self._launch(self.sk.refactor_dense, W,
                                    inputs=[nblk, shift_f, shift_b, cfg.penalty.eta, w.row_stride, w.n_rows,
                                            w.row_body, w.row_J, w.row_info, w.reg, w.inv_inertia_w, w.P, w.rho_u],
                                    outputs=[w.pending, w.sdiag, w.D])
        if self.device.is_capturing and self._recording is None:  # (a dry run records the body once)
            wp.capture_while(w.remaining, lambda: iterate(self.padmm_chunk))
        else:  # each launch runs the worlds to their cap or to a switch
            for _ in range(self.max_switches + 1):
                iterate(2 * cfg.max_iterations)

    def __del__(self, _lock=CUDA_STREAM_LOCK) -> None:
        """On a CUDA device, free the buffers and graphs while holding :data:`CUDA_STREAM_LOCK`: a free on Warp's
        stream while another thread captures a graph on it would break that capture. The lock is bound at definition:
        at interpreter exit the module's globals may already be gone."""
        if getattr(self, "device", None) is not None and self.device.is_cuda:
            with _lock:
                self.__dict__.clear()

    def run(self, num_steps: int) -> None:
        """Advance ``num_steps`` steps in place (replaying a captured graph on CUDA)."""
        if not self.use_graph:
            for _ in range(num_steps):
                self.launch_step()
            return
        wp.capture_launch(self.graph(num_steps))

    def captured(self, num_steps: int):
        """The CUDA graph of ``num_steps`` steps if :meth:`graph` captured it, else ``None``."""
        return self._graphs.get(num_steps)

    def graph(self, num_steps: int):
        """The CUDA graph of ``num_steps`` steps, captured on first use (on Warp's stream of the device; it replays
        on any stream, XLA's included: ``jit.py``)."""
        graph = self._graphs.get(num_steps)
        if graph is None:
            self.precompile()  # outside the capture: the dry run's fills are not part of the graph
            with CUDA_STREAM_LOCK, wp.ScopedCapture(device=self.device) as capture:
                for _ in range(num_steps):
                    self.launch_step()
            graph = self._graphs[num_steps] = capture.graph
        return graph
