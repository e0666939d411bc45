"""The Warp production backend (kernels, CUDA graphs, JAX interop): docs/warp_backend.md.

Stages (docs/architecture.md "Backend contract", the same module names as ``kamino/jax_ref``): ``jacobians``
(kinematics), ``collision``, ``contacts``, ``rows`` (dynamics), ``solver`` / ``solver_lanes`` / ``solver_rules``
(PADMM), ``linear_solve`` (the sparse LLT, CR), ``integrate``, ``post_stabilisation``, orchestrated by ``pipeline``;
``backend`` holds the engine a ``kamino.Simulator`` uses.
"""
