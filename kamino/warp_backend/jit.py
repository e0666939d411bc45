"""The Warp step as a JAX primitive: ``kamino.step(..., backend="warp")`` inside ``jax.jit``.

When the State holds traced arrays (inside ``jax.jit``, ``lax.scan``, ...), the Warp backend calls
its step through Warp's JAX FFI (``wp.jax_callable``): XLA allocates the output buffers, Warp reads
and writes them in place (no host round trip), and the step's kernels are launched on XLA's stream.
The callable copies the inputs into the stepper's persistent buffers and the results out of them
(device-to-device, ~35 small copies per call; docs/warp_backend.md "JAX interop"). XLA does not capture
the call (``JaxCallableGraphMode.NONE``). On a GPU the call replays the step's own CUDA graph, captured when
the callable is built, so that its PADMM loop is a ``wp.capture_while``; on the CPU the PADMM loop runs each
world to its end, or to its next switch, in one launch. No host synchronisation either way.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import warp as wp

from kamino.model import Model
from kamino.state import ContactState, Control, State, StepInfo
from kamino.warp_backend.parameters import FIELDS as PARAMETER_FIELDS
from kamino.warp_backend.parameters import WorldParameters, load_parameters, shapes
from kamino.warp_backend.pipeline import Stepper
from kamino.warp_backend.types import types_of

# (State/Control field path, Work buffer, kind) of every input; kind picks the Warp dtype
_INPUTS = (
    ("body_q", "q", "transform"), ("body_u", "u", "vec6"), ("time", "time", "scalar"),
    ("constraint_force", "kin_force", "scalar"), ("coupling_force", "cpl_force", "scalar"),
    ("actuator_force", "act_force", "scalar"), ("passive_force", "pas_force", "scalar"),
    ("limit_force", "lim_force", "scalar"), ("contacts.pair", "con_pair", "int"),
    ("contacts.pos", "con_pos", "vec3"), ("contacts.normal", "con_normal", "vec3"),
    ("contacts.dist", "con_dist", "scalar"), ("contacts.force", "con_force", "vec3"),
    ("contacts.velocity", "con_velocity", "vec3"), ("contacts.point_b", "con_point_b", "vec3"),
    ("control.dof_effort", "effort", "scalar"), ("control.position_target", "position_target", "scalar"),
    ("control.velocity_target", "velocity_target", "scalar"), ("control.body_wrench", "wrench", "vec6"),
    ("info.penalty", "rho_u", "scalar"), ("info.unconverged_steps", "unconverged", "int"),
    ("info.failed", "frozen", "int"),
)
_STATE_OUTPUTS = _INPUTS[:15]
_INFO_OUTPUTS = (("iterations", "iters", "int"), ("primal_residual", "r_p", "scalar"),
                 ("dual_residual", "r_d", "scalar"), ("complementarity_residual", "r_c", "scalar"),
                 ("converged", "converged", "int"), ("failed", "failed", "int"), ("num_contacts", "n_con", "int"),
                 ("found", "ct_found", "int"), ("penalty", "rho_u", "scalar"),
                 ("unconverged_steps", "unconverged", "int"))


def is_traced(*trees) -> bool:
    """Whether any array of ``trees`` (a State, a Control, ...) is a JAX tracer (we are inside a JAX
    transformation: ``jit``, ``vmap``, ``grad``, ...)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def _warp_dtype(T, kind):
    return {"transform": T.transform, "vec6": T.vec6, "vec3": T.vec3, "scalar": T.scalar, "int": wp.int32,
            "mat33": T.mat33}[kind]


