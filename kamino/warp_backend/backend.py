"""The Warp backend behind ``kamino.step(..., backend="warp")`` / ``rollout``: State <-> device buffers.

``State``/``Control`` stay JAX pytrees. A :class:`~kamino.warp_backend.pipeline.Stepper` holds the
device buffers of one (model, config, precision, device); a call copies the State into them, runs
the step (a CUDA graph on the GPU) and returns a new State. On a CUDA device the JAX buffers are
wrapped with ``wp.from_jax`` (no host round trip: one device-to-device copy into the stepper's
persistent buffers, which a captured graph needs) and the results are handed back with
``wp.to_jax`` (zero-copy); on the CPU the arrays go through numpy. docs/warp_backend.md measures
the cost of this boundary.
"""

from __future__ import annotations

import weakref

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp

from kamino.checks import check_control, check_rollout_controls, check_state
from kamino.config import SolverConfig
from kamino.model import Model
from kamino.state import ContactState, Control, State, StepInfo
from kamino.warp_backend.jit import is_traced, traced_step
from kamino.warp_backend.pipeline import Stepper
from kamino.warp_backend.types import types_of

_STEPPERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def default_device() -> wp.context.Device:
    """Warp's preferred device (the first CUDA GPU, else the CPU)."""
    return wp.get_device()


def stepper(model: Model, cfg: SolverConfig, np_dtype, device=None, *, for_jit: bool = False,
            padmm: str | None = None) -> Stepper:
    """The cached :class:`Stepper` of ``model`` for ``cfg``, precision and device (``for_jit``: the one
    called from inside JAX transformations, which launches without its own graph capture; ``padmm``: see
    :class:`Stepper`)."""
    dev = wp.get_device(device)
    key = (cfg, np.dtype(np_dtype), str(dev), for_jit, padmm)
    per_model = _STEPPERS.setdefault(model, {})
    if key not in per_model:
        per_model[key] = st = Stepper(model, cfg, np_dtype, dev, padmm=padmm)
        st.use_graph = st.use_graph and not for_jit
    return per_model[key]


def _jax_device() -> str:
    """The Warp device of JAX's default backend (where traced arrays will live)."""
    return "cuda:0" if jax.default_backend() == "gpu" else "cpu"


def _on_gpu(x: jax.Array) -> bool:
    try:
        return any(d.platform == "gpu" for d in x.devices())
    except AttributeError:  # a numpy array
        return False


def _np_dtype(arr: wp.array) -> np.dtype:
    dtype = arr.dtype
    return np.dtype(wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype)))


def _write(dst: wp.array, src, device, keep: list) -> None:
    """Copy a JAX/numpy array into the device buffer ``dst`` (``wp.from_jax`` on the GPU: no host copy).

    On the GPU the copy is only enqueued on Warp's stream, behind whatever that stream still runs (a replayed
    step of another stepper, say). The JAX buffer it reads, often a temporary made here by a dtype
    conversion, is appended to ``keep``: the caller holds it until it has synchronised, so that JAX cannot
    free and reuse the buffer before the copy has read it."""
    if dst.size == 0:
        return
    if device.is_cuda and isinstance(src, jax.Array) and _on_gpu(src):
        # JAX computes on its own stream: wait for the buffer before Warp's stream reads it
        buf = jax.block_until_ready(src.astype(_np_dtype(dst)))
        keep.append(buf)
        wp.copy(dst, wp.from_jax(buf, dtype=dst.dtype))
    else:
        a = np.asarray(src, dtype=_np_dtype(dst))
        dst.assign(a.reshape(dst.shape[0], -1) if a.ndim > 1 else a)


def _read(src: wp.array, shape, dtype=None) -> jax.Array:
    """A new JAX array holding ``src`` (``wp.to_jax`` of a device copy on the GPU)."""
    if src.size == 0:
        return jnp.zeros(shape, dtype if dtype is not None else _np_dtype(src))
    if src.device.is_cuda:
        out = wp.clone(src)
        wp.synchronize_device(src.device)
        return wp.to_jax(out).reshape(shape)
    return jnp.asarray(src.numpy().reshape(shape))


def load_state(st: Stepper, state: State, control: Control | None) -> None:
    """Copy ``state`` and ``control`` into the stepper's buffers (zeros for absent controls)."""
    w, dev = st.work, st.device
    keep: list = []  # the JAX buffers the enqueued copies read (see _write)
    for dst, src in ((w.q, state.body_q), (w.u, state.body_u), (w.time, state.time),
                     (w.kin_force, state.constraint_force), (w.cpl_force, state.coupling_force),
                     (w.act_force, state.actuator_force), (w.pas_force, state.passive_force),
                     (w.lim_force, state.limit_force)):
        _write(dst, src, dev, keep)
    c = state.contacts
    for dst, src in ((w.con_pair, c.pair), (w.con_pos, c.pos), (w.con_normal, c.normal), (w.con_dist, c.dist),
                     (w.con_force, c.force), (w.con_velocity, c.velocity), (w.con_point_b, c.point_b)):
        _write(dst, src, dev, keep)
    load_control(st, control, keep)


