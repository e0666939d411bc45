"""Solver configuration (frozen, hashable: it is a static argument of the compiled step).

The defaults, why they are what they are, and the one setting that trades speed for accuracy (``tolerance``):
docs/settings.md. Design notes behind each: docs/conventions.md.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import re
from typing import Literal

import numpy as np

#: the adaptive penalty of the limit and contact rows changes at most every ``PENALTY_INTERVAL`` PADMM iterations,
#: and only when the primal and dual residuals are out of balance by more than ``PENALTY_THRESHOLD`` (on the square
#: root of their ratio); it stays in ``[RHO_MIN, RHO_MAX]`` (the scaled problem has a unit diagonal). Both backends
#: use these (docs/conventions.md, "Penalty"). Against 10 and 5, where the slowest steps are solves whose primal
#: residual stays 2-5x the dual one for 100+ iterations, 5 and 2 lower the 99th percentile of iterations per step by
#: 15-22 % on the robots and the four-bar (64 worlds x 400 steps of every benchmark scene, Warp CPU, float32,
#: defaults); no scene converges less often or closes its loops worse
PENALTY_INTERVAL, PENALTY_THRESHOLD = 5, 2.0
RHO_MIN, RHO_MAX = 1e-3, 10.0
#: one balancing step changes the penalty by at most this factor: the uncapped ``sqrt(r_p / r_d)`` is 0 when every
#: limit impulse is feasible (``r_p = 0``) and swings the penalty between ``RHO_MIN`` and 0.4 in a limit cycle on a
#: parallelogram four-bar with all three hinge limits active (docs/conventions.md, "Penalty")
PENALTY_MAX_FACTOR = 10.0
#: the PADMM residuals weigh each row by the square root of its effective mass, relative to the world's heaviest row,
#: but a light row's velocity error may exceed the tolerance by at most this factor (docs/conventions.md, "PADMM
#: defaults"): uncapped, dr_legs' light rotational rows let the standing robot lean by 1 cm in 5 s at tolerance 1e-3;
#: at 10, the driven four-bar's light limit rows stall PADMM in rare worlds (1 failed world of 4096 on the GPU)
RESIDUAL_LOOSENING_MAX = 30.0
#: a PADMM iterate whose remaining velocity error on the always-active rows no longer responds to the impulse
#: changes is a least-squares solution along a numerically null direction of the scaled Delassus matrix: it stops
#: (converged) when the change of that error is below ``NULL_DIRECTION_RATIO`` times the proximal shift times the
#: change of the impulse, a Rayleigh quotient below 1e-2 of the shift (docs/conventions.md, "Null directions")
NULL_DIRECTION_RATIO = 1e-2
#: an effort-limited row starts a PADMM solve saturated (penalty ``rho``) when its warm start lies within this
#: fraction of its bound (kamino.jax_ref.solver.solve, "Saturation"): a row saturated in the previous step comes back
#: as ``P (bound / P)``, a few roundings off the bound, on either side; an exact test split such rows between the
#: backends (measured on dr_legs in float64, 1 row in 12 on some steps)
SATURATION_MARGIN = 1e-4
#: the shift ``s`` of the warm-start filter (docs/conventions.md, "Warm start"): PADMM starts from
#: ``x0 - (P D_ff P + s I)^-1 s x0`` on the always-active rows, which keeps ``sigma / (sigma + s)`` of the warm start
#: along a direction of scaled curvature ``sigma``. The loop of a four-bar with a hinge tilted by 1° has ``sigma =
#: 1.2e-7`` there (kept: 11 %; at 0.1°, 1.2e-9: 0.1 %), by 10° ``1.2e-5`` (kept: 92 %), by 45° ``3.8e-4``; exactly
#: redundant rows have ``sigma = 0``. A factor with a shift much below this fails in float32 (1e-7 did on the four-bar)
WARM_START_FILTER_SHIFT = 1e-6
#: iterative-refinement steps of the eliminated rows' solves under ``SolverConfig.reduction = "schur"``
#: (``kamino.jax_ref.reduction``, docs/formulation.md §7.11): each one multiplies the error of the shifted factor along
#: a direction of scaled curvature ``sigma`` by ``eps / (sigma + eps)``; two leave dr_legs' loops closed like the full
#: solve in float32 (16 worlds x 64 steps of random PD targets; none: 1.6x the closure error, one: the same closure
#: but 13x the largest residual on those rows)
SCHUR_REFINEMENT_STEPS = 2
#: post-stabilisation gives a world one projection pass more when, after its ``post_stabilisation`` passes, an anchor
#: gap (a translational joint row's residual) is still above this [m], as it does when PADMM did not converge
#: (docs/conventions.md, "Post-stabilisation"). A pass leaves about ``h |omega|`` of the error it starts from, and
#: more along the directions its shift holds back; a healthy float32 world keeps its anchors within a few 1e-6 m,
#: and the eight-legged Jansen walker's one-pass gap after a foot lands (1.6e-5 m on an H200) closes to below this
#: with the second pass
REPROJECTION_GAP = 1e-5
#: post-stabilisation: a world whose anchors the extra pass leaves open past ``REPROJECTION_GAP`` gets up to this many
#: Gauss-Newton passes more, each with the joint rows' Jacobian evaluated again at the projected pose and the
#: projection's factor redone, until its gaps are below ``REPROJECTION_GAP`` (docs/conventions.md,
#: "Post-stabilisation"): the step's Jacobian lags a link that turns 0.5 rad in a step, and passes with it stall
REPROJECTION_PASSES = 4
#: world health (docs/conventions.md, "World health"; both backends read these): a world whose largest anchor gap (a
#: translational joint row's residual) exceeds ``LOOP_OPEN_BOUND`` [m] at the pose a step ends in, and exceeds the gap
#: it had before the step, fails on that step. A healthy world keeps its anchors within ~1e-5 m in float32
#: (post-stabilisation); a world whose solve diverges opens them by millimetres a few steps before its state turns
#: non-finite. Rotational rows are not checked: along a jammed loop's numerically null direction they drift by up to
#: 1e-2 rad in float32 in a healthy world (tests/test_world_health.py, the tilted four-bar)
LOOP_OPEN_BOUND = 1e-3
#: world health: a world fails on the step that leaves one of its bodies turning by more than ``HEALTH_TURN`` [rad] in
#: one step (``|omega| dt``: half a turn, beyond which the rotation of a step aliases) or moving faster than
#: ``max(HEALTH_SPEED, HEALTH_TURN * reach / dt)`` [m/s], where ``reach`` is the world's sum of joint lever arms
#: (``kamino.tables.world_reach``: no point of an articulated world is farther than it from a joint anchor). No sane
#: simulation reaches either (the four-bar at 2.5 ms: 1.2 km/s and 1257 rad/s, where a four-bar coasting fast turns
#: at 60 rad/s); a diverging solve passes both within a few steps while its state is still finite
HEALTH_TURN = math.pi
HEALTH_SPEED = 1e3
#: the backends' names (``backend=``): the JAX reference and the Warp backend
BACKENDS = ("jax", "warp")
#: Moreau-Jean midpoint rule: fraction ``gamma`` of the start pose's constraint velocity (as a displacement
#: over the half-step) that the end-of-step target keeps (docs/conventions.md "Stabilisation"). It makes
#: the end pose's constraint velocity ``w+ = -(1 - gamma) w- - alpha e- / h``; with ``gamma = 0`` the
#: target reverses ``w-`` every step (the trapezoidal rule's undamped alternating mode), with ``gamma = 1`` it is a
#: rotation, undamped too
MIDPOINT_DAMPING = 1.0 / 3.0
#: Newton iterations of the implicit-midpoint gyroscopic solve (docs/conventions.md, "Gyroscopic term"), fixed so
#: that the step stays capturable and differentiable. From the explicit guess 2 reach float64 rounding on the
#: 30 rad/s plate at dt = 2.5e-3; 4 also on bodies with a 70:1 inertia ratio at dt |w| = 0.35 (3 leave 3e-12)
GYRO_ITERATIONS = 4
#: narrow phase: golden-section steps (the bracket shrinks to 0.618**48 ~ 1e-10 of the segment)
GOLDEN_STEPS = 48
#: narrow phase: alternating-projection rounds (cylinder pairs)
PROJECTION_ROUNDS = 64
#: narrow phase: bisection steps (2**-32 of the segment)
BISECTION_STEPS = 32
#: narrow phase: capsule segments count as near parallel below sin(angle) = 0.1
PARALLEL_SIN2 = 1e-2


#: fixed settings, the same in both backends (docs/settings.md, "Constants"). Restart Nesterov's momentum when the
#: combined residual fails to drop below this factor (docs/formulation.md §7.4)
RESTART_TOLERANCE = 0.999
#: angular velocity damping rate [1/s] (docs/formulation.md §6.2 step 4): none
ANGULAR_DAMPING = 0.0
#: fraction ``gamma`` of a contact penetration removed per step (docs/formulation.md §4.2, §5)
CONTACT_BAUMGARTE = 0.2
#: the penetration term of a contact's normal bias asks at most this separating speed [m/s] (docs/formulation.md
#: §4.2, "gap bias"), as PhysX's maximum depenetration velocity: a body that starts 2 cm deep rises at this speed, not
#: at ``CONTACT_BAUMGARTE * d / dt`` (0.96 m/s at 1/240 s), and the energy the overlap injects is at most
#: ``m DEPENETRATION_SPEED**2 / 2`` (a 34 kg humanoid: 1.0 J, against 15 J unbounded; MuJoCo's default soft contact,
#: a critically damped spring of time constant 0.02 s, lifts it at up to 0.37 m/s, 2.2 J). The 2 cm are below 1 mm
#: after 0.09 s (MuJoCo: 0.10-0.12 s): 0.25 m/s is below MuJoCo's exit speed, yet resolves as fast. Only
#: penetrations deeper than ``DEPENETRATION_SPEED dt / CONTACT_BAUMGARTE`` (5.2 mm at 1/240 s) reach the bound:
#: resting contacts, which penetrate by micrometres, are unchanged
DEPENETRATION_SPEED = 0.25
#: fraction ``beta`` of a joint-limit violation removed per step (docs/formulation.md §4.1, §5)
LIMIT_BAUMGARTE = 0.2
#: gaps and penetrations below this [m] get no bias (``delta`` of docs/formulation.md §4.2)
CONTACT_DEADBAND = 1e-6
#: approach speed [m/s] below which contacts are inelastic (docs/formulation.md §4.2)
RESTITUTION_THRESHOLD = 0.1
#: a new contact continues a previous one of the same geom pair when their points on geom b are closer than this
#: [m] (warm start, docs/formulation.md §7.8)
CONTACT_MATCH_DISTANCE = 2e-3
#: a limit row is active when the DoF is within this distance [m or rad] of the limit, plus what its velocity covers
#: in the step (docs/formulation.md §4.1). The free velocity of a body does not see what its joints transmit (gravity
#: on a pendulum is a joint reaction), so a margin is needed for a DoF that rests on its limit not to fall through for
#: a step
LIMIT_MARGIN = 1e-2
#: joint position errors below this [m or rad] get no bias (rounding noise on redundant loop rows would otherwise be
#: an inconsistent right-hand side), by the state's dtype: :func:`joint_deadband` (docs/conventions.md,
#: "Stabilisation")
JOINT_DEADBAND_FLOAT32, JOINT_DEADBAND_FLOAT64 = 1e-6, 1e-11


def joint_deadband(dtype) -> float:
    """The joint dead band for states of ``dtype``: ``JOINT_DEADBAND_FLOAT32`` (1e-6) in float32,
    ``JOINT_DEADBAND_FLOAT64`` (1e-11) otherwise (docs/conventions.md, "Stabilisation")."""
    return JOINT_DEADBAND_FLOAT32 if np.dtype(dtype) == np.float32 else JOINT_DEADBAND_FLOAT64


def _rejecter(obj, path: str):
    """A ``bad(field, why)`` that raises a ``ValueError`` naming ``path.field`` and its value."""

    def bad(field: str, why: str) -> None:
        raise ValueError(f"{path}.{field}: {why} (got {getattr(obj, field)!r})")

    return bad


@dataclasses.dataclass(frozen=True)
class WarpSettings:
    """Warp backend settings (``SolverConfig.warp``): the Jacobian's layout and the linear solver of PADMM. The JAX
    reference always computes densely and solves by a dense Cholesky factorisation (it warns when given
    ``linear_solver="cr"`` or a non-default ``cr_iterations``, ``kamino.checks.check_config``); the physics is the
    same."""

    jacobian: Literal["dense", "sparse"] = "sparse"
    """``"sparse"`` block rows (default) or a ``"dense"`` per-world Jacobian."""
    linear_solver: Literal["llt", "cr", "auto"] = "auto"
    """``"llt"`` Cholesky (sparse factor with ``jacobian="sparse"``), ``"cr"`` matrix-free Conjugate Residual,
    ``"auto"`` (default): the LLT, except CR above ``AUTO_CR_ROWS`` rows per world on a GPU with one thread per world
    (``kamino.warp_backend.pipeline.resolve_linear_solver``)."""
    cr_iterations: int = 100
    """Conjugate Residual iterations per PADMM iteration. PADMM waits for an inexact inner solve: on the same 90
    problems of the eight-legged Jansen walker (float32) 30 take 17.7 PADMM iterations a step, 100 take 7.5, the LLT
    and the JAX reference 6.7; 9 left 5.6 % of them unconverged (docs/warp_backend.md, "Linear solvers")."""

    def __post_init__(self) -> None:
        bad = _rejecter(self, "SolverConfig.warp")
        if self.jacobian not in ("dense", "sparse"):
            bad("jacobian", "must be 'dense' or 'sparse'")
        if self.linear_solver not in ("llt", "cr", "auto"):
            bad("linear_solver", "must be 'llt', 'cr' or 'auto'")
        if int(self.cr_iterations) < 1:
            bad("cr_iterations", "must be >= 1")


@dataclasses.dataclass(frozen=True)
class Stabilisation:
    """How the joints' position errors are removed (``SolverConfig.stabilisation``; docs/formulation.md §5,
    docs/conventions.md "Stabilisation" and "Post-stabilisation")."""

    baumgarte: float = 0.01
    """fraction ``alpha`` of a joint's position error removed by the end of a step (§5)."""
    curvature_correction: bool = True
    """add the second-order drift of the pose update to the joint bias, so that velocity-level constraints hold at
    position level to O(dt^3) per step (docs/conventions.md, "Stabilisation")."""
    curvature_refinement: bool = True
    """after PADMM converges, evaluate the curvature term once more along the solved velocity ``u+`` and continue
    PADMM from its iterate (docs/conventions.md, "Stabilisation"): the loop closure error of a step drops from
    ``O(h^2 |u+ - u_f| |u|)`` to third order, and a loop driven by an explicit torque keeps its kinetic energy
    (docs/settings.md, "Integrators"), at the price of the extra iterations (up to ``max_iterations`` more). Only a
    world whose first solve converged and that has joint or coupling rows refines; any other keeps its first solve
    exactly, so a world's result does not depend on the worlds batched with it."""
    post_stabilisation: int = 1
    """number of position projections after the pose update (0: none; a world whose PADMM did not converge, or whose
    anchors are still open past ``REPROJECTION_GAP`` after them, gets one more, and a world whose anchors that one
    found open up to ``REPROJECTION_PASSES`` Gauss-Newton passes with the Jacobian at the projected pose). Each one
    removes the joint and
    coupling rows' position errors by the smallest mass-weighted displacement of the bodies (a Gauss-Newton step with
    the step's Jacobian and a sparse Cholesky of the always-active rows' Delassus block), so that a soft
    ``baumgarte`` can keep PADMM well conditioned while the loops stay closed (docs/conventions.md,
    "Post-stabilisation")."""
    projection_shift: float | None = None
    """the diagonal shift of post-stabilisation's scaled system (``None``: PADMM's own shifts of the always-active
    rows, ``eta + rho_free``, so that the Warp backend solves with PADMM's factor;
    :meth:`SolverConfig.projection_shifts`)."""

    def __post_init__(self) -> None:
        bad = _rejecter(self, "SolverConfig.stabilisation")
        if not (0.0 <= self.baumgarte <= 1.0):
            bad("baumgarte", "must lie in [0, 1]")
        if int(self.post_stabilisation) != self.post_stabilisation or self.post_stabilisation < 0:
            bad("post_stabilisation", "must be an integer >= 0 (the number of position projections per step)")
        if self.projection_shift is not None and not self.projection_shift > 0:
            bad("projection_shift", "must be > 0 or None")