def _callable(st: Stepper, stepper_on: Callable, parameters: bool = False):
    """The ``wp.jax_callable`` of one stepper (built once, kept on the stepper), with the non-empty fields as
    arguments; with ``parameters``, the non-empty :class:`~kamino.warp_backend.parameters.WorldParameters` fields
    follow the state's and control's, and the call writes them into the stepper's model arrays before the step
    (:func:`~kamino.warp_backend.parameters.load_parameters`; such a stepper owns those arrays, and a stepper makes
    one kind of call). ``stepper_on(device)`` is the stepper of the same model, configuration, precision and kind
    on the device XLA runs the call on: under ``pmap`` or ``shard_map`` over several GPUs every device has its own
    (buffers, kernels loaded there). Warp runs the callbacks one at a time (its FFI lock), so the forced host devices
    of a CPU, which all map to Warp's one CPU device, share its stepper safely."""
    if st.ffi is not None:
        return st.ffi
    T = types_of(st.np_dtype)
    w = st.work
    ins = [f for f in _INPUTS if getattr(w, f[1]).size]
    prm = [f for f in PARAMETER_FIELDS if getattr(st.wm.arrays, f[1]).size] if parameters else []
    outs = [("out_" + f[0].replace(".", "_"), f[1], f[2]) for f in _STATE_OUTPUTS + _INFO_OUTPUTS
            if getattr(w, f[1]).size]
    names = [f[0].replace(".", "_") for f in ins] + ["param_" + f[0] for f in prm] + [f[0] for f in outs]
    types = {n: wp.array(dtype=_warp_dtype(T, f[2])) for n, f in zip(names, ins + prm + outs, strict=True)}
    n_in = len(ins) + len(prm)

    def body(arrays):
        s = st if arrays[0].device == st.device else stepper_on(arrays[0].device)
        for arr, (_, buf, _) in zip(arrays[:len(ins)], ins, strict=True):
            wp.copy(getattr(s.work, buf), arr)
        if prm:
            given = {f[0]: arr for arr, f in zip(arrays[len(ins):n_in], prm, strict=True)}
            load_parameters(s.wm.arrays, s.np_dtype, s.device, given)
        graph = s.captured(1)
        if graph is not None:  # the step's graph, captured below; it replays on XLA's stream
            wp.capture_launch(graph)
        else:
            s.launch_step()
        for arr, (_, buf, _) in zip(arrays[n_in:], outs, strict=True):
            wp.copy(arr, getattr(s.work, buf))

    src = f"def kamino_warp_step({', '.join(names)}):\n    _body([{', '.join(names)}])\n"
    ns = {"_body": body}
    exec(src, ns)  # a signature with one annotated argument per field (what jax_callable reads)
    fn = ns["kamino_warp_step"]
    fn.__annotations__ = types
    fn.__module__ = __name__
    # load (compile) every kernel before the first traced call; on a GPU capture the step as a CUDA graph here, at
    # trace time, outside XLA's execution: the callback replays it, so its PADMM loop is the graph's capture_while
    # (every world advances in chunks, a switch's refactorisation after each chunk) instead of one launch per
    # possible switch, each as long as its slowest world (benchmarks/README.md, PPO's collection on the GPU). A stepper
    # first used inside a call (another device under pmap) launches without a graph.
    if st.device.is_cuda:
        st.graph(1)
    else:
        st.launch_step()
    call = wp.jax_callable(fn, num_outputs=len(outs), graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method=None)
    st.ffi = (call, ins, prm, outs)
    return st.ffi