def load_control(st: Stepper, control: Control | None, keep: list | None = None) -> None:
    """Copy ``control`` into the stepper's buffers (zeros for absent fields); on the GPU, wait for the copies
    before the JAX buffers they read (``keep``, and the temporaries made here) may be freed."""
    w, dev = st.work, st.device
    keep = [] if keep is None else keep
    for name, dst in (("dof_effort", w.effort), ("body_wrench", w.wrench), ("position_target", w.position_target),
                      ("velocity_target", w.velocity_target)):
        value = None if control is None else getattr(control, name)
        if value is None:
            dst.zero_()
        else:
            _write(dst, jnp.asarray(value, st.np_dtype), dev, keep)
    if dev.is_cuda:
        # The copies were only enqueued, possibly behind a step of another stepper still running on Warp's
        # stream. Under jax_enable_x64 the float64 controls are converted to temporaries that JAX would free
        # and reuse before such a queued copy reads them: this was the captured-vs-uncaptured test failure
        # (docs/warp_backend.md). Wait here, then let the buffers go.
        wp.synchronize_device(dev)
    keep.clear()


def read_state(st: Stepper, int_dtype=jnp.int32) -> State:
    """A new :class:`State` from the stepper's buffers (after a step)."""
    w, m = st.work, st.wm.model
    if st.device.is_cuda:
        # the copies handed to JAX are made on Warp's stream; JAX must not read them earlier
        wp.synchronize_device(st.device)
    B, cap = m.num_bodies, m.num_contacts
    info_found = _read(w.ct_found, (m.num_worlds,))
    num_contacts = _read(w.n_con, (m.num_worlds,))
    return State(
        body_q=_read(w.q, (B, 7)),
        body_u=_read(w.u, (B, 6)),
        time=_read(w.time, (m.num_worlds,)),
        constraint_force=_read(w.kin_force, (m.num_constraints,)),
        actuator_force=_read(w.act_force, (m.num_dofs,)),
        passive_force=_read(w.pas_force, (m.num_dofs,)),
        limit_force=_read(w.lim_force, (m.num_dofs,)),
        coupling_force=_read(w.cpl_force, (m.num_couplings,)),
        contacts=ContactState(
            pair=_read(w.con_pair, (cap,), jnp.int32),
            pos=_read(w.con_pos, (cap, 3)),
            normal=_read(w.con_normal, (cap, 3)),
            dist=_read(w.con_dist, (cap,)),
            force=_read(w.con_force, (cap, 3)),
            velocity=_read(w.con_velocity, (cap, 3)),
            point_b=_read(w.con_point_b, (cap, 3)),
        ),
        info=StepInfo(
            iterations=_read(w.iters, (m.num_worlds,)),
            primal_residual=_read(w.r_p, (m.num_worlds,)),
            dual_residual=_read(w.r_d, (m.num_worlds,)),
            complementarity_residual=_read(w.r_c, (m.num_worlds,)),
            converged=_read(w.converged, (m.num_worlds,)) != 0,
            failed=_read(w.failed, (m.num_worlds,)) != 0,
            num_contacts=num_contacts,
            contact_overflow=jnp.maximum(info_found - num_contacts, 0).astype(int_dtype),
        ),
    )


def _dtype_of(state: State):
    dt = np.dtype(state.body_q.dtype)
    types_of(dt)  # raises for unsupported precisions
    return dt


def step(model: Model, state: State, control: Control | None, cfg: SolverConfig) -> State:
    check_state(model, state)
    check_control(model, control)
    if is_traced(state) or any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(control)):
        st = stepper(model, cfg, _dtype_of(state), _jax_device(), for_jit=True)
        return traced_step(st, model, state, control)
    st = stepper(model, cfg, _dtype_of(state))
    load_state(st, state, control)
    st.run(1)
    return read_state(st)


def rollout(model: Model, state: State, controls: Control | None, num_steps: int | None,
            cfg: SolverConfig) -> State:
    check_state(model, state)
    num_steps = check_rollout_controls(model, controls, num_steps)
    if is_traced(state) or any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(controls)):
        def body(s, c):
            s2 = step(model, s, c, cfg)
            return s2, s2

        _, traj = jax.lax.scan(body, state, controls, length=num_steps)
        return traj
    st = stepper(model, cfg, _dtype_of(state))
    load_state(st, state, None)
    traj = []
    for t in range(num_steps):
        if controls is not None:
            load_control(st, jax.tree_util.tree_map(lambda x, t=t: x[t], controls))
        st.run(1)
        traj.append(read_state(st))
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *traj)
