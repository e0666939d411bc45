"""What an MJCF model uses that kamino cannot simulate, and how its actuators map (docs/mjcf.md).

Everything here reads the compiled ``mujoco.MjModel`` (the numbers MuJoCo itself simulates), so
defaults classes, ``<include>`` and compiler settings (degrees, ``autolimits``...) are already applied.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from kamino.model import ActuationMode

#: Below this a mass is zero (MuJoCo's ``mjMINVAL``).
MJ_MINVAL = 1e-15


def obj_name(mujoco: Any, mj: Any, objtype: Any, idx: int, prefix: str) -> str:
    """The element's name, or MuJoCo's placeholder ``<prefix><index>`` when it has none."""
    name = mujoco.mj_id2name(mj, objtype, int(idx))
    return name if name else f"{prefix}{int(idx)}"


def _listed(mujoco: Any, mj: Any, objtype: Any, ids: Any, prefix: str, limit: int = 6) -> str:
    ids = [int(i) for i in ids]
    names = [obj_name(mujoco, mj, objtype, i, prefix) for i in ids[:limit]]
    more = f" and {len(ids) - limit} more" if len(ids) > limit else ""
    return ", ".join(repr(n) for n in names) + more


def global_problems(mujoco: Any, mj: Any, spec: Any = None) -> list[str]:
    """Model-wide features that change the physics and that kamino does not simulate (``spec``, the
    ``mujoco.MjSpec``, names the plugins)."""
    out: list[str] = []
    O = mujoco.mjtObj
    dis = int(mj.opt.disableflags)
    ena = int(mj.opt.enableflags)
    D = mujoco.mjtDisableBit
    if mj.ntendon:
        out.append(f"tendons ({mj.ntendon}: {_listed(mujoco, mj, O.mjOBJ_TENDON, range(mj.ntendon), 'tendon')})")
    if mj.nflex:
        out.append(f"flex bodies ({mj.nflex}: {_listed(mujoco, mj, O.mjOBJ_FLEX, range(mj.nflex), 'flex')})")
    if mj.nplugin:
        names = [p.plugin_name or p.name for p in getattr(spec, "plugins", [])] if spec is not None else []
        out.append(f"engine plugins ({mj.nplugin}{': ' + ', '.join(names) if names else ''})")
    if mj.opt.density != 0.0 or mj.opt.viscosity != 0.0:
        out.append(f"fluid forces (option density={mj.opt.density:g}, viscosity={mj.opt.viscosity:g})")
    if np.any(np.asarray(mj.opt.wind) != 0.0):
        out.append(f"wind (option wind={np.asarray(mj.opt.wind).tolist()})")
    grav = np.nonzero(np.asarray(mj.body_gravcomp) != 0.0)[0]
    if grav.size:
        out.append(f"gravity compensation (gravcomp) on bodies {_listed(mujoco, mj, O.mjOBJ_BODY, grav, 'body')}")
    if ena & int(mujoco.mjtEnableBit.mjENBL_OVERRIDE):
        out.append("contact override (option flag override='enable')")
    if dis & int(D.mjDSBL_CONSTRAINT):
        out.append("disabled constraints (option flag constraint='disable')")
    if dis & int(D.mjDSBL_ACTUATION) and mj.nu:
        out.append("disabled actuation (option flag actuation='disable') with actuators")
    if int(mj.opt.disableactuator) and mj.nu:
        out.append(f"disabled actuator groups (option actuatorgroupdisable, mask {int(mj.opt.disableactuator)})")
    if dis & int(D.mjDSBL_CLAMPCTRL) and np.any(mj.actuator_ctrllimited):
        out.append("unclamped controls (option flag clampctrl='disable') with ctrlrange")
    return out


def joint_problems(mujoco: Any, mj: Any) -> list[str]:
    """Per-joint features kamino does not simulate (frictionloss, ball limits, nonlinear springs...)."""
    out: list[str] = []
    O, J = mujoco.mjtObj, mujoco.mjtJoint
    dis = int(mj.opt.disableflags)
    D = mujoco.mjtDisableBit

    def names(mask: np.ndarray) -> str:
        return _listed(mujoco, mj, O.mjOBJ_JOINT, np.nonzero(mask)[0], "joint")

    def per_joint(dof_values: np.ndarray) -> np.ndarray:
        return np.array([np.any(dof_values[mj.dof_jntid == j] != 0.0) for j in range(mj.njnt)], dtype=bool)

    jt = np.asarray(mj.jnt_type)
    if not dis & int(D.mjDSBL_FRICTIONLOSS):
        fl = per_joint(np.asarray(mj.dof_frictionloss))
        if fl.any():
            out.append(f"joint frictionloss on joints {names(fl)}")
    if not dis & int(D.mjDSBL_LIMIT):
        ball_lim = (jt == J.mjJNT_BALL) & np.asarray(mj.jnt_limited, dtype=bool)
        if ball_lim.any():
            out.append(f"ball-joint cone limits (range) on joints {names(ball_lim)}")
    if not dis & int(D.mjDSBL_SPRING):
        stiff = (np.asarray(mj.jnt_stiffness) != 0.0) & ((jt == J.mjJNT_BALL) | (jt == J.mjJNT_FREE))
        if stiff.any():
            out.append(f"stiffness on ball/free joints {names(stiff)}")
    for field, what in (("jnt_stiffnesspoly", "nonlinear joint stiffness (stiffnesspoly)"),
                        ("jnt_springyield", "joint spring yield (plasticity)")):
        arr = np.asarray(getattr(mj, field, np.zeros(mj.njnt))).reshape(mj.njnt, -1)
        bad = np.any(arr != 0.0, axis=1)
        if bad.any():
            out.append(f"{what} on joints {names(bad)}")
    plastic = np.asarray(getattr(mj, "jnt_plasticadr", np.full(mj.njnt, -1))) >= 0
    if plastic.any():
        out.append(f"joint plasticity on joints {names(plastic)}")
    if hasattr(mj, "dof_dampingpoly"):
        dp = per_joint(np.abs(np.asarray(mj.dof_dampingpoly)).sum(axis=1))
        if dp.any():
            out.append(f"nonlinear joint damping (dampingpoly) on joints {names(dp)}")
    gc = np.asarray(getattr(mj, "jnt_actgravcomp", np.zeros(mj.njnt)), dtype=bool)
    if gc.any():
        out.append(f"actuator gravity compensation (actuatorgravcomp) on joints {names(gc)}")
    return out


@dataclasses.dataclass(frozen=True)
class ActuatorSpec:
    """One MuJoCo actuator as kamino sees it: the joint it drives and the joint's Actuation terms."""

    index: int
    name: str
    joint: int  # MuJoCo joint id
    mode: ActuationMode
    kp: float
    kd: float
    effort_limit: float  # on the generalized (joint) force
    gear: float  # ctrl -> generalized effort (EFFORT); 1 for POSITION/VELOCITY
    ctrl_range: tuple[float, float]


