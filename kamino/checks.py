"""Validation of what a caller passes to ``kamino.step`` / ``rollout`` (both backends), before any backend runs.

Each check raises a ``TypeError`` (wrong kind of object) or ``ValueError`` (wrong shape or value) that names the
argument, so a mistake fails here rather than as a compile, hashing or buffer error inside a backend.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import numpy as np

from kamino.config import SolverConfig, WarpSettings
from kamino.model import Model, fingerprint
from kamino.state import Control, State

#: the Warp backend's settings (``SolverConfig.warp``) with the values the JAX reference computes as (``None``: any
#: value is the JAX reference's own). The JAX reference builds a dense Jacobian and solves with a dense Cholesky
#: factorisation: ``jacobian="dense"`` and ``linear_solver="llt"`` are what it does anyway.
WARP_ONLY_FIELDS = {"linear_solver": ("llt", "auto"), "cr_iterations": None}


#: The state dtypes: float32 (the Warp backend's and the environments' default) and float64 (the reference).
STATE_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))

#: The largest time step [s] that steps without a warning: 20 Hz, coarser than any control rate kamino's models are
#: built for. The contact, joint-limit and PD rows are solved at the velocity level once per step, so a longer step
#: lets a body move a whole link length between two solves (a pendulum of 0.5 m swings 0.5 rad in 0.05 s at 10 rad/s);
#: MuJoCo's default is 2 ms and kamino's 1/240 s.
MAX_QUIET_DT = 0.05


def _type_name(x) -> str:
    t = type(x)
    return t.__name__ if t.__module__ == "builtins" else f"{t.__module__}.{t.__qualname__}"


def check_model(model, fn: str = "step") -> None:
    """``model`` must be a :class:`kamino.Model`."""
    if not isinstance(model, Model):
        raise TypeError(f"{fn}: model must be a kamino.Model (kamino.models.fourbar(), ModelBuilder.finalize(), "
                        f"kamino.load_mjcf(...)), got {_type_name(model)}")


def check_config(config, backend: str, fn: str = "step") -> None:
    """``config`` must be a :class:`kamino.SolverConfig` or ``None``. With ``backend="jax"`` a Warp-only setting
    away from what the JAX reference computes (``warp.linear_solver="cr"``, a ``warp.cr_iterations`` other than the
    default) warns (``UserWarning``): the JAX reference always solves with a dense Cholesky factorisation, so the
    setting has no effect there. It warns rather than raises so that one config can drive both backends."""
    if config is None:
        return
    if not isinstance(config, SolverConfig):
        hint = " (write config=kamino.SolverConfig(**your_dict))" if isinstance(config, dict) else ""
        raise TypeError(f"{fn}: config must be a kamino.SolverConfig or None, got {_type_name(config)}{hint}")
    if backend != "jax":
        return
    defaults = WarpSettings()
    for name, honoured in WARP_ONLY_FIELDS.items():
        value = getattr(config.warp, name)
        if honoured is None:
            ignored = value != getattr(defaults, name)
        else:
            ignored = value not in honoured
        if ignored:
            warnings.warn(f"{fn}: SolverConfig.warp.{name}={value!r} is a Warp backend setting; backend='jax' "
                          "ignores it (the JAX reference uses a dense Jacobian and a dense Cholesky solve; pass "
                          "backend='warp' to use it)", UserWarning, stacklevel=3)


def check_state_dtype(dtype, fn: str = "init_state", name: str = "dtype") -> np.dtype:
    """``dtype`` as a numpy dtype, if it is a state dtype (:data:`STATE_DTYPES`); else a ``ValueError`` naming
    ``name`` (a ``TypeError`` for what is no dtype at all): integer poses truncate every quaternion to zero, and
    float16 (or bfloat16) cannot resolve a joint's closure (its rounding step at 1 m is 1e-3 m)."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise TypeError(f"{fn}: {name} must be float32 or float64, got {dtype!r}") from None
    if dt not in STATE_DTYPES:
        raise ValueError(f"{fn}: {name} must be float32 or float64 (kamino steps float32 and float64 states), got "
                         f"{dt.name}")
    return dt


def check_dt(model: Model, config: SolverConfig | None, fn: str = "step") -> None:
    """Warn (``UserWarning``) when ``config.dt`` exceeds :data:`MAX_QUIET_DT`: a step that long lets the model's
    bodies move far between two velocity-level solves, so contacts, limits and loops are missed or overshot.
    ``model.suggested_dt`` (an MJCF file's ``<option timestep>``) is named when there is one."""
    dt = (config or SolverConfig()).dt
    if dt <= MAX_QUIET_DT:
        return
    hint = "" if getattr(model, "suggested_dt", None) is None else f"; the model suggests dt={model.suggested_dt:g}"
    warnings.warn(f"{fn}: config.dt={dt:g} s is longer than {MAX_QUIET_DT:g} s: bodies move far between two "
                  f"solves and contacts, joint limits and loop closures are missed or overshot (kamino's default is "
                  f"{SolverConfig().dt:.4g} s{hint})", UserWarning, stacklevel=3)


def check_control_type(control, name: str = "control", fn: str = "step") -> None:
    """``control`` must be a :class:`kamino.Control` or ``None`` (not a bare array)."""
    if control is None or isinstance(control, Control):
        return
    raise TypeError(f"{fn}: {name} must be a kamino.Control or None, got {_type_name(control)} "
                    "(wrap arrays by field: kamino.Control(position_target=...), Control(dof_effort=...), or "
                    "kamino.Control.from_ctrl(model, ctrl) for a MuJoCo-style ctrl vector)")


