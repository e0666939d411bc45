"""The Warp backend behind ``kamino.Simulator(..., backend="warp")``: State <-> device buffers.

``State``/``Control`` stay JAX pytrees. A :class:`~kamino.warp_backend.pipeline.Stepper` holds the
device buffers of one (model, config, precision, device); a call copies the State into them, runs
the step (a CUDA graph on the GPU) and returns a new State. On a CUDA device the JAX buffers are
wrapped with ``wp.from_jax`` (no host round trip: one device-to-device copy into the stepper's
persistent buffers, which a captured graph needs) and the results are handed back with
``wp.to_jax`` (zero-copy); on the CPU the arrays go through numpy. docs/warp_backend.md measures
the cost of this boundary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp
from tqdm import tqdm

from kamino.config import SolverConfig
from kamino.model import Model, replicate
from kamino.state import ContactState, Control, State, StepInfo
from kamino.warp_backend.jit import batchable_step, is_traced
from kamino.warp_backend.model_data import warp_model
from kamino.warp_backend.parameters import WorldParameters, private_parameters
from kamino.warp_backend.pipeline import CUDA_STREAM_LOCK, Stepper
from kamino.warp_backend.types import types_of

#: an eager rollout of at least this many steps shows a progress bar (tqdm, on stderr, cleared at the end);
#: shorter ones print nothing. Set it to ``float("inf")`` for none.
PROGRESS_MIN_STEPS = 1000


def default_device() -> wp.context.Device:
    """Warp's preferred device (the first CUDA GPU, else the CPU)."""
    return wp.get_device()