@dataclasses.dataclass(frozen=True)
class Penalty:
    """ADMM penalty and proximal parameters (``SolverConfig.penalty``; docs/formulation.md §7.3, §7.6,
    docs/conventions.md "Penalty")."""

    mode: Literal["fixed", "adaptive"] = "adaptive"
    """``"adaptive"`` (default): the always-active rows carry ``rho_free``, the limit and contact rows a per-world
    penalty balanced by the residuals (docs/conventions.md, "Penalty"); ``"fixed"``: every row carries ``rho``
    (docs/formulation.md §7.6)."""
    rho: float = 0.1
    """the ADMM penalty (§7.3). With ``mode="adaptive"`` the starting penalty of the limit and contact rows, which
    each world then balances (and carries to its next step in ``state.info.penalty``)."""
    eta: float = 1e-5
    """the proximal parameter (§7.3): a diagonal shift of every row."""
    rho_free: float = 1e-4
    """the penalty of the always-active rows (joint-dynamics, joint, coupling) under ``mode="adaptive"``: only a
    proximal shift there, small for fast convergence, large enough to keep float32 factors of redundant loops well
    conditioned."""

    def __post_init__(self) -> None:
        bad = _rejecter(self, "SolverConfig.penalty")
        if self.mode not in ("adaptive", "fixed"):
            bad("mode", "must be 'adaptive' or 'fixed'")
        if not self.rho > 0:
            bad("rho", "must be > 0")
        if not self.eta >= 0:
            bad("eta", "must be >= 0")
        if not self.rho_free > 0:
            bad("rho_free", "must be > 0")


