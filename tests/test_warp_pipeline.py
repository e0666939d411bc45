"""The Warp backend's step pipeline on Warp's CPU device (what CI can check without a GPU)."""

import jax.numpy as jnp
import numpy as np

import kamino


def test_worlds_stop_iterating_when_they_converge():
    # one world at rest converges in 2 iterations, a thrown one needs more: per-world convergence
    model = kamino.concat([kamino.models.fourbar(), kamino.models.fourbar()])
    state = kamino.init_state(model, jnp.float32)
    u = np.array(state.body_u)
    u[model.world_body_start[1]:, 3:] = 3.0
    state = state.replace(body_u=jnp.asarray(u))
    # a tolerance far below the default, so that the thrown world's solve takes more than the minimum 2 iterations
    out = kamino.step(model, state, config=kamino.SolverConfig(tolerance=1e-7), backend="warp")
    it = np.asarray(out.info.iterations)
    assert it[0] < it[1]


def test_the_warp_step_runs_inside_jax_jit_and_scan():
    # through Warp's JAX FFI (kamino/warp_backend/jit.py): the same kernels on XLA's buffers, so the
    # result is bitwise the eager call's
    import jax

    model = kamino.models.box_stack(2)
    state = kamino.init_state(model)
    cfg = kamino.SolverConfig()
    step = jax.jit(lambda s: kamino.step(model, s, config=cfg, backend="warp"))
    jitted = step(step(state))
    eager = kamino.step(model, kamino.step(model, state, config=cfg, backend="warp"), config=cfg, backend="warp")
    np.testing.assert_array_equal(np.asarray(jitted.body_q), np.asarray(eager.body_q))
    np.testing.assert_array_equal(np.asarray(jitted.contacts.force), np.asarray(eager.contacts.force))
    assert int(jitted.info.num_contacts[0]) == int(eager.info.num_contacts[0]) > 0
    traj = jax.jit(lambda s: kamino.rollout(model, s, num_steps=10, config=cfg, backend="warp"))(state)
    ref = kamino.rollout(model, state, num_steps=10, config=cfg, backend="warp")
    np.testing.assert_array_equal(np.asarray(traj.body_q), np.asarray(ref.body_q))


def test_a_returned_state_is_not_changed_by_later_steps():
    """The eager step reuses its stepper's buffers: every State it returns must own its arrays. jaxlib 0.9 made
    ``jnp.asarray`` of a numpy view alias the buffer, and a state returned by one step then took the values of the
    next step of another state. Here a falling box's first state must survive a step of a state moving
    the other way, field by field."""
    model = kamino.models.box_stack(1)
    s0 = kamino.init_state(model, jnp.float32)
    cfg = kamino.SolverConfig()
    s1 = kamino.step(model, s0, config=cfg, backend="warp")
    before = {k: np.array(v) for k, v in (("body_q", s1.body_q), ("body_u", s1.body_u), ("time", s1.time),
                                          ("iterations", s1.info.iterations))}
    up = s0.replace(body_u=s0.body_u.at[:, 2].set(5.0))
    s2 = kamino.step(model, kamino.step(model, up, config=cfg, backend="warp"), config=cfg, backend="warp")
    assert not np.array_equal(np.asarray(s2.body_u), before["body_u"])  # the later steps differ ...
    for name, arr in (("body_q", s1.body_q), ("body_u", s1.body_u), ("time", s1.time),
                      ("iterations", s1.info.iterations)):
        np.testing.assert_array_equal(np.asarray(arr), before[name], err_msg=name)  # ... and s1 is untouched