class Engine:
    """The Warp backend stepping one model with one configuration (what ``kamino.Simulator(..., backend="warp")``
    holds). It builds on first use, and frees with itself:

    - a device model per (precision, device) (:func:`~kamino.warp_backend.model_data.warp_model`);
    - a :class:`Stepper` per (precision, device, traced or eager): device buffers, loaded kernels, CUDA graphs;
    - the traced step that ``jax.jit`` / ``vmap`` call (:func:`~kamino.warp_backend.jit.batchable_step`), and the
      engines of the replicated models a ``vmap`` of ``B`` states steps as one.

    An eager step or rollout holds the engine's lock from loading the state to reading the result: the steppers'
    buffers are the engine's, so two threads sharing one engine take turns. ``padmm`` picks the PADMM schedule
    (:class:`Stepper`; ``None``: by device and size)."""

    def __init__(self, model: Model, cfg: SolverConfig, padmm: str | None = None) -> None:
        self.model, self.cfg, self.padmm = model, cfg, padmm
        self._models: dict = {}
        self._steppers: dict = {}
        self._traced: dict = {}
        self._replicas: dict[int, Engine] = {}
        self._reference = None
        self._lock = threading.RLock()

    def __del__(self, _lock=CUDA_STREAM_LOCK) -> None:
        """Free the device models and steppers while holding :data:`~kamino.warp_backend.pipeline.CUDA_STREAM_LOCK`
        (:meth:`Stepper.__del__` says why, and why the lock is bound at definition)."""
        with _lock:
            self.__dict__.clear()

    def stepper(self, np_dtype, device=None, *, for_jit: bool = False, parameters: bool = False) -> Stepper:
        """The :class:`Stepper` in ``np_dtype`` on ``device`` (Warp's preferred one by default); ``for_jit``: the one
        called from inside JAX transformations, which launches without its own graph capture; ``parameters``: the
        one whose traced calls take per-world parameters (:mod:`kamino.warp_backend.parameters`): it owns its
        parameter arrays, the rest of the device model is shared."""
        dev = wp.get_device(device)
        key = (np.dtype(np_dtype), str(dev), for_jit, parameters)
        with self._lock, CUDA_STREAM_LOCK:  # uploads go through Warp's stream (CUDA_STREAM_LOCK says why)
            if key not in self._steppers:
                wm_key = key[:2]
                if wm_key not in self._models:
                    self._models[wm_key] = warp_model(self.model, *wm_key)
                wm = private_parameters(self._models[wm_key]) if parameters else self._models[wm_key]
                st = Stepper(self.model, self.cfg, np_dtype, dev, padmm=self.padmm, wm=wm)
                st.use_graph = st.use_graph and not for_jit
                self._steppers[key] = st
            return self._steppers[key]

    def replica(self, copies: int) -> Engine:
        """The engine of ``kamino.replicate(model, copies)`` with this configuration (a ``vmap`` over ``copies``
        states steps them as that model's worlds)."""
        with self._lock:
            if copies not in self._replicas:
                self._replicas[copies] = Engine(replicate(self.model, copies), self.cfg, self.padmm)
            return self._replicas[copies]

    def compile_in_background(self, num_worlds: int, np_dtype) -> threading.Thread:
        """Start building and compiling, in a daemon thread, the stepper that a ``jax.vmap`` over ``num_worlds``
        traced states in ``np_dtype`` calls (``replica(num_worlds)``'s, on the device where JAX's traced arrays
        live: :func:`~kamino.warp_backend.jit.batchable_step`), and return the thread. Warp's compiler runs outside
        Python's lock, so the modules compile while the caller goes on (building an environment's reset bank,
        tracing and compiling the XLA program around the step); the traced step then finds its stepper built and
        compiled, or waits for it (:meth:`~kamino.warp_backend.pipeline.Stepper.precompile`). An error in the thread
        is not lost: the traced step builds and compiles the stepper again in its own thread, and raises there.

        On a GPU the caller's thread acquires Warp's CUDA context before the worker starts, and the worker runs
        under it (``wp.ScopedDevice``): a worker that acquires the context lazily itself leaves the traced step's
        graph capture unregistered on the device that ``wp.capture_while`` reads, and the capture fails."""
        if isinstance(num_worlds, bool) or not isinstance(num_worlds, (int, np.integer)) or num_worlds < 1:
            raise ValueError(f"compile_in_background: num_worlds must be an integer >= 1, got {num_worlds!r}")
        device = wp.get_device(_jax_device())
        if device.is_cuda:
            _ = device.context  # acquired on the caller's thread (the docstring says why)

        def work() -> None:
            # an error is repeated, and raised, by the traced step (the docstring)
            with contextlib.suppress(Exception), wp.ScopedDevice(device):
                self.replica(int(num_worlds)).stepper(np_dtype, device, for_jit=True).precompile()

        thread = threading.Thread(target=work, name=f"kamino-compile-{num_worlds}", daemon=True)
        thread.start()
        return thread

    def reference(self):
        """The JAX reference's engine (``kamino.jax_ref.backend.Engine``) of this model and configuration, built once,
        with ``fixed_iterations`` off: the traced step's derivative is its implicit one at this backend's solution
        (:func:`~kamino.warp_backend.jit.batchable_step`)."""
        with self._lock:
            if self._reference is None:
                from kamino.jax_ref.backend import Engine as Reference

                self._reference = Reference(self.model, self.cfg.replace(fixed_iterations=False))
            return self._reference

    def traced_step(self, np_dtype):
        """The step called with traced arrays (inside ``jax.jit``, ``lax.scan``, ``vmap``), built once per
        precision."""
        dtype = np.dtype(np_dtype)
        with self._lock:
            if dtype not in self._traced:
                self._traced[dtype] = batchable_step(self, dtype, _jax_device())
            return self._traced[dtype]

    def step(self, state: State, control: Control | None, parameters: WorldParameters | None = None) -> State:
        """One step; ``parameters`` (per-world masses, gains, friction, gravity..., possibly traced:
        :class:`~kamino.warp_backend.parameters.WorldParameters`) in place of the model's own goes through the
        traced step (the JAX FFI call) whether or not the arrays are traced."""
        if parameters is not None or is_traced(state, control):
            return self.traced_step(_dtype_of(state))(state, control, parameters)
        with self._lock:
            st = self.stepper(_dtype_of(state))
            with _driving(st):
                load_state(st, state, control)
                st.run(1)
                return read_state(st)

    def rollout(self, state: State, controls: Control | None, num_steps: int) -> State:
        if is_traced(state, controls):
            def body(s, c):
                s2 = self.step(s, c)
                return s2, s2

            return jax.lax.scan(body, state, controls, length=num_steps)[1]
        with self._lock, _driving(self.stepper(_dtype_of(state))) as st:
            load_state(st, state, None)
            traj = _Trajectory(st, num_steps)
            for t in tqdm(range(num_steps), desc="kamino rollout (warp)", unit="step", leave=False, mininterval=0.5,
                          dynamic_ncols=True, file=sys.stderr, disable=num_steps < PROGRESS_MIN_STEPS):
                if controls is not None:
                    load_control(st, jax.tree_util.tree_map(lambda x, t=t: x[t], controls))
                st.run(1)
                traj.record(t)
            result = traj.result()
            del traj  # its Warp buffers go while this thread drives the stream (CUDA_STREAM_LOCK)
            return result


