"""Worlds sharded over devices (kamino/sharding.py): on two forced host devices a sharded batch steps to
the unsharded result, world by world, on both backends, and each block stays on its device. The Warp step also
runs under ``pmap`` (what brax's PPO does over local devices).

The two-device runs need ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` before jax is imported: one
subprocess runs them all, on both backends, and the benchmark's smoke run.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import pytest

import kamino
from kamino.model import same_model, take_worlds
from kamino.sharding import group_model, shard_worlds
from tests.helpers import ALL_CORES, default_xla_env


def test_take_worlds_inverts_concat():
    """Slicing worlds out of a heterogeneous model gives back the models it was built from (every field, index
    fields shifted back), and the slices concatenate to the original."""
    parts = [kamino.models.fourbar(), kamino.models.dr_legs(), kamino.models.box_stack(3)]
    mixed = kamino.concat(parts)
    for k, part in enumerate(parts):
        assert same_model(take_worlds(mixed, k, k + 1), part)
    assert same_model(kamino.concat([take_worlds(mixed, 0, 2), take_worlds(mixed, 2, 3)]), mixed)
    with pytest.raises(kamino.ModelError, match="start < stop"):
        take_worlds(mixed, 2, 2)


def test_sharding_needs_identical_groups_of_worlds():
    """Each device steps one traced model, so the worlds must split into identical groups: a clear error naming
    the group otherwise, and for a number of worlds that does not divide."""
    pair = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)])
    assert same_model(group_model(kamino.replicate(pair, 3), 3), pair)
    with pytest.raises(ValueError, match=r"worlds 1\.\.1 \(device 1\) differ"):
        group_model(pair, 2)
    with pytest.raises(ValueError, match="3 worlds do not split over 2 devices"):
        group_model(kamino.replicate(kamino.models.fourbar(), 3), 2)
    state = kamino.init_state(kamino.models.fourbar())
    with pytest.raises(ValueError, match="do not split"):
        shard_worlds(kamino.models.fourbar(), state, [jax.devices()[0]] * 2)


_TWO_DEVICES = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import NamedSharding
    import kamino
    from kamino.sharding import shard_worlds

    devices = jax.devices()
    assert len(devices) == 2, devices
    # two identical groups of two different robots: a loop mechanism and a contact scene
    model = kamino.replicate(kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)]), 2)
    state = kamino.init_state(model, jnp.float32)
    # a different twist on every body: the two blocks differ, so a block stepped on the wrong device would show
    twist = 0.2 * np.random.default_rng(0).standard_normal((model.num_bodies, 6))
    state = state.replace(body_u=jnp.asarray(twist, jnp.float32))
    cfg = kamino.SolverConfig(dt=0.004)
    steps = 12
    for backend in ("jax", "warp"):
        ref = kamino.rollout(model, state, num_steps=steps, config=cfg, backend=backend)
        sharded = shard_worlds(model, state)
        traj = kamino.rollout(model, sharded, num_steps=steps, config=cfg, backend=backend)
        compared = [("body_q", traj.body_q, ref.body_q, True), ("time", traj.time, ref.time, True),
                    ("contact force", traj.contacts.force, ref.contacts.force, True)]
        if backend == "warp":  # the sharded step alone (the body of the sharded rollout: the docstring)
            one = kamino.step(model, sharded, config=cfg, backend=backend)
            compared.append(("step body_q", one.body_q, ref.body_q[0], False))
        for name, a, b, t in compared:
            # world blocks: block g of every entity axis on device g, the time axis whole
            spec = a.sharding.spec
            assert isinstance(a.sharding, NamedSharding) and spec[1 if t else 0] == "worlds", (backend, name, spec)
            ref_host = np.asarray(b)
            half = ref_host.shape[1 if t else 0] // 2
            for shard in a.addressable_shards:
                g = devices.index(shard.device)
                want = ref_host[:, g * half:(g + 1) * half] if t else ref_host[g * half:(g + 1) * half]
                err = float(np.max(np.abs(np.asarray(shard.data, np.float64) - want), initial=0.0))
                print(backend, name, "device", g, "max |sharded - unsharded|", err)
                assert err <= TOL[backend], (backend, name, g, err)
        assert bool(np.all(np.asarray(traj.info.converged))), backend

    # the Warp step under pmap (brax's PPO over local devices): each device steps its own stack of worlds
    group = kamino.concat([kamino.models.fourbar(), kamino.models.box_stack(2)])
    half = model.num_bodies // 2
    g_states = [state.replace(body_q=state.body_q[:half], body_u=state.body_u[:half]),
                state.replace(body_q=state.body_q[half:], body_u=state.body_u[half:])]
    g_states = [kamino.init_state(group, jnp.float32).replace(body_q=s.body_q, body_u=s.body_u) for s in g_states]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *g_states)
    out = jax.pmap(lambda s: kamino.step(group, s, config=cfg, backend="warp"))(stacked)
    assert {d for d in out.body_q.sharding.device_set} == set(devices)
    for k in range(2):
        alone = kamino.step(group, g_states[k], config=cfg, backend="warp")
        err = float(np.max(np.abs(np.asarray(out.body_q[k]) - np.asarray(alone.body_q))))
        print("pmap device", k, "max |pmap - alone|", err)
        assert err == 0.0, err

    # kamino bench multi_device runs (a smoke run: the figures are taken on GPUs)
    import json
    from kamino.bench import multi_device
    multi_device.main(["--scenes", "fourbar", "--worlds-per-device", "2", "--block", "2", "--replays", "1",
                       "--repeats", "1", "--out", OUT])
    recs = json.load(open(OUT))["records"]
    assert [(r["devices"], r["path"]) for r in recs] == [(1, "shard_map"), (1, "eager"), (2, "shard_map")], recs
    assert all(r["throughput"] > 0 and r["converged_fraction"] == 1.0 for r in recs if r["path"] == "shard_map")
    print("OK")
""")


@pytest.mark.slow  # the JAX reference's two programs (sharded and not): about 40 s of compiling on the 2-core machine
def test_sharded_worlds_on_two_devices_match_unsharded(tmp_path):
    """Two forced host devices, a model of two identical groups (a four-bar and a two-box stack each): a rollout of
    the sharded state gives, block by block on each device, the unsharded result, on both backends, and so does a
    step on the Warp backend. A sharded rollout is a ``lax.scan`` whose body is the sharded step itself
    (``kamino.sharding.sharded_program``, whatever the backend), so the JAX reference's rollout checks its sharded
    step; the step alone on that backend would be a third compile of its program (about 20 s on the 2-core machine).

    Tolerances: the Warp backend computes each world in its own threads whatever the other worlds are
    (test_cross_backend.py::test_heterogeneous_worlds_match_standalone_on_warp: exact), so its blocks are
    compared exactly. The JAX reference is the same program on half the worlds, which XLA may vectorise
    differently: float32 rounding over 12 steps, bounded at 1e-5 (m, rad, N s, and s for the time). Then the Warp
    step under ``pmap`` and ``kamino bench multi_device``'s smoke run (its records, not its speed). Everything runs
    in one subprocess: one start-up of jax and Warp on the two devices."""
    env = default_xla_env()  # the sharded and the unsharded programs at XLA's default level (tests/conftest.py)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env["JAX_PLATFORMS"] = "cpu"
    out_json = str(tmp_path / "multi_device.json")
    script = (ALL_CORES + f"TOL = {{'jax': 1e-5, 'warp': 0.0}}\nOUT = {out_json!r}\n" + _TWO_DEVICES)
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=root, capture_output=True, text=True,
                         timeout=600, check=False)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-4000:]
    assert "OK" in out.stdout