def check_state(model: Model, state: State, fn: str = "step") -> None:
    """``state`` must be a :class:`kamino.State` whose arrays fit ``model`` (one step's state, no time axis)."""
    if not isinstance(state, State):
        raise TypeError(f"{fn}: state must be a kamino.State (kamino.init_state(model)), got {_type_name(state)}")
    missing = [jax.tree_util.keystr(path) for path, leaf in
               jax.tree_util.tree_flatten_with_path(state, is_leaf=lambda v: v is None)[0] if leaf is None]
    if missing:
        raise ValueError(f"{fn}: state{missing[0]} is None ({len(missing)} fields in all): the state went through "
                         "kamino.state.drop_empty (an environment's pipeline_state); restore it with "
                         "kamino.state.fill_empty(state, kamino.init_state(model)) or env.full_state(pipeline_state)")
    check_state_model(model, state, fn)
    if np.dtype(state.body_q.dtype) not in STATE_DTYPES:
        raise ValueError(f"{fn}: state.body_q has dtype {np.dtype(state.body_q.dtype).name}; kamino steps float32 and "
                         "float64 states (kamino.init_state(model, dtype=np.float32))")
    nb = model.num_bodies
    if state.body_q.shape != (nb, 7):
        raise ValueError(f"state.body_q has shape {state.body_q.shape}, expected ({nb}, 7) for this model")
    if state.body_u.shape != (nb, 6):
        raise ValueError(f"state.body_u has shape {state.body_u.shape}, expected ({nb}, 6) for this model")
    for field in ("actuator_force", "passive_force", "limit_force"):
        if getattr(state, field).shape != (model.num_dofs,):
            raise ValueError(f"state.{field} has shape {getattr(state, field).shape}, expected ({model.num_dofs},)")
    if state.coupling_force.shape != (model.num_couplings,):
        raise ValueError(f"state.coupling_force has shape {state.coupling_force.shape}, expected "
                         f"({model.num_couplings},) for this model")
    if state.contacts.pair.shape != (model.num_contacts,):
        raise ValueError(f"state.contacts has capacity {state.contacts.pair.shape[0]}, expected {model.num_contacts} "
                         "for this model (create the state with kamino.init_state(model))")
    if state.constraint_force.shape != (model.num_constraints,):
        raise ValueError(
            f"state.constraint_force has shape {state.constraint_force.shape}, expected "
            f"({model.num_constraints},) for this model"
        )


def check_state_model(model: Model, state: State, fn: str = "step") -> None:
    """``state`` (one step's, or a trajectory) must belong to ``model``: its ``model_fingerprint``, set by
    ``kamino.init_state``, is ``model``'s :func:`kamino.model.fingerprint` (a state whose fingerprint is ``None`` is
    not checked). Static data, so the check runs at trace time under ``jax.jit`` / ``vmap``."""
    key = state.model_fingerprint
    if key is None or key == fingerprint(model):
        return
    raise ValueError(f"{fn}: the state belongs to another model (state.model_fingerprint {key!r}, this model's "
                     f"{fingerprint(model)!r}): its bodies would jump to that model's poses. Create the state with "
                     "kamino.init_state(model) for this model (the fingerprint covers the mechanism: names, joints, "
                     "frames, geoms; masses, gains and limits may differ)")


def check_control(model: Model, control: Control | None, *, time_axis: bool = False, name: str = "control") -> None:
    """Shapes of a step's control (``time_axis=False``: exactly one step's arrays) or of a rollout's controls
    (``time_axis=True``: one leading time axis on every field)."""
    if control is None:
        return
    check_control_type(control, name, "rollout" if time_axis else "step")
    expected = {"dof_effort": (model.num_dofs,), "body_wrench": (model.num_bodies, 6),
                "position_target": (model.num_dofs,), "velocity_target": (model.num_dofs,)}
    for field in dataclasses.fields(Control):
        value = getattr(control, field.name)
        if value is None:
            continue
        shape, want = tuple(np.shape(value)), expected[field.name]
        if time_axis:
            ok = len(shape) == len(want) + 1 and shape[1:] == want
            what = f"(num_steps, {', '.join(map(str, want))})"
            hint = "; rollout controls carry one leading time axis"
        else:
            ok = shape == want
            what = str(want)
            hint = ("; kamino.step takes one step's control (a leading time axis belongs to kamino.rollout's "
                    "controls; worlds are already in the flat axis)") if shape[len(shape) - len(want):] == want else ""
        if not ok:
            raise ValueError(f"{name}.{field.name} has shape {shape}, expected {what} for this model "
                             f"(total over its {model.num_worlds} world(s)){hint}")


def check_rollout_controls(model: Model, controls: Control | None, num_steps: int | None) -> int:
    """The number of steps of a rollout, after checking that the controls share one leading time axis."""
    if controls is None:
        if num_steps is None:
            raise ValueError("rollout: give controls with a leading time axis, or num_steps")
        if isinstance(num_steps, bool) or int(num_steps) != num_steps or num_steps < 1:
            raise ValueError(f"rollout: num_steps must be a positive integer, got {num_steps!r}")
        return int(num_steps)
    check_control(model, controls, time_axis=True, name="controls")
    lengths = {x.shape[0] for x in jax.tree_util.tree_leaves(controls)}
    if len(lengths) != 1:
        raise ValueError(f"rollout: controls must share one leading time axis, got lengths {lengths}")
    n = lengths.pop()
    if num_steps is not None and num_steps != n:
        raise ValueError(f"rollout: num_steps={num_steps} but controls hold {n} steps")
    return int(n)