@contextlib.contextmanager
def _driving(st: Stepper):
    """``st``, with Warp's stream of its device held for this thread on a CUDA device
    (:data:`~kamino.warp_backend.pipeline.CUDA_STREAM_LOCK`)."""
    if not st.device.is_cuda:
        yield st
        return
    with CUDA_STREAM_LOCK:
        yield st


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
    """A new JAX array holding ``src`` (on the GPU a copy JAX makes from ``wp.to_jax`` and owns).

    Always a copy: the stepper reuses ``src`` on its next step, and a JAX array that aliased it would change under
    the caller's feet. On the GPU the copy's memory is JAX's, not Warp's: a JAX array holding Warp's memory frees it
    through Warp when it goes, in whatever thread, and a free on Warp's stream while another thread captures a graph
    on it breaks that capture. On the CPU ``jnp.asarray`` of a numpy view may alias it (jaxlib 0.9 does, for aligned
    buffers): a state returned by one step then took the values of a later step of another state
    (tests/test_world_health.py, the frozen world)."""
    if src.size == 0:
        return jnp.zeros(shape, dtype if dtype is not None else _np_dtype(src))
    if src.device.is_cuda:
        wp.synchronize_device(src.device)  # the step has written src
        return _owned(wp.to_jax(src)).reshape(shape)
    return jnp.asarray(np.array(src.numpy().reshape(shape), copy=True))


def _owned(view: jax.Array) -> jax.Array:
    """A JAX-owned copy of ``view`` (a JAX array on Warp's memory), finished before the caller goes on: the next step
    overwrites the memory it reads."""
    return jnp.array(view, copy=True).block_until_ready()


def load_state(st: Stepper, state: State, control: Control | None) -> None:
    """Copy ``state`` and ``control`` into the stepper's buffers (zeros for absent controls)."""
    w, dev = st.work, st.device
    keep: list = []  # the JAX buffers the enqueued copies read (see _write)
    for dst, src in ((w.q, state.body_q), (w.u, state.body_u), (w.time, state.time),
                     (w.kin_force, state.constraint_force), (w.cpl_force, state.coupling_force),
                     (w.act_force, state.actuator_force), (w.pas_force, state.passive_force),
                     (w.lim_force, state.limit_force), (w.rho_u, state.info.penalty),
                     (w.unconverged, state.info.unconverged_steps), (w.frozen, state.info.failed)):
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


def state_fields(st: Stepper) -> dict[str, tuple[wp.array, tuple[int, ...], np.dtype]]:
    """The stepper buffers a :class:`State` is read from: field name -> (buffer, per-step shape, dtype). The
    contact fields carry their :class:`ContactState` names; ``found`` (contacts the narrow phase found, kept or
    not) only feeds ``contact_overflow``. One table for :func:`read_state` and :class:`_Trajectory`."""
    w, m = st.work, st.wm.model
    W, B, cap = m.num_worlds, m.num_bodies, m.num_contacts
    table = (
        ("body_q", w.q, (B, 7), None), ("body_u", w.u, (B, 6), None), ("time", w.time, (W,), None),
        ("constraint_force", w.kin_force, (m.num_constraints,), None),
        ("actuator_force", w.act_force, (m.num_dofs,), None), ("passive_force", w.pas_force, (m.num_dofs,), None),
        ("limit_force", w.lim_force, (m.num_dofs,), None), ("coupling_force", w.cpl_force, (m.num_couplings,), None),
        ("pair", w.con_pair, (cap,), np.int32), ("pos", w.con_pos, (cap, 3), None),
        ("normal", w.con_normal, (cap, 3), None), ("dist", w.con_dist, (cap,), None),
        ("force", w.con_force, (cap, 3), None), ("velocity", w.con_velocity, (cap, 3), None),
        ("point_b", w.con_point_b, (cap, 3), None),
        ("iterations", w.iters, (W,), None), ("primal_residual", w.r_p, (W,), None),
        ("dual_residual", w.r_d, (W,), None), ("complementarity_residual", w.r_c, (W,), None),
        ("converged", w.converged, (W,), None), ("failed", w.failed, (W,), None),
        ("num_contacts", w.n_con, (W,), None), ("found", w.ct_found, (W,), None),
        ("penalty", w.rho_u, (W,), None), ("unconverged_steps", w.unconverged, (W,), None),
    )
    return {name: (src, shape, np.dtype(dtype) if dtype is not None else _np_dtype(src))
            for name, src, shape, dtype in table}


_CONTACT_FIELDS = ("pair", "pos", "normal", "dist", "force", "velocity", "point_b")
_FLAGS = ("converged", "failed", "contact_overflow")
_DERIVED = ("converged", "failed", "found")


def _assemble(get, flags: dict[str, jax.Array]) -> State:
    """A :class:`State` from ``get(name)`` (a JAX array per :func:`state_fields` entry, read as is) and the
    derived ``flags`` (``converged``, ``failed``: bool; ``contact_overflow``: int32)."""
    info = {f.name: flags[f.name] if f.name in _FLAGS else get(f.name) for f in dataclasses.fields(StepInfo)}
    top = {f.name: get(f.name) for f in dataclasses.fields(State) if f.name not in ("contacts", "info")}
    return State(**top, contacts=ContactState(**{k: get(k) for k in _CONTACT_FIELDS}), info=StepInfo(**info))


