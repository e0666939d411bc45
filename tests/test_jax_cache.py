"""JAX's persistent compilation cache, as ``import kamino`` sets it up (kamino/_jax_cache.py).

The choice of directory (``KAMINO_JAX_CACHE`` off / a path / the user's cache directory, and an existing JAX setting
respected) is tested by calling the module with a monkeypatched environment; the JAX config values it may change are
saved and restored around every test. Loading an entry prints no XLA log line: tested on a fake loader, and end to
end in subprocesses that compile one small function and load it back.
"""

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import pytest

import kamino
from kamino import _jax_cache

_NAMES = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")


@pytest.fixture(autouse=True)
def _jax_config(monkeypatch):
    """JAX's cache settings and the module's record as they were, afterwards (conftest's per-worker cache)."""
    saved = {name: getattr(jax.config, name) for name in _NAMES}
    saved_choice = _jax_cache.choice
    update = jax.config.update  # a test may replace it (monkeypatch undoes that only after this fixture)
    monkeypatch.delenv(_jax_cache.ENV, raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    yield
    for name, value in saved.items():
        update(name, value)
    _jax_cache.choice = saved_choice


def _no_jax_dir():
    jax.config.update("jax_compilation_cache_dir", None)


def test_the_test_suite_does_not_use_the_users_cache_directory():
    # conftest.py configures JAX's cache (.pytest_cache/jax-<worker>) before kamino is imported: kamino keeps it
    assert _jax_cache.choice is not None
    assert _jax_cache.choice.source != "default", _jax_cache.choice
    assert kamino.__doc__ and "KAMINO_JAX_CACHE" in kamino.__doc__


@pytest.mark.parametrize("value", ["0", "off", "OFF", " false ", "no", "none"])
def test_off_leaves_jax_alone(monkeypatch, value):
    monkeypatch.setenv(_jax_cache.ENV, value)
    _no_jax_dir()
    choice = _jax_cache.enable()
    assert (choice.directory, choice.source) == (None, "off")
    assert jax.config.jax_compilation_cache_dir is None
    assert _jax_cache.choice is choice


def test_a_path_from_the_environment(monkeypatch, tmp_path):
    target = tmp_path / "nested" / "jax"
    monkeypatch.setenv(_jax_cache.ENV, str(target))
    _no_jax_dir()
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 5.0)
    choice = _jax_cache.enable()
    assert (choice.directory, choice.source) == (str(target), "env")
    assert target.is_dir()  # created
    assert jax.config.jax_compilation_cache_dir == str(target)
    # a higher threshold would leave kamino's compiles out: lowered to kamino's
    assert jax.config.jax_persistent_cache_min_compile_time_secs == _jax_cache.MIN_COMPILE_TIME_SECS


def test_a_lower_threshold_of_the_users_stays(monkeypatch, tmp_path):
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path))
    _no_jax_dir()
    low = _jax_cache.MIN_COMPILE_TIME_SECS / 4
    jax.config.update("jax_persistent_cache_min_compile_time_secs", low)
    _jax_cache.enable()
    assert jax.config.jax_persistent_cache_min_compile_time_secs == low


def test_tilde_is_expanded(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    choice = _jax_cache.choose({_jax_cache.ENV: "~/kc"}, jax_dir=None)
    assert choice.directory == str(tmp_path / "kc")


def test_default_is_the_users_cache_directory(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    choice = _jax_cache.choose(jax_dir=None)
    assert choice.source == "default"
    try:
        import platformdirs
    except ImportError:
        assert choice.directory == str(tmp_path / "xdg" / "kamino" / "jax")
    else:
        assert choice.directory == str(Path(platformdirs.user_cache_dir("kamino")) / "jax")
        assert Path(choice.directory).parts[-2:] == ("kamino", "jax")


def test_default_without_platformdirs(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "platformdirs", None)  # import platformdirs -> ImportError
    monkeypatch.setenv("HOME", str(tmp_path))
    assert _jax_cache.default_dir({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == tmp_path / "xdg" / "kamino" / "jax"
    # unset, empty or relative XDG_CACHE_HOME: ~/.cache (the XDG base directory specification)
    for env in ({}, {"XDG_CACHE_HOME": ""}, {"XDG_CACHE_HOME": "relative/dir"}):
        assert _jax_cache.default_dir(env) == tmp_path / ".cache" / "kamino" / "jax"


def test_default_when_enabled_writes_there(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "platformdirs", None)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    _no_jax_dir()
    choice = _jax_cache.enable()
    assert choice.source == "default"
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "kamino" / "jax")
    assert (tmp_path / "kamino" / "jax").is_dir()


def test_an_existing_jax_setting_is_respected(monkeypatch, tmp_path):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "users"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 7.0)
    choice = _jax_cache.enable()
    assert (choice.directory, choice.source) == (str(tmp_path / "users"), "jax")
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "users")
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 7.0  # the user's cache, the user's threshold
    assert not (tmp_path / "users").exists()  # kamino creates nothing there


def test_jax_setting_wins_over_the_variable_with_a_warning(monkeypatch, tmp_path):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "users"))
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path / "kamino"))
    with pytest.warns(RuntimeWarning, match="already set"):
        choice = _jax_cache.enable()
    assert choice.source == "jax"
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "users")
    # the same directory both ways (what conftest.py may do for the test subprocesses): no warning
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path / "users"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _jax_cache.enable().source == "jax"


def test_jax_cache_switched_off_is_respected(monkeypatch, tmp_path):
    _no_jax_dir()
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path))
    assert _jax_cache.choose(jax_dir=None, jax_enabled=False) == _jax_cache.CacheChoice(
        None, "jax", "jax_enable_compilation_cache is False")
    monkeypatch.setattr(_jax_cache, "_jax_value", lambda name: name != "jax_enable_compilation_cache" and None)
    assert _jax_cache.enable().source == "jax"
    assert jax.config.jax_compilation_cache_dir is None


