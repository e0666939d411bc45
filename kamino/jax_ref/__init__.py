"""The JAX reference backend: a readable, vmapped, jit-compiled oracle (pure JAX).

Stages (docs/architecture.md "Backend contract"): ``joints`` (kinematics), ``dynamics``,
``padmm`` (solve), ``spatial.integrate_pose`` (integrate), orchestrated by ``step``.
"""