def read_state(st: Stepper) -> State:
    """A new :class:`State` from the stepper's buffers (after a step)."""
    if st.device.is_cuda:
        # the copies handed to JAX are made on Warp's stream; JAX must not read them earlier
        wp.synchronize_device(st.device)
    fields = state_fields(st)
    host = {k: np.asarray(fields[k][0].numpy()) if fields[k][0].size else np.zeros(fields[k][1], fields[k][2])
            for k in (*_DERIVED, "num_contacts")}
    return _assemble(lambda k: _read(*fields[k]), _flags(host))


def _flags(host: dict[str, np.ndarray]) -> dict[str, jax.Array]:
    """The derived flags, computed on the host from the raw ``converged``/``failed`` counters and the contact
    counts (``jax.device_put``: no XLA operation to compile)."""
    overflow = np.maximum(host["found"] - host["num_contacts"], 0).astype(np.int32)
    return {"converged": jax.device_put(host["converged"] != 0), "failed": jax.device_put(host["failed"] != 0),
            "contact_overflow": jax.device_put(overflow)}


def _dtype_of(state: State):
    dt = np.dtype(state.body_q.dtype)
    types_of(dt)  # raises for unsupported precisions
    return dt


class _Trajectory:
    """The trajectory of an eager rollout (docs/warp_backend.md, "JAX interop"), written step by step into
    buffers ``[num_steps, ...]`` allocated once: numpy arrays on the CPU; on a CUDA device Warp arrays filled
    by device-to-device copies (``wp.copy`` at an offset, on Warp's stream behind the step: no host round
    trip per step). They become JAX arrays once, at the end (``jax.device_put`` / ``wp.to_jax``).

    It reads the stepper buffers :func:`read_state` reads, into the same State fields, shapes and dtypes,
    without any XLA operation whose shapes depend on ``num_steps``: such an operation is compiled again for
    every new length (the former ``jnp.stack`` of one State per step was an XLA concatenate with
    ``num_steps`` operands, compiled in time superlinear in the length;
    tests/test_cross_backend.py::test_eager_warp_rollout_length_compiles_nothing).
    """

    def __init__(self, st: Stepper, num_steps: int) -> None:
        self.num_steps, self.device, self.cuda = int(num_steps), st.device, st.device.is_cuda
        self.fields = state_fields(st)
        self.bufs: dict[str, wp.array | np.ndarray] = {}
        for name, (src, shape, _) in self.fields.items():
            if src.size == 0 or self.num_steps == 0:
                continue  # read as zeros in result()
            if self.cuda:
                self.bufs[name] = wp.empty(self.num_steps * src.size, dtype=src.dtype, device=src.device)
            else:
                self.bufs[name] = np.empty((self.num_steps, *shape), _np_dtype(src))

    def record(self, t: int) -> None:
        """Write the stepper's current State (after step ``t``) into row ``t`` of the buffers."""
        for name, buf in self.bufs.items():
            src = self.fields[name][0]
            if self.cuda:
                wp.copy(buf, src, dest_offset=t * src.size, count=src.size)
            else:
                buf[t] = src.numpy().reshape(buf.shape[1:])

    def _host(self, name: str) -> np.ndarray:
        """Field ``name`` as a host array ``[num_steps, ...]`` (zeros where the stepper buffer is empty)."""
        src, shape, dtype = self.fields[name]
        buf = self.bufs.get(name)
        if buf is None:
            return np.zeros((self.num_steps, *shape), dtype)
        return buf.numpy().reshape((self.num_steps, *shape)) if self.cuda else buf

    def _jax(self, name: str) -> jax.Array:
        """Field ``name`` as a JAX array ``[num_steps, ...]``: a JAX-owned copy of the Warp buffer on a CUDA device
        (:func:`_owned`: device to device), else ``jax.device_put`` (which, unlike ``jnp.asarray``, compiles
        nothing)."""
        src, shape, _ = self.fields[name]
        buf = self.bufs.get(name)
        if self.cuda and buf is not None:
            scalar = getattr(src.dtype, "_wp_scalar_type_", src.dtype)
            return _owned(wp.to_jax(buf.view(scalar).reshape((self.num_steps, *shape))))
        return jax.device_put(self._host(name))

    def result(self) -> State:
        """The trajectory: a :class:`State` whose arrays have a leading time axis (as :func:`read_state`)."""
        if self.cuda:
            # the copies were enqueued on Warp's stream: JAX must not read the buffers earlier
            wp.synchronize_device(self.device)
        return _assemble(self._jax, _flags({k: self._host(k) for k in (*_DERIVED, "num_contacts")}))