def _sym_limit(lo: float, hi: float) -> float | None:
    """The bound ``f`` of a symmetric range ``[-f, f]`` (None when asymmetric)."""
    if lo < 0.0 < hi and np.isclose(-lo, hi, rtol=1e-12, atol=0.0):
        return float(hi)
    return None


def classify_actuators(mujoco: Any, mj: Any, problems: list[str]) -> dict[int, ActuatorSpec]:
    """MuJoCo actuators -> :class:`ActuatorSpec` keyed by MuJoCo joint id; unsupported ones go to ``problems``.

    Supported: joint transmission on a hinge or slide joint, no activation dynamics, and the
    gain/bias patterns of ``<motor>`` (gain g, no bias), ``<position>`` (gain kp, bias 0, -kp, -kv)
    and ``<velocity>`` (gain kv, bias 0, 0, -kv), whichever element wrote them.
    """
    O = mujoco.mjtObj
    out: dict[int, ActuatorSpec] = {}
    for i in range(mj.nu):
        name = obj_name(mujoco, mj, O.mjOBJ_ACTUATOR, i, "actuator")
        what = f"actuator {name!r}"
        trn = int(mj.actuator_trntype[i])
        if trn != int(mujoco.mjtTrn.mjTRN_JOINT):
            kind = mujoco.mjtTrn(trn).name.replace("mjTRN_", "").lower()
            problems.append(f"{what}: {kind} transmission (only joint actuators are supported)")
            continue
        j = int(mj.actuator_trnid[i, 0])
        jtype = int(mj.jnt_type[j])
        if jtype not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            kind = mujoco.mjtJoint(jtype).name.replace("mjJNT_", "").lower()
            problems.append(f"{what}: actuator on a {kind} joint (only hinge and slide joints can be actuated)")
            continue
        if int(mj.actuator_dyntype[i]) != int(mujoco.mjtDyn.mjDYN_NONE):
            kind = mujoco.mjtDyn(int(mj.actuator_dyntype[i])).name.replace("mjDYN_", "").lower()
            problems.append(f"{what}: activation dynamics ({kind})")
            continue
        extras = []
        for field, label in (("actuator_armature", "armature"), ("actuator_damping", "damping"),
                             ("actuator_delay", "delay"), ("actuator_dampingpoly", "dampingpoly")):
            if hasattr(mj, field) and np.any(np.asarray(getattr(mj, field))[i] != 0.0):
                extras.append(label)
        if hasattr(mj, "actuator_ctrlnum") and int(np.asarray(mj.actuator_ctrlnum)[i]) != 1:
            extras.append(f"{int(np.asarray(mj.actuator_ctrlnum)[i])} controls")
        if extras:
            problems.append(f"{what}: actuator {', '.join(extras)}")
            continue
        gear6 = np.asarray(mj.actuator_gear[i], dtype=float)
        gear = float(gear6[0])
        gt, bt = int(mj.actuator_gaintype[i]), int(mj.actuator_biastype[i])
        g, bprm = np.asarray(mj.actuator_gainprm[i], float), np.asarray(mj.actuator_biasprm[i], float)
        mode, kp, kd, scale = None, 0.0, 0.0, 1.0
        fixed_gain = gt == int(mujoco.mjtGain.mjGAIN_FIXED) and not np.any(g[1:] != 0.0) and g[0] != 0.0
        if fixed_gain and bt == int(mujoco.mjtBias.mjBIAS_NONE):
            mode, scale = ActuationMode.EFFORT, float(g[0])
        elif fixed_gain and bt == int(mujoco.mjtBias.mjBIAS_AFFINE) and bprm[0] == 0.0 and not np.any(bprm[3:]):
            if np.isclose(bprm[1], -g[0], rtol=1e-12, atol=0.0) and bprm[2] <= 0.0 and g[0] > 0.0:
                mode, kp, kd = ActuationMode.POSITION, float(g[0]), float(-bprm[2])
            elif bprm[1] == 0.0 and np.isclose(bprm[2], -g[0], rtol=1e-12, atol=0.0) and g[0] > 0.0:
                mode, kd = ActuationMode.VELOCITY, float(g[0])
        if mode is None:
            problems.append(f"{what}: gain/bias parameters (gaintype {gt}, gainprm {g[:3].tolist()}, biastype {bt}, "
                            f"biasprm {bprm[:3].tolist()}) are not a motor, position or velocity actuator")
            continue
        if mode != ActuationMode.EFFORT and gear != 1.0:
            problems.append(f"{what}: {mode.name.lower()} actuator with gear {gear:g} (kamino needs gear 1)")
            continue
        if mode == ActuationMode.POSITION and float(mj.qpos0[mj.jnt_qposadr[j]]) != 0.0:
            problems.append(f"{what}: position actuator on joint "
                            f"{obj_name(mujoco, mj, O.mjOBJ_JOINT, j, 'joint')!r} whose ref is not 0 "
                            "(kamino's position targets are relative to the reference pose)")
            continue
        effort_limit = np.inf
        if mj.actuator_forcelimited[i]:
            f = _sym_limit(*map(float, mj.actuator_forcerange[i]))
            if f is None:
                problems.append(f"{what}: asymmetric forcerange {np.asarray(mj.actuator_forcerange[i]).tolist()}")
                continue
            effort_limit = abs(gear) * f
        if mj.jnt_actfrclimited[j]:
            f = _sym_limit(*map(float, mj.jnt_actfrcrange[j]))
            if f is None:
                problems.append(f"{what}: asymmetric actuatorfrcrange on its joint")
                continue
            effort_limit = min(effort_limit, f)
        ctrl = (-np.inf, np.inf)
        if mj.actuator_ctrllimited[i]:
            ctrl = (float(mj.actuator_ctrlrange[i, 0]), float(mj.actuator_ctrlrange[i, 1]))
        if j in out:
            problems.append(f"{what}: joint {obj_name(mujoco, mj, O.mjOBJ_JOINT, j, 'joint')!r} already has actuator "
                            f"{out[j].name!r} (kamino allows one actuator per DoF)")
            continue
        out[j] = ActuatorSpec(index=i, name=name, joint=j, mode=mode, kp=kp, kd=kd, effort_limit=float(effort_limit),
                              gear=gear * scale if mode == ActuationMode.EFFORT else 1.0, ctrl_range=ctrl)
    return out