#: the nested settings' classes, by their ``SolverConfig`` field
NESTED = {"stabilisation": Stabilisation, "penalty": Penalty, "warp": WarpSettings}


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Time stepping, stabilisation and Proximal-ADMM settings (docs/formulation.md §5-§8). The stabilisation, the
    penalty and the Warp backend's settings are nested: ``SolverConfig(stabilisation=Stabilisation(baumgarte=1.0),
    penalty=Penalty(mode="fixed"), warp=WarpSettings(linear_solver="cr"))``; :meth:`replace` takes dotted names
    (``cfg.replace(**{"warp.linear_solver": "cr"})``). Fixed settings are module constants (``CONTACT_BAUMGARTE``
    and the others above)."""

    dt: float = 1.0 / 240.0
    """time step [s]."""
    integrator: Literal["euler", "midpoint"] = "midpoint"
    """``"midpoint"`` (default: Moreau-Jean, §6.3) or ``"euler"`` (semi-implicit Euler, §6.2). Both take one PADMM
    solve per step. The midpoint rule is second order in the free motion: a passive loop gains no energy from the
    step (the tilted four-bar of tests/test_tilted_fourbar.py at rest under gravity: at most 6.3e-5 J in 5 s, where
    Euler's first-order swing gains 3.7e-3 J), and a driven loop's kinetic energy follows the reference more closely
    (docs/settings.md, "Integrators")."""
    max_iterations: int = 200
    """PADMM iteration cap per step."""
    tolerance: float = 1e-3
    """the one knob that trades speed for accuracy. PADMM stops when its primal and dual residuals are below it as
    velocities [m/s or rad/s] of the world's heaviest constrained direction (each row's impulse and velocity error
    weighted by the square root of its effective mass: a row's kinetic-energy error is at most that of a
    ``tolerance`` velocity error on the heaviest row, and no row's velocity error exceeds ``RESIDUAL_LOOSENING_MAX``
    times ``tolerance``), and the complementarity residual ``|lambda v|`` below it too
    (``kamino.jax_ref.solver.solve``; docs/conventions.md, "PADMM defaults"). 1e-3 m/s moves a body by at most 2.5 um
    in a 2.5 ms step; post-stabilisation removes the joints' share of that drift. A robot at rest to below 1 mm/s
    asks for 1e-4; in float32 a tighter tolerance buys no loop closure (docs/settings.md: what each value buys and
    costs)."""
    fixed_iterations: bool = False
    """run exactly ``max_iterations`` PADMM iterations with no early exit (``lax.fori_loop``); under ``jax.grad`` the
    JAX reference's derivative is then the unrolled iterations' instead of the implicit one at the solution
    (docs/formulation.md §7.10), which needs no such mode; the Warp backend's is the implicit one either way."""
    redundant_limits: bool = False
    """fix ``lambda = 0`` up front on limit rows that are equivalent, modulo the bilateral rows, to another limit
    row with a smaller bias (all three hinge limits of a parallelogram loop); the solution is unchanged and PADMM
    stops creeping along the null direction (``kamino.jax_ref.solver.redundant_limits``). JAX reference, float64 only
    (float32 and the Warp backend raise)."""
    reduction: Literal["none", "schur"] = "none"
    """``"schur"`` eliminates the unbounded always-active rows (bilateral joint, loop-closure and coupling rows,
    actuator rows without an effort limit) before PADMM and runs PADMM on the Schur complement of the rest (limit,
    contact and effort-limited actuator rows), then recovers the eliminated impulses (docs/formulation.md §7.11;
    ``kamino.jax_ref.reduction``). ``"none"``: PADMM on every row. The JAX reference, and the Warp backend's
    32-thread schedule with the sparse factor (``padmm="warp"``, picked by itself then; docs/warp_backend.md)."""
    warm_start: bool = True
    """start PADMM from the previous step's constraint forces (§7.8)."""
    warmstart_scale: float = 1.0
    """factor on the warm-start reactions (§7.8)."""
    acceleration: bool = True
    """Nesterov acceleration with restart (§7.4)."""
    contact_margin: float = 1e-3
    """contacts count as active within this distance [m], added to the geoms' own margins (§4.2; ``LIMIT_MARGIN``
    is the joint limits' counterpart)."""
    max_unconverged_steps: int = 50
    """a world whose PADMM has not converged for more than this many consecutive steps is marked
    ``state.info.failed`` and frozen, like a world whose state went non-finite (docs/conventions.md, "World
    health")."""
    stabilisation: Stabilisation = Stabilisation()
    """joint stabilisation: Baumgarte fraction, curvature correction and refinement, post-stabilisation
    (:class:`Stabilisation`)."""
    penalty: Penalty = Penalty()
    """PADMM's penalty: mode, ``rho``, ``eta``, ``rho_free`` (:class:`Penalty`)."""
    warp: WarpSettings = WarpSettings()
    """the Warp backend's Jacobian layout and linear solver (:class:`WarpSettings`)."""

    def projection_shifts(self, dtype) -> tuple[float, float]:
        """The diagonal shifts of post-stabilisation's scaled system ``P D_ff P + diag(s)``: ``s`` on a row with
        PADMM's small shift and on a row with its larger penalty (a saturated effort-limited actuator's
        joint-dynamics row, ``kamino.jax_ref.solver.solve``, "Saturation").

        The shifts are those PADMM's adaptive penalty gives the always-active rows, ``eta + rho_free`` and ``eta +
        rho``, in every dtype (``dtype`` is accepted for symmetry with the other rules and does not change them). A
        shift ``s`` leaves ``s / (sigma + s)`` of the error along a direction of scaled curvature ``sigma``
        (docs/conventions.md, "Post-stabilisation"): the projection holds back where the velocity solve holds back.
        A smaller shift (``sqrt(eps)`` in float64) moves the bodies of a nearly singular loop far along its nearly free
        direction and adds energy (the four-bar with a hinge tilted by 0.1°, at rest under gravity: +2.0 J in 5 s).
        Under the adaptive penalty the Warp backend solves with PADMM's factor. ``stabilisation.projection_shift``
        sets both shifts."""
        shift, pen = self.stabilisation.projection_shift, self.penalty
        if shift is not None:
            return shift, shift
        return pen.eta + pen.rho_free, pen.eta + pen.rho

    def shares_padmm_factor(self, dtype) -> bool:
        """Whether post-stabilisation's default system is PADMM's factor of the always-active rows
        (:meth:`projection_shifts`): under the adaptive penalty, in every dtype."""
        return self.stabilisation.projection_shift is None and self.penalty.mode == "adaptive"

    def replace(self, **changes) -> SolverConfig:
        """A copy with ``changes`` applied; a nested setting goes by its dotted name
        (``cfg.replace(tolerance=1e-4, **{"warp.linear_solver": "cr", "penalty.rho": 0.05})``), a nested class
        whole by its own name (``cfg.replace(penalty=Penalty(mode="fixed"))``). An unknown name raises a
        ``TypeError`` that lists the valid ones (:func:`field_names`)."""
        top: dict = {}
        nested: dict[str, dict] = {}
        for key, value in changes.items():
            group, dot, name = key.partition(".")
            if key not in field_names() and not (not dot and group in NESTED):
                raise TypeError(f"SolverConfig has no setting {key!r}; the settings: {', '.join(field_names())}")
            if dot:
                nested.setdefault(group, {})[name] = value
            else:
                top[key] = value
        for group, fields in nested.items():
            top[group] = dataclasses.replace(top.get(group, getattr(self, group)), **fields)
        return dataclasses.replace(self, **top)

    def __post_init__(self) -> None:
        bad = _rejecter(self, "SolverConfig")
        for name, cls in NESTED.items():
            if not isinstance(getattr(self, name), cls):
                bad(name, f"must be a kamino.{cls.__name__}")
        if not (math.isfinite(self.dt) and self.dt > 0):
            bad("dt", "must be a finite positive time step")
        if self.integrator not in ("euler", "midpoint"):
            bad("integrator", "must be 'euler' or 'midpoint'")
        if int(self.max_iterations) < 1:
            bad("max_iterations", "must be >= 1")
        if not self.tolerance > 0:
            bad("tolerance", "must be > 0")
        if self.reduction not in ("none", "schur"):
            bad("reduction", "must be 'none' or 'schur'")
        if int(self.max_unconverged_steps) != self.max_unconverged_steps or self.max_unconverged_steps < 0:
            bad("max_unconverged_steps", "must be an integer >= 0")
        if not (0.0 <= self.warmstart_scale <= 1.0):
            bad("warmstart_scale", "must lie in [0, 1]")
        if not (math.isfinite(self.contact_margin) and self.contact_margin >= 0):
            bad("contact_margin", "must be a finite number >= 0")