def batchable_step(engine, np_dtype, device: str):
    """The traced step of ``engine`` (a :class:`~kamino.warp_backend.backend.Engine`: one model and configuration)
    in ``np_dtype`` as a function ``(state, control, parameters=None) -> State`` that ``jax.vmap`` batches; its
    stepper lives on the Warp device ``device`` (where JAX's traced arrays live). ``parameters``
    (:class:`~kamino.warp_backend.parameters.WorldParameters`, possibly traced) replaces the model's masses,
    inertias, friction, gains, armature, damping, effort limits and gravity for this call; ``None`` steps the
    model's own (no parameter copies). The two kinds of call use two steppers: the one reading its caller's
    parameters owns its parameter arrays (:func:`~kamino.warp_backend.parameters.private_parameters`).

    The FFI call itself has no batching rule (``vmap_method=None``). The rule here (``jax.custom_batching``) uses
    the storage layout instead: arrays are world after world (docs/conventions.md, "Data layout"), so a batch of
    ``B`` states of the model is, flattened, the state of ``kamino.replicate(model, B)``. The rule reshapes every
    ``[B, n, ...]`` array to ``[B * n, ...]`` (the parameters too: ``gravity`` is ``[num_worlds, 3]``, so a batch of
    environments gives each replica world its own), makes one call for all ``B * N`` worlds with the replica's engine
    (``engine.replica(B)``) and reshapes back; an unbatched array (a parameter the randomization leaves alone) is
    broadcast first. Nested ``vmap`` recurses through the replica's own function.

    Derivatives (``jax.jvp``, ``jax.grad``; docs/formulation.md §7.10, "The Warp backend's derivative"): the step is a
    ``jax.custom_jvp`` whose value is the Warp step's and whose tangent is the JAX reference's implicit one at the
    Warp solution: the reference's step (``engine.reference()``, the same model and configuration) linearised at the
    same inputs, with its solves warm-started from this step's output (:func:`kamino.jax_ref.backend.tangent_at`), so
    that its PADMM starts at the Warp solution and stops within ``tolerance`` of it, in a few iterations. Reverse mode
    transposes that linear map (the reference's tangent solve is a matrix product). The ``custom_jvp`` wraps the
    ``custom_vmap``: under ``vmap`` of ``jvp`` or ``jvp`` of ``vmap`` the value is one batched Warp call and the
    tangent the reference's step vmapped over the batch. Integer and boolean inputs and outputs have ``float0``
    tangents."""
    model = engine.model

    def stepper_on(parameters: bool):
        return lambda dev: engine.stepper(np_dtype, dev, for_jit=True, parameters=parameters)

    @jax.custom_jvp
    def step(state: State, control: Control | None, parameters: WorldParameters | None = None) -> State:
        return batched(state, control, parameters)

    @step.defjvp
    def reference_tangent(primals, tangents):
        from kamino.jax_ref.backend import tangent_at  # the JAX reference is imported on first use

        out = batched(*primals)
        return out, tangent_at(engine.reference(), out, primals, tangents)

    @jax.custom_batching.custom_vmap
    def batched(state: State, control: Control | None, parameters: WorldParameters | None) -> State:
        on = stepper_on(parameters is not None)
        return traced_step(on(device), on, model, state, control, parameters)

    @batched.def_vmap
    def rule(axis_size: int, in_batched, state: State, control: Control | None,
             parameters: WorldParameters | None):
        def lift(x, batched):
            return x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        state = jax.tree.map(lift, state, in_batched[0])
        control = jax.tree.map(lift, control, in_batched[1])
        parameters = jax.tree.map(lift, parameters, in_batched[2])
        merge = lambda x: x.reshape((axis_size * x.shape[1], *x.shape[2:]))  # noqa: E731
        big = engine.replica(axis_size).traced_step(np_dtype)
        out = big(jax.tree.map(merge, state), jax.tree.map(merge, control), jax.tree.map(merge, parameters))
        split = lambda x: x.reshape((axis_size, x.shape[0] // axis_size, *x.shape[1:]))  # noqa: E731
        out = jax.tree.map(split, out)
        return out, jax.tree.map(lambda _: True, out)

    return step


def traced_step(st: Stepper, stepper_on: Callable, model: Model, state: State, control: Control | None,
                parameters: WorldParameters | None = None) -> State:
    """One step with traced inputs, through the Warp FFI (``stepper_on``: :func:`_callable`); ``parameters``
    (``None``: the model's own) must have the shapes of :func:`kamino.warp_backend.parameters.shapes`."""
    call, ins, prm, outs = _callable(st, stepper_on, parameters is not None)
    dtype = jnp.dtype(st.np_dtype)
    args = []
    for path, buf, _ in ins:
        if path.startswith("control."):
            value = None if control is None else getattr(control, path[8:])
            shape = (model.num_bodies, 6) if path.endswith("body_wrench") else (model.num_dofs,)
            args.append(jnp.zeros(shape, dtype) if value is None else jnp.asarray(value, dtype).reshape(shape))
        elif path.startswith("contacts."):
            args.append(getattr(state.contacts, path[9:]))
        elif path.startswith("info."):
            value = getattr(state.info, path[5:])
            args.append(value.astype(jnp.int32) if value.dtype == jnp.bool_ else value)
        else:
            args.append(getattr(state, path))
    if prm:
        want = shapes(model.num_bodies, model.num_geoms, model.num_dofs, model.num_worlds)
        for field, _, _ in prm:
            value = getattr(parameters, field)
            got = None if value is None else jnp.shape(value)
            if got != want[field]:
                raise ValueError(f"Warp step: parameters.{field} has shape {got}, expected "
                                 f"{want[field]} (kamino.warp_backend.parameters.WorldParameters)")
            args.append(jnp.asarray(value, dtype))
    dims = {name: getattr(st.work, buf).shape for name, buf, _ in outs}
    # the barrier keeps XLA's GPU compiler from fusing the call into a consumer it also feeds: a ``lax.scan`` that
    # both carries the step's state and stacks it (``rollout``) otherwise runs the call twice per iteration
    # (jax 0.11.2, dynamic-slice fusion; docs/warp_backend.md "JAX interop")
    results = dict(zip([o[0] for o in outs], jax.lax.optimization_barrier(call(*args, output_dims=dims)), strict=True))
    W, cap = model.num_worlds, model.num_contacts

    def get(path, shape, kind="scalar"):
        name = "out_" + path.replace(".", "_")
        if name in results:
            return results[name].reshape(shape)
        return jnp.zeros(shape, jnp.int32 if kind == "int" else dtype)

    n_con = get("num_contacts", (W,), "int")
    return State(
        body_q=get("body_q", (model.num_bodies, 7)), body_u=get("body_u", (model.num_bodies, 6)),
        time=get("time", (W,)), constraint_force=get("constraint_force", (model.num_constraints,)),
        actuator_force=get("actuator_force", (model.num_dofs,)), passive_force=get("passive_force", (model.num_dofs,)),
        limit_force=get("limit_force", (model.num_dofs,)), coupling_force=get("coupling_force", (model.num_couplings,)),
        contacts=ContactState(
            pair=get("contacts.pair", (cap,), "int") if cap else jnp.zeros(0, jnp.int32),
            pos=get("contacts.pos", (cap, 3)), normal=get("contacts.normal", (cap, 3)),
            dist=get("contacts.dist", (cap,)), force=get("contacts.force", (cap, 3)),
            velocity=get("contacts.velocity", (cap, 3)), point_b=get("contacts.point_b", (cap, 3))),
        info=StepInfo(
            iterations=get("iterations", (W,), "int"), primal_residual=get("primal_residual", (W,)),
            dual_residual=get("dual_residual", (W,)), complementarity_residual=get("complementarity_residual", (W,)),
            converged=get("converged", (W,), "int") != 0, failed=get("failed", (W,), "int") != 0,
            num_contacts=n_con, contact_overflow=jnp.maximum(get("found", (W,), "int") - n_con, 0),
            penalty=get("penalty", (W,)), unconverged_steps=get("unconverged_steps", (W,), "int")),
    )


__all__ = ["batchable_step", "is_traced", "traced_step"]
