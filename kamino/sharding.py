"""Worlds spread over several devices: a State sharded along its world axis, stepped in place on each device.

Every array of a :class:`~kamino.state.State` (and of a :class:`~kamino.state.Control`) is stored world after world
along its leading axis (docs/conventions.md, "Data layout"). A model of ``n`` identical groups of worlds (what
``kamino.replicate`` builds) therefore splits into ``n`` equal, contiguous blocks of every array, one per device,
and each block is the state of the group's model alone. :func:`shard_worlds` places a state that way
(``NamedSharding`` over a one-axis mesh); ``kamino.step`` / ``kamino.rollout`` given such a state run the
backend's own step under ``jax.shard_map``: each device steps its block as the group model, in place, with no
gather to one device and no host round trip, and the result keeps the input's sharding. The Warp backend's step
inside ``shard_map`` is its traced FFI call (``kamino/warp_backend/jit.py``), which runs on the device XLA calls it
on with that device's own stepper (docs/warp_backend.md, "Several devices"). JAX's device parallelism does the
rest; kamino adds only the world layout.

Why identical groups: ``shard_map`` traces the step once for every device, so every device must step the same
model. Worlds of different robots still shard if each device's group holds the same mix (``replicate(concat(...),
n)``); any other split raises a ``ValueError`` naming the group that differs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from kamino.model import Model, same_model, take_worlds

WORLD_AXIS = "worlds"
"""The mesh axis name :func:`shard_worlds` uses."""


def group_model(model: Model, num_shards: int, fn: str = "shard_worlds") -> Model:
    """The model of one device's block of worlds: ``model`` must be ``num_shards`` identical groups."""
    if model.num_worlds % num_shards:
        raise ValueError(f"{fn}: the model's {model.num_worlds} worlds do not split over {num_shards} devices; "
                         "the number of worlds must be a multiple of the number of devices")
    k = model.num_worlds // num_shards
    first = take_worlds(model, 0, k)
    for g in range(1, num_shards):
        if not same_model(first, take_worlds(model, g * k, (g + 1) * k)):
            raise ValueError(f"{fn}: worlds {g * k}..{(g + 1) * k - 1} (device {g}) differ from worlds 0..{k - 1} "
                             f"(device 0); sharding needs {num_shards} identical groups of worlds, as "
                             "kamino.replicate(model, n) builds")
    return first


def shard_worlds(model: Model, tree, devices: Sequence[jax.Device] | Mesh | None = None):
    """``tree`` (a State, a Control, or any pytree of per-entity arrays of ``model``) placed on ``devices``, world
    block ``g`` on device ``g``: every array gets ``NamedSharding(mesh, P("worlds"))``. ``devices``: a list of
    devices, a one-axis :class:`jax.sharding.Mesh`, or ``None`` for all of ``jax.devices()``. Raises a
    ``ValueError`` when the worlds do not split into identical groups (:func:`group_model`)."""
    mesh = _mesh(devices)
    group_model(model, mesh.devices.size)
    sharding = NamedSharding(mesh, P(mesh.axis_names[0]))
    return jax.tree.map(lambda x: jax.device_put(x, sharding), tree)


def _mesh(devices) -> Mesh:
    if isinstance(devices, Mesh):
        if len(devices.axis_names) != 1:
            raise ValueError(f"shard_worlds: the mesh must have one axis (the worlds), got {devices.axis_names}")
        return devices
    devs = jax.devices() if devices is None else list(devices)
    if not devs:
        raise ValueError("shard_worlds: no devices given")
    return Mesh(np.asarray(devs), (WORLD_AXIS,))


def world_sharding(state) -> tuple[Mesh, str | tuple[str, ...]] | None:
    """``(mesh, axis)`` when ``state.body_q`` is sharded over several devices along its world axis (a
    ``NamedSharding`` whose spec names a mesh axis first), else ``None`` (one device, or traced). Any other
    multi-device placement raises: it would make XLA gather the worlds onto every device."""
    q = state.body_q
    if isinstance(q, jax.core.Tracer) or not isinstance(q, jax.Array):
        return None
    sharding = q.sharding
    if len(sharding.device_set) <= 1:
        return None
    spec = getattr(sharding, "spec", None)
    if not isinstance(sharding, NamedSharding) or spec is None or len(spec) == 0 or spec[0] is None \
            or any(s is not None for s in spec[1:]):
        raise ValueError(f"the state is spread over {len(sharding.device_set)} devices as {sharding}; kamino "
                         "steps worlds sharded along their leading axis only: place the state with "
                         "kamino.sharding.shard_worlds(model, state)")
    return sharding.mesh, spec[0]


def num_shards(mesh: Mesh, axis) -> int:
    """How many blocks ``axis`` (a mesh axis name, or a tuple of them) cuts the worlds into."""
    names = axis if isinstance(axis, tuple) else (axis,)
    return int(np.prod([mesh.shape[a] for a in names]))


def sharded_program(fn: str, group_step: Callable, mesh: Mesh, axis, num_steps: int | None = None) -> Callable:
    """The jitted ``(state, control) -> State`` that runs ``group_step`` (one step of the group model, every
    device's block of worlds: :func:`group_model`) under ``jax.shard_map`` (``fn == "step"``), or a rollout of it.
    A rollout is a ``lax.scan`` whose body is that sharded step: the carry stays sharded, so each device still steps
    its own block in place. The scan is outside the ``shard_map`` on purpose: XLA's GPU compiler (jax 0.11.2) crashes
    on a loop inside a per-device program that carries a zero-size array, which a State holds for what its model does
    not use (docs/warp_backend.md, "Several devices"; :func:`kamino.state.drop_empty`). The control and a rollout's
    trajectory keep their leading time axis unsharded. ``kamino.Simulator`` keeps one per (call, steps, mesh)."""
    one = jax.shard_map(group_step, mesh=mesh, in_specs=(P(axis), P(axis)), out_specs=P(axis), check_vma=False)
    if fn == "step":
        return jax.jit(one)

    def run(s, cs):
        def body(carry, c):
            nxt = one(carry, c)
            return nxt, nxt

        return jax.lax.scan(body, s, cs, length=num_steps)[1]

    return jax.jit(run)


__all__ = ["WORLD_AXIS", "group_model", "shard_worlds", "world_sharding"]