def field_names() -> tuple[str, ...]:
    """Every setting of :class:`SolverConfig` by its path: the top-level fields other than the nested classes, then
    ``stabilisation.baumgarte`` and the other nested ones (what :meth:`SolverConfig.replace` and the command lines'
    ``--solver F=V`` take)."""
    top = tuple(f.name for f in dataclasses.fields(SolverConfig) if f.name not in NESTED)
    return top + tuple(f"{group}.{f.name}" for group, cls in NESTED.items() for f in dataclasses.fields(cls))


def setting_value(text: str):
    """One ``--solver F=V`` value: a Python literal (``1e-2``, ``'schur'``, ``True``), else a JSON one (``false``),
    else a bare word taken as the string it spells (``schur``, ``midpoint``); anything else raises ``ValueError``.
    Every command line that takes ``--solver`` reads its values here."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        pass
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.-]*", text):
        return text
    raise ValueError(f"{text!r} is neither a Python literal nor a bare word")


def solver_settings(items: list[str], flag: str = "--solver") -> dict:
    """``["tolerance=1e-2", "warp.linear_solver=cr"]`` -> SolverConfig settings by their dotted names
    (:meth:`SolverConfig.replace`), the values read by :func:`setting_value`; an unknown name or a malformed item
    raises ``ValueError`` naming ``flag`` and the item."""
    fields = field_names()
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in fields:
            raise ValueError(f"{flag} {item!r}: expected F=V with F one of SolverConfig's settings: "
                             f"{', '.join(fields)}")
        try:
            out[key] = setting_value(value)
        except ValueError as e:
            raise ValueError(f"{flag} {key}: {e}") from None
    return out