def test_an_unusable_directory_warns_and_leaves_the_cache_off(monkeypatch, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    monkeypatch.setenv(_jax_cache.ENV, str(blocker / "jax"))
    _no_jax_dir()
    with pytest.warns(RuntimeWarning, match=r"KAMINO_JAX_CACHE=0"):
        choice = _jax_cache.enable()
    assert (choice.directory, choice.source) == (None, "failed")
    assert jax.config.jax_compilation_cache_dir is None


def test_jax_config_names_that_differ_warn(monkeypatch, tmp_path):
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path))
    _no_jax_dir()

    def missing(name):
        raise AttributeError(f"'Config' object has no attribute {name!r}")

    monkeypatch.setattr(_jax_cache, "_jax_value", missing)
    with pytest.warns(RuntimeWarning, match="jax_compilation_cache_dir"):
        assert _jax_cache.enable().source == "failed"
    assert jax.config.jax_compilation_cache_dir is None


def test_a_failing_update_warns_naming_the_option(monkeypatch, tmp_path):
    monkeypatch.setenv(_jax_cache.ENV, str(tmp_path))
    _no_jax_dir()
    real = jax.config.update

    def update(name, value):
        if name == "jax_persistent_cache_min_compile_time_secs":
            raise AttributeError(f"Unrecognized config option: {name}")
        real(name, value)

    jax.config.update("jax_persistent_cache_min_compile_time_secs", 5.0)
    monkeypatch.setattr(jax.config, "update", update)
    with pytest.warns(RuntimeWarning, match="jax_persistent_cache_min_compile_time_secs"):
        choice = _jax_cache.enable()
    assert choice.source == "env"  # the directory is set; only the threshold is JAX's
    assert jax.config.jax_compilation_cache_dir == str(tmp_path)


# ---------------------------------------------------------------------------------------------
# Loading an entry prints no XLA log line
# ---------------------------------------------------------------------------------------------

def test_import_kamino_makes_cache_loads_quiet():
    from jax._src import compilation_cache

    assert getattr(compilation_cache.get_executable_and_time, "kamino_quiet", False)
    assert _jax_cache.quiet_cache_loads()  # idempotent: the loader is wrapped once
    assert not getattr(compilation_cache.get_executable_and_time.__wrapped__, "kamino_quiet", False)


def test_a_load_runs_with_xla_logs_off_and_restores_them(monkeypatch):
    levels: list[int] = []
    monkeypatch.setattr(_jax_cache, "_set_xla_min_log_level", levels.append)
    monkeypatch.setenv("TF_CPP_MIN_LOG_LEVEL", "1")  # what `import jax` sets when the user set nothing

    inside: list[list[int]] = []

    def load(key, **options):
        inside.append(list(levels))
        if key == "broken":
            raise ValueError("a corrupt entry")
        return "executable", options["devices"]

    quiet = _jax_cache._quiet_loader(load)
    assert quiet("key", devices=2) == ("executable", 2)
    assert inside == [[3]]  # fatal only while the entry loads
    assert levels == [3, _jax_cache.XLA_DEFAULT_MIN_LOG_LEVEL]  # jaxlib's default back: warnings and errors
    levels.clear()
    with pytest.raises(ValueError, match="a corrupt entry"):  # JAX turns this into its own Python warning
        quiet("broken", devices=1)
    assert levels == [3, 1]
    # a level the user chose stands: nothing is changed
    for env, value in (("TF_CPP_MIN_LOG_LEVEL", "0"), ("TF_CPP_MIN_LOG_LEVEL", "2")):
        levels.clear()
        monkeypatch.setenv(env, value)
        assert quiet("key", devices=1) == ("executable", 1)
        assert levels == [] and inside[-1] == []
    assert _jax_cache.user_chose_xla_logging({"TF_CPP_MIN_LOG_LEVEL": "0"})
    assert not _jax_cache.user_chose_xla_logging({"TF_CPP_MIN_LOG_LEVEL": "1"})


_COMPILE_ONE = """
import jax, jax.numpy as jnp
import kamino
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # keep even this small program
f = jax.jit(lambda x: jnp.sin(x) @ x.T + 1.0)
print(float(f(jnp.ones((4, 4))).sum()))
"""


def _compile_one(cache: Path, **env: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k not in ("TF_CPP_MIN_LOG_LEVEL", "JAX_LOGGING_LEVEL")}
    environ.update({_jax_cache.ENV: str(cache), **env})
    return subprocess.run([sys.executable, "-c", _COMPILE_ONE], capture_output=True, text=True, env=environ,
                          timeout=300, check=True)


def test_a_warm_process_prints_no_xla_log_lines(tmp_path):
    cache = tmp_path / "jax"
    cold = _compile_one(cache)
    assert any(cache.iterdir()), "the first process writes its executable"
    warm = _compile_one(cache)
    assert warm.stdout == cold.stdout
    xla_line = re.compile(r"^[IWEF]\d{4} .*\.cc:\d+\]", re.M)  # absl's format: W1128 21:50:50.366 ... file.cc:642]
    assert not xla_line.search(warm.stderr), warm.stderr  # no pjrt_executable.cc / cpu_aot_loader.cc lines
    # the same load with the user's own log level shows XLA's lines: the entry is loaded, and its lines are there
    # to be hidden
    chosen = _compile_one(cache, TF_CPP_MIN_LOG_LEVEL="0")
    assert "pjrt_executable.cc" in chosen.stderr and "Assume version compatibility" in chosen.stderr, chosen.stderr