def test_jax_vmap_batches_the_warp_step():
    """``jax.vmap`` over states of a two-world model (a four-bar and a box stack) on the Warp backend: the batch is
    stepped as one replicated model (``kamino.warp_backend.jit.batchable_step``), and each batch entry equals that
    state stepped alone, exactly (a world's arithmetic does not depend on the other worlds:
    test_cross_backend.py::test_heterogeneous_worlds_match_standalone_on_warp). Also under ``jit``, with an
    unbatched control broadcast, and nested (a ``vmap`` of a ``vmap``)."""
    import jax

    model = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)])
    cfg = kamino.SolverConfig()
    base = kamino.init_state(model, jnp.float32)
    twists = 0.1 * np.random.default_rng(1).standard_normal((3, model.num_bodies, 6))
    states = [base.replace(body_u=jnp.asarray(t, jnp.float32)) for t in twists]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *states)
    control = kamino.Control(dof_effort=jnp.full(model.num_dofs, 0.3, jnp.float32))

    def one(s):
        return kamino.step(model, s, control, config=cfg, backend="warp")

    for fn in (jax.vmap(one), jax.jit(jax.vmap(one))):
        out = fn(batch)
        for k, s in enumerate(states):
            alone = one(s)
            np.testing.assert_array_equal(np.asarray(out.body_q[k]), np.asarray(alone.body_q))
            np.testing.assert_array_equal(np.asarray(out.info.iterations[k]), np.asarray(alone.info.iterations))
    nested = jax.vmap(jax.vmap(one))(jax.tree.map(lambda x: jnp.stack([x, x]), batch))
    np.testing.assert_array_equal(np.asarray(nested.body_q[1, 2]), np.asarray(one(states[2]).body_q))


def assert_precompile_covers_a_step(device: str, monkeypatch) -> None:
    """``Stepper.precompile`` loads every module that a step of dr_legs (loops, contacts, limits, actuators,
    post-stabilisation) launches: the step that follows asks Warp for no module it did not record."""
    from kamino.warp_backend import backend as wb

    model = kamino.models.dr_legs()
    st = wb.Stepper(model, kamino.SolverConfig(), np.float32, device)
    st.precompile()
    modules = {m for m, _ in st.precompiled}
    assert len(modules) > 20  # the step's kernels, each a module of its own
    assert all(m.execs for m in modules)  # each one loaded
    launched: set = set()
    module_type = type(next(iter(modules)))
    load = module_type.load

    def spy(self, *args, **kwargs):
        launched.add(self)
        return load(self, *args, **kwargs)

    wb.load_state(st, kamino.init_state(model, jnp.float32), None)
    monkeypatch.setattr(module_type, "load", spy)
    st.run(2)
    monkeypatch.undo()
    assert launched, "the step launched nothing"
    missed = {m.name for m in launched - modules}
    assert not missed, f"launched but not precompiled: {sorted(missed)}"
    assert np.isfinite(st.work.q.numpy()).all()


def test_precompile_covers_every_module_a_step_launches(monkeypatch):
    assert_precompile_covers_a_step("cpu", monkeypatch)


def test_a_step_compiled_in_the_background_is_the_one_a_vmap_steps_with():
    """``Engine.compile_in_background(n, dtype)`` builds and compiles, in a thread, the stepper that a ``jax.vmap``
    over ``n`` traced states calls. Stepped at once, without waiting for the thread, the batch must use that very
    stepper (no second build: the traced step waits for the thread's compile under ``CUDA_STREAM_LOCK``) and give
    bitwise the states a simulator without the background compile gives (the same kernels on the same inputs)."""
    import jax

    from kamino.warp_backend.backend import _jax_device

    model = kamino.models.fourbar()
    cfg = kamino.SolverConfig()
    base = kamino.init_state(model, jnp.float32)
    twists = 0.2 * np.random.default_rng(2).standard_normal((3, model.num_bodies, 6))
    batch = jax.tree.map(lambda *x: jnp.stack(x),
                         *[base.replace(body_u=jnp.asarray(t, jnp.float32)) for t in twists])
    sim = kamino.Simulator(model, cfg, backend="warp")
    thread = sim.engine.compile_in_background(3, np.float32)
    out = jax.jit(jax.vmap(sim.step))(batch)
    thread.join()
    device = _jax_device()  # "cpu" in CI, "cuda:0" where JAX runs on the GPU
    stepper = sim.engine.replica(3).stepper(np.float32, device, for_jit=True)
    assert stepper.precompiled, "the thread's stepper was not compiled"
    assert sim.engine.replica(3)._steppers == {(np.dtype(np.float32), device, True, False): stepper}
    plain = jax.jit(jax.vmap(kamino.Simulator(model, cfg, backend="warp").step))(batch)
    for name in ("body_q", "body_u"):
        np.testing.assert_array_equal(np.asarray(getattr(out, name)), np.asarray(getattr(plain, name)), err_msg=name)
    assert np.asarray(out.info.converged).all()
    with np.testing.assert_raises(ValueError):
        sim.engine.compile_in_background(0, np.float32)
