"""The JAX reference backend: a readable, vmapped, jit-compiled oracle (pure JAX).

Stages (docs/architecture.md "Backend contract", the same module names as ``kamino/warp_backend``): ``jacobians``
(kinematics), ``collision``, ``contacts``, ``dynamics`` and ``rows`` (the joint-dynamics, joint, coupling and limit
rows), ``solver`` (PADMM), ``linear_solve`` (its block Cholesky), ``post_stabilisation``, orchestrated by
``pipeline``; ``backend`` holds the engine a ``kamino.Simulator`` uses.
"""
